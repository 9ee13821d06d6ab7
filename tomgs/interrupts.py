"""The signals that stop a command, as an exception every exit path sees.

By default SIGTERM and SIGHUP end a process at once: no `finally` runs, and a half-written
temporary stays where it was. While `raising()` is active (the CLI runs every command inside it)
SIGINT, SIGTERM and SIGHUP raise `Interrupted` in the main thread instead, so writers release their
files and remove their temporaries on the way out, and the command exits with the shell's
128 + signal number.

`held()` keeps signals back over a few lines that must not be cut in two (a temporary made and
noted, a file renamed into place, a clean-up): a signal that arrives meanwhile is delivered when
the outermost `held()` ends. Handlers installed elsewhere take part through `deferrable`.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


class Interrupted(KeyboardInterrupt):
    """A command stopped by a signal; `signum` is the signal, `exit_code` the shell's 128 + signum."""

    def __init__(self, signum: int = signal.SIGINT):
        self.signum = int(signum)
        super().__init__(f"interrupted ({signal_name(self.signum)})")

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


def signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


_state = {"depth": 0, "pending": None}  # held() nesting in the main thread; a (handler, signum, frame) kept back


def deferrable(handler: Callable) -> Callable:
    """`handler` (a signal handler) run at once, or, inside `held()`, when the outermost one ends."""
    def run(signum, frame):
        if _state["depth"] > 0:
            if _state["pending"] is None:
                _state["pending"] = (handler, signum, frame)
            return
        handler(signum, frame)
    return run


@contextmanager
def held() -> Iterator[None]:
    """Signals (through `deferrable` handlers) wait until this block ends; only the main thread,
    where Python runs signal handlers, holds them (elsewhere this does nothing)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _state["depth"] += 1
    try:
        yield
    finally:
        _state["depth"] -= 1
        if _state["depth"] == 0 and _state["pending"] is not None:
            handler, signum, frame = _state["pending"]
            _state["pending"] = None
            handler(signum, frame)


def _raise(signum, frame) -> None:
    raise Interrupted(signum)


@contextmanager
def raising() -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP raise Interrupted while the block runs (main thread only; a
    signal its starter set to be ignored stays ignored, as a background job's SIGINT); the previous
    handlers are restored after."""
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for sig in STOP_SIGNALS:
            before = signal.getsignal(sig)
            if before is signal.SIG_IGN or before is None:
                continue
            previous[sig] = before
            signal.signal(sig, deferrable(_raise))
    try:
        yield
    finally:
        for sig, before in previous.items():
            signal.signal(sig, before)


def ignore_stop_signals() -> None:
    """Ignore SIGINT, SIGTERM and SIGHUP from now on (main thread): a process already on its way out
    after one of them, whose handlers `raising()` restores as it leaves."""
    if threading.current_thread() is threading.main_thread():
        for sig in STOP_SIGNALS:
            signal.signal(sig, signal.SIG_IGN)


__all__ = ["STOP_SIGNALS", "Interrupted", "deferrable", "held", "ignore_stop_signals", "raising", "signal_name"]
