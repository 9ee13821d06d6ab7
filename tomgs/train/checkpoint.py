"""Checkpoints of a fit, and the signals that stop one.

A checkpoint is tensors and plain data only (dicts, lists, str, int, float, bool, None), written
with torch.save through `tomgs.outputs.atomic_file` (a private temporary in the same folder,
fsync'd, renamed over the last one: a crash leaves the previous complete checkpoint) and read with
`torch.load(weights_only=True)`, which builds no object but those: a file that holds anything else
(a pickled class, a `__reduce__` payload) is refused with an InputError before any of it runs.
After loading, its layout is checked (`check_state`) before a tensor of it is used.

    format, version   "tomgs-checkpoint", 1
    iteration, elapsed, extent       steps done, training seconds so far, scene size
    config            TrainConfig's fields as a dict (rebuilt with `config_from`)
    frames            [V, H, W]: the training views and their size
    params            {name: float tensor [N, ...]} (tomgs.model.PARAM_NAMES), sh_degree
    optimizer         the optimiser's state_dict (Adam's layout, moments [N, ...])
    sampler           {psnr: float64 [V] (running), latest: float64 [V] (each frame's last; absent before it),
                      generator: uint8 tensor, pending: [[frame, PSNR], ...] the steps' measurements it has
                      not heard yet (absent in checkpoints before it: none)}
    densifier         {grad_sum: [N], seen: [N], capped: bool, generator: uint8 tensor, changed_at: int,
                      stopped: bool, densified_at: int (the last two absent before growth could stop),
                      limit: int (absent before growth in stages: the cap)}
    sparsifier        tomgs.train.sparsify.Sparsifier's state: {taken: int, share: float, measured: [[count,
                      PSNR], ...], priced: [[count, proposed, PSNR, PSNR without them, taken], ...],
                      stopped: str, seconds: float (the rounds' cost; absent before it: 0)} (absent in
                      checkpoints before it: no round yet; `grown`, in those
                      before growth in stages, is not read)
    growth            tomgs.train.growth.Growth's state: {limit: int, stages: [[count, PSNR, worth], ...],
                      full_since: float or None, heard: [PSNR, ...], stopped: str} (absent before it:
                      grown as far as the densifier's limit)
    history, notes    the CSV rows (dicts of numbers and "") and the fit's notes (str); rows of a
                      checkpoint written before clip_frames was logged get it on reading (their clip
                      PSNRs covered every frame), and scene_bytes "" (not logged then)
    clip              what identifies the clip for `fit(resume=True)` (tomgs.train.pipeline fills it)

Signals: `StopSignals` turns SIGINT, SIGTERM and SIGHUP into a request that the training loop reads
at a step boundary, where the parameters, the optimiser and the densifier agree; the loop saves and
raises `FitInterrupted`. A second signal, or one outside the loop (`immediate=True`: decoding,
poses, writing the scene), raises `FitInterrupted` at once; the checkpoint on disk is then the last
complete one.

A checkpoint that cannot be written (a full disk) stops nothing: `CheckpointWriter.failed` holds the
OSError, the trainer notes it and goes on, and the last complete checkpoint stays the one to resume.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import re
import signal
import threading
import warnings
from pathlib import Path
from typing import Callable, NoReturn

import torch

from tomgs.errors import InputError
from tomgs.interrupts import STOP_SIGNALS, deferrable
from tomgs.model import PARAM_NAMES
from tomgs.outputs import atomic_file

FORMAT = "tomgs-checkpoint"
VERSION = 1
# a history row; clip_frames: the frames its clip_psnr covers ("" without one)
# scene_bytes: the scene file's bytes for the Gaussians of the row (tomgs.io.scene.vertex_bytes)
LOG_FIELDS = ("iteration", "wall_s", "train_psnr", "clip_psnr", "clip_frames", "gaussians", "scene_bytes",
              "memory_mb")
ADDED_LOG_FIELDS = ("clip_frames", "scene_bytes")  # absent from the rows of older checkpoints
START_OVER = "pass --overwrite (-y) to start the fit over (Python: overwrite=True)"


class FitInterrupted(KeyboardInterrupt):
    """A fit stopped by SIGINT (Ctrl-C) or SIGTERM. `checkpoint`: the checkpoint that a resume
    continues from (saved at the step the fit reached, or the last one before it), or None when there
    is none (stopped before training began); `signum`: the signal; `iteration`: the step saved, or
    None. `exit_code` is the shell's convention, 128 + signum."""

    def __init__(self, checkpoint: Path | None, signum: int = signal.SIGINT, iteration: int | None = None,
                 unsaved: str | None = None):
        self.checkpoint = None if checkpoint is None else Path(checkpoint)
        self.signum = int(signum)
        self.iteration = iteration
        self.unsaved = unsaved  # why the step reached could not be saved (the checkpoint kept is an older one)
        super().__init__(self.message())

    @property
    def exit_code(self) -> int:
        return 128 + self.signum

    def message(self) -> str:
        try:
            name = signal.Signals(self.signum).name
        except ValueError:
            name = f"signal {self.signum}"
        lost = f"; the step reached could not be saved ({self.unsaved})" if self.unsaved else ""
        if self.checkpoint is None:
            return f"interrupted ({name}) before the first checkpoint{lost}: nothing to resume; run the fit again"
        at = f" (iteration {self.iteration})" if self.iteration is not None else ""
        kept = "the last complete checkpoint" if self.unsaved else "checkpoint"
        return f"interrupted ({name}){lost}: {kept}{at} at {self.checkpoint}; continue with --resume"

    def __str__(self) -> str:
        return self.message()


class StopSignals:
    """Context manager: SIGINT, SIGTERM and SIGHUP, while it is active, set `signum` (the loop stops at its
    next step boundary) instead of killing the process or raising in the middle of a step. A second
    signal raises FitInterrupted(`checkpoint`) at once, and so does the first with `immediate=True`.
    `checkpoint`: the last complete checkpoint, kept up to date by its user. Installs nothing outside
    the main thread (signals are delivered there only) nor for a signal that is ignored (a
    background job's SIGINT); the previous handlers are restored on exit."""

    SIGNALS = STOP_SIGNALS

    def __init__(self, immediate: bool = False, checkpoint: Path | None = None):
        self.immediate = immediate
        self.checkpoint = checkpoint
        self.signum: int | None = None
        self._previous: dict[int, object] = {}

    def request(self, signum: int = signal.SIGINT) -> None:
        """Ask the loop to stop at its next step boundary (what a signal does)."""
        if self.signum is None:
            self.signum = int(signum)

    def _handle(self, signum, frame) -> None:
        if self.immediate or self.signum is not None:
            raise FitInterrupted(self.checkpoint() if callable(self.checkpoint) else self.checkpoint, signum)
        self.signum = int(signum)

    def __enter__(self) -> "StopSignals":
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                previous = signal.getsignal(sig)
                if previous is signal.SIG_IGN or previous is None:
                    continue  # ignored by whoever started us (or set from C): leave it so
                self._previous[sig] = previous
                signal.signal(sig, deferrable(self._handle))  # held back while a file is renamed into place
        return self

    def __exit__(self, *exc) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)
        self._previous.clear()


# -- writing and reading ---------------------------------------------------------------------------


def write_checkpoint(path, state: dict) -> Path:
    """Save `state` (check_state's layout) to `path` atomically and durably: the previous file at
    `path` is replaced only by a complete new one. RuntimeError, and nothing written, for a state
    that is torn or holds anything read_checkpoint would refuse."""
    check_state(state, path, ours=True)
    _check_plain(state, "state", path)
    with atomic_file(path, durable=True) as tmp, open(tmp, "wb") as f, _pinned_copies(state):
        try:
            torch.save(state, f)
        except RuntimeError as e:  # torch's zip writer wraps the file's own OSError (a full disk)
            cause = e.__cause__ or e.__context__
            if not isinstance(cause, OSError):
                raise
            raise cause from None
    return Path(path)


# torch.save copies a device's storages to the host one at a time. Into pageable memory the driver
# stages each copy on the CPU, and the training thread's launches waited meanwhile (5M Gaussians on
# the H100: 0.66-0.91 s of training lost per checkpoint); into pinned memory it is the copy engine's
# (0.02-0.2 s; 0.44 s the first time, which pins the blocks). torch keeps those blocks for reuse, as
# large as the largest storage: above this (SH colours of many Gaussians) the copies stay pageable
# rather than hold that much host memory for the rest of the process.
PINNED_STORAGE_MAX = 256 << 20


def _pinned_copies(state: dict):
    """A context in which torch.save copies `state`'s device storages to the host through pinned
    memory, when every storage is within PINNED_STORAGE_MAX: torch's own switch where it has one.
    The switch is the process's: a fit's torch.save calls are its checkpoints', one at a time."""
    try:
        from torch.utils.serialization import config
    except ImportError:
        return contextlib.nullcontext()
    largest = max((t.untyped_storage().nbytes() for t in _tensors(state) if t.is_cuda), default=0)
    if not hasattr(config.save, "use_pinned_memory_for_d2h") or not 0 < largest <= PINNED_STORAGE_MAX:
        return contextlib.nullcontext()
    return config.patch({"save.use_pinned_memory_for_d2h": True})


class CheckpointWriter:
    """Writes a fit's periodic checkpoints on a thread of its own, one at a time, so training goes on
    while a state goes to the host and the disk (a 5M-Gaussian state took 1.3-2.1 s on the H100, 5% of
    a GPU fit at one every 30 s). `submit(path, state)` first waits for the write before it; the
    state's tensors must be the writer's alone (`own_copies`), since training changes its own in place.
    `wait()` returns once nothing is being written and raises the first error a write met (a full
    disk); `done` is the last checkpoint written completely (None before one). As a context manager
    it waits on leaving. A write that fails with an OSError (a full disk) is not raised: it is kept in
    `failed` (the latest such) for the trainer to note, and `done` stays the last complete one."""

    def __init__(self):
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self.done: Path | None = None
        self.failed: OSError | None = None

    def submit(self, path, state: dict, ready=None) -> None:
        """Write `state` to `path` on the thread. `ready`: None, or a CUDA event recorded after the
        state's copies were queued; the thread's copies to the host then run on a stream of their own
        that waits for it, where on the training's stream every kernel queued behind them waited too
        (a 5M-Gaussian camel fit: the clip PSNR beside the write 0.8 s instead of 0.15)."""
        self.wait()

        def write():
            try:
                if ready is None:
                    self.done = write_checkpoint(path, state)
                    return
                side = torch.cuda.Stream(ready.device)
                side.wait_event(ready)
                with torch.cuda.stream(side):  # the thread's own current stream: training's is untouched
                    self.done = write_checkpoint(path, state)
            except OSError as e:  # training goes on; the trainer says so
                self.failed = e
            except BaseException as e:  # handed to the training thread by wait()
                self._error = e

        self._thread = threading.Thread(target=write, name="tomgs-checkpoint", daemon=True)
        self._thread.start()

    def wait(self, raise_error: bool = True) -> None:
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._error is not None and raise_error:
            error, self._error = self._error, None
            raise error

    def __enter__(self) -> "CheckpointWriter":
        return self

    def __exit__(self, kind, error, trace) -> None:
        """Wait for the write in progress; a write's error is raised unless another is on its way."""
        self.wait(raise_error=kind is None)


def own_copies(value):
    """`value` (a checkpoint state) with every tensor below it cloned where it lives: the writer's own."""
    if isinstance(value, torch.Tensor):
        return value.detach().clone()
    if isinstance(value, dict):
        return {k: own_copies(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(own_copies(v) for v in value)
    return value


def state_bytes(value) -> int:
    """Bytes of the tensors below `value`."""
    return sum(t.numel() * t.element_size() for t in _tensors(value))


def _tensors(value):
    """Every tensor below `value` (a checkpoint state)."""
    if isinstance(value, torch.Tensor):
        yield value
    elif isinstance(value, dict):
        for v in value.values():
            yield from _tensors(v)
    elif isinstance(value, (list, tuple)):
        for v in value:
            yield from _tensors(v)


def _check_plain(value, where: str, path) -> None:
    """Only tensors and plain data below `value` (a numpy scalar would make the file unreadable with
    weights_only)."""
    if value is None or type(value) in (str, int, float, bool) or type(value) is torch.Tensor:
        return
    if type(value) in (list, tuple):
        for i, item in enumerate(value):
            _check_plain(item, f"{where}[{i}]", path)
    elif type(value) is dict:
        for key, item in value.items():
            if type(key) not in (str, int):
                raise RuntimeError(f"refusing to write checkpoint {path}: key {key!r} in {where}")
            _check_plain(item, f"{where}[{key!r}]", path)
    else:
        raise RuntimeError(f"refusing to write checkpoint {path}: {where} is a {type(value).__name__}, not plain data")


def read_checkpoint(path) -> dict:
    """The checked state of the checkpoint at `path`; InputError for a file that is missing, damaged,
    holds anything but tensors and plain data (nothing in it runs), or is not laid out as tomgs
    writes it."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no checkpoint to resume from; run without --resume")
    try:
        with warnings.catch_warnings():  # torch's notes on foreign pickle protocols: the refusal says enough
            warnings.simplefilter("ignore")
            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - every way a foreign or damaged file fails to load
        raise InputError(f"{path} is not a checkpoint tomgs can read ({_load_failure(e)}); nothing in it was run. "
                         f"Delete it, or {START_OVER}") from None
    _check_storages(state, path)
    check_state(state, path)
    for row in state["history"]:  # an older checkpoint's rows: every clip PSNR covered all the views
        row.setdefault("clip_frames", state["frames"][0] if row["clip_psnr"] != "" else "")
        row.setdefault("scene_bytes", "")  # not logged then
    return state


def _check_storages(state, path) -> None:
    """InputError for a tensor its stored bytes do not hold: a view that repeats its storage (a stride
    of 0 declaring 200M rows over one). Such a tensor costs nothing to load, and the first copy of it
    allocates what it declares. (torch.load itself refuses a view that reaches past its storage.)"""
    for t in _tensors(state):
        bytes_held = t.untyped_storage().nbytes()
        if t.numel() * t.element_size() > bytes_held:
            raise _bad(path, f"a tensor of shape {tuple(t.shape)} over {bytes_held:,} stored bytes")


def _load_failure(error: Exception) -> str:
    """Why torch.load(weights_only=True) refused a file, in one short clause."""
    text = str(error)
    found = re.search(r"unsupported GLOBAL ([\w.]+)|Unsupported global: GLOBAL ([\w.]+)", text)
    if found:
        name = found.group(1) or found.group(2)
        return (f"it asks to build the Python object {name}; a checkpoint holds only tensors and plain data, and "
                f"tomgs loads nothing else")
    if "Weights only load failed" in text:
        detail = re.search(r"WeightsUnpickler error: \s*(.+)", text)
        return "damaged, or not a checkpoint" + (f": {detail.group(1).strip()[:100]}" if detail else "")
    first = text.strip().split(". ")[0].splitlines()[0] if text.strip() else type(error).__name__
    return f"damaged, or not a checkpoint: {first[:160]}"


def _bad(path, what: str) -> InputError:
    return InputError(f"{path} is not a tomgs checkpoint of this version ({what}); delete it, or {START_OVER}")


def check_state(state, path="<checkpoint>", ours: bool = False) -> None:
    """Check the layout of a checkpoint's state before anything of it is used: InputError naming
    `path` otherwise (a RuntimeError when `ours`: the trainer about to write a torn state). The parts
    are checked in the order they are listed here, so the first fault found is the one named."""
    def fail(what):
        if ours:
            raise RuntimeError(f"refusing to write checkpoint {path}: {what}")
        raise _bad(path, what)

    _check_header(state, path, fail)
    rows = _check_params(state["params"], fail)
    _check_optimizer(state["optimizer"], state["params"], rows, fail)
    _check_sampler(state["sampler"], state["frames"][0], fail)
    _check_densifier(state["densifier"], rows, fail)
    _check_growth(state.get("growth", dict(limit=1, stages=[], full_since=None, heard=[], stopped="")), fail)
    _check_sparsifier(state.get("sparsifier", dict(taken=0, share=0.5, measured=[], priced=[], stopped="",
                                                   grown=None)), fail)


# check_state's parts: each calls `fail(what)` (which raises) at the first fault it finds


def _check_header(state, path, fail: Callable[[str], NoReturn]) -> None:
    """The format and version, every top-level key present with its type, the counters, the frames
    ([views, height, width]), the settings (config_from), the notes and the history rows."""
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        fail(f"no \"format\": \"{FORMAT}\"")
    if state.get("version") != VERSION:
        fail(f"version {state.get('version')!r}, this tomgs reads {VERSION}")
    for key, kinds in dict(iteration=int, elapsed=(int, float), extent=(int, float), sh_degree=int, config=dict,
                           params=dict, optimizer=dict, sampler=dict, densifier=dict, history=list, notes=list,
                           clip=dict, frames=list).items():
        if not isinstance(state.get(key), kinds) or isinstance(state.get(key), bool):
            fail(f"{key!r} missing or not {kinds}")
    if state["iteration"] < 0 or not math.isfinite(state["elapsed"]) or state["elapsed"] < 0:
        fail("negative iteration or elapsed time")
    if not (math.isfinite(state["extent"]) and state["extent"] > 0):
        fail("scene extent not a positive number")
    if not 0 <= state["sh_degree"] <= 3:
        fail(f"sh_degree {state['sh_degree']}")
    frames = state["frames"]
    if len(frames) != 3 or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in frames):
        fail("'frames' is not [views, height, width]")
    config_from(state["config"], path)  # unknown or mistyped settings
    if not all(isinstance(n, str) for n in state["notes"]):
        fail("notes that are not text")
    for row in state["history"]:
        if not isinstance(row, dict) or not set(LOG_FIELDS) - set(ADDED_LOG_FIELDS) <= set(row) <= set(LOG_FIELDS) \
                or not all(isinstance(v, (int, float, str)) for v in row.values()):
            fail(f"history rows are not {', '.join(LOG_FIELDS)}")


def _check_params(params: dict, fail: Callable[[str], NoReturn]) -> int:
    """The Gaussians' rows N: `params` must be the float tensors PARAM_NAMES, each [N, ...]."""
    if set(params) != set(PARAM_NAMES) or not all(torch.is_tensor(v) and v.is_floating_point() for v in params.values()):
        fail(f"params are not the float tensors {', '.join(PARAM_NAMES)}")
    rows = {name: (v.shape[0] if v.dim() else -1) for name, v in params.items()}
    n = rows["means"]
    if len(set(rows.values())) != 1 or n < 0:
        fail(f"parameters of different lengths {sorted(set(rows.values()))}")
    return n


def _check_optimizer(optimizer: dict, params: dict, n: int, fail: Callable[[str], NoReturn]) -> None:
    """Adam's state_dict: one named group a parameter, and moments [N, ...] shaped as their parameter
    (n: the rows, for the message)."""
    groups, moments = optimizer.get("param_groups"), optimizer.get("state")
    if not isinstance(groups, list) or not isinstance(moments, dict) or len(groups) != len(PARAM_NAMES):
        fail("optimizer state of another layout")
    ids = {}
    for group in groups:
        if not isinstance(group, dict) or group.get("name") not in params or not isinstance(group.get("params"), list) \
                or len(group["params"]) != 1:
            fail("optimizer groups of another layout")
        ids[group["params"][0]] = group["name"]
    for index, entry in moments.items():
        if index not in ids or not isinstance(entry, dict):
            fail("optimizer moments of unknown parameters")
        shape = params[ids[index]].shape
        for key in ("exp_avg", "exp_avg_sq"):
            if not torch.is_tensor(entry.get(key)) or entry[key].shape != shape:
                fail(f"Adam moments of {ids[index]} ({key}) do not match its {n} rows")


def _check_sampler(sampler: dict, views: int, fail: Callable[[str], NoReturn]) -> None:
    """The frame sampler's PSNRs [views] (running, and each frame's latest when present), its
    generator, and its pending [frame, PSNR] pairs, of frames below `views`."""
    if not torch.is_tensor(sampler.get("psnr")) or tuple(sampler["psnr"].shape) != (views,) \
            or not torch.is_tensor(sampler.get("generator")) or ("latest" in sampler and (
                not torch.is_tensor(sampler["latest"]) or tuple(sampler["latest"].shape) != (views,))):
        fail("sampler state does not match the frames")
    pending = sampler.get("pending", [])
    if not isinstance(pending, list) or not all(
            isinstance(p, list) and len(p) == 2 and type(p[0]) is int and 0 <= p[0] < views
            and type(p[1]) is float for p in pending):
        fail("sampler's pending measurements are not [frame, PSNR] pairs of its frames")


def _check_densifier(densifier: dict, n: int, fail: Callable[[str], NoReturn]) -> None:
    """The densifier's statistics [n] (grad_sum, seen) and its flags, counters, generator and limit
    (the keys added later may be absent)."""
    for key in ("grad_sum", "seen"):
        if not torch.is_tensor(densifier.get(key)) or tuple(densifier[key].shape) != (n,):
            fail(f"densifier statistics ({key}) do not match the {n} rows")
    if not isinstance(densifier.get("capped"), bool) or not torch.is_tensor(densifier.get("generator")) \
            or type(densifier.get("changed_at", 0)) is not int or type(densifier.get("stopped", False)) is not bool \
            or type(densifier.get("densified_at", 0)) is not int or not _count(densifier.get("limit", 1)):
        fail("densifier state of another layout")


def _check_growth(growth, fail: Callable[[str], NoReturn]) -> None:
    """tomgs.train.growth.Growth's state: a limit, [count, PSNR, worth] stages, the PSNRs heard, when
    it was full (a float or None) and why it stopped."""
    if not isinstance(growth, dict) or not _count(growth.get("limit")) or not isinstance(growth.get("stopped"), str) \
            or not isinstance(growth.get("stages"), list) or not isinstance(growth.get("heard"), list) \
            or not all(isinstance(s, list) and len(s) == 3 and type(s[0]) is int and type(s[1]) is float
                       and type(s[2]) is float for s in growth["stages"]) \
            or not all(type(p) is float for p in growth["heard"]) \
            or not (growth.get("full_since") is None or type(growth["full_since"]) is float):
        fail("growth state of another layout")


def _check_sparsifier(sparsifier, fail: Callable[[str], NoReturn]) -> None:
    """tomgs.train.sparsify.Sparsifier's state: counts, its share, the [count, PSNR] measured, the
    rounds priced ([count, proposed, PSNR, PSNR without them, taken]), why it stopped, its seconds."""
    if not isinstance(sparsifier, dict) or type(sparsifier.get("taken")) is not int \
            or type(sparsifier.get("share")) is not float or not isinstance(sparsifier.get("stopped"), str) \
            or not isinstance(sparsifier.get("measured"), list) or not isinstance(sparsifier.get("priced"), list) \
            or not all(_count_and_psnr(m) for m in sparsifier["measured"]) \
            or not all(isinstance(p, list) and len(p) == 5 and _count_and_psnr(p[:3:2]) and type(p[1]) is int
                       and type(p[3]) is float and type(p[4]) is bool for p in sparsifier["priced"]) \
            or not (sparsifier.get("grown") is None or _count_and_psnr(sparsifier["grown"])) \
            or type(sparsifier.get("seconds", 0.0)) is not float:
        fail("sparsifier state of another layout")


def _count(value) -> bool:
    """Whether `value` is a count of Gaussians: a positive int."""
    return type(value) is int and value > 0


def _count_and_psnr(pair) -> bool:
    """Whether `pair` is [count, PSNR]: an int and a float."""
    return isinstance(pair, list) and len(pair) == 2 and type(pair[0]) is int and type(pair[1]) is float


def config_from(values: dict, path="<checkpoint>"):
    """TrainConfig from a checkpoint's plain dict; InputError for unknown or mistyped settings."""
    from tomgs.train.config import TrainConfig

    fields = {f.name: f for f in dataclasses.fields(TrainConfig)}
    unknown = set(values) - set(fields)
    if unknown:
        raise _bad(path, f"unknown settings {', '.join(sorted(map(str, unknown)))}")
    for name, value in values.items():
        if not isinstance(value, (int, float, str, bool, type(None))):
            raise _bad(path, f"setting {name} of type {type(value).__name__}")
    try:
        return TrainConfig(**values)
    except ValueError as e:  # a value TrainConfig refuses (init_depth)
        raise _bad(path, str(e)) from None


def check_same_settings(saved: dict, config, where) -> None:
    """InputError unless `config` keeps the settings a checkpoint's Gaussians depend on (SH degree,
    temporal or static), naming the option; `saved` is the checkpoint's config dict."""
    fitted = config_from(saved, where)
    for name, option in (("sh_degree", "--sh-degree"), ("temporal", "--static")):
        if getattr(fitted, name) != getattr(config, name):
            raise InputError(f"{where} was fitted with {name}={getattr(fitted, name)!r}, this run asks for "
                             f"{getattr(config, name)!r}: resume with the same {option}, or {START_OVER}")


def config_to_dict(config) -> dict:
    """TrainConfig's fields as plain Python values (numpy scalars given as settings become numbers)."""
    return {k: (v.item() if hasattr(v, "item") and not isinstance(v, (str, bytes)) else v)
            for k, v in dataclasses.asdict(config).items()}


__all__ = ["CheckpointWriter", "FitInterrupted", "StopSignals", "check_same_settings", "check_state",
           "config_from", "config_to_dict", "read_checkpoint", "own_copies", "state_bytes", "write_checkpoint"]
