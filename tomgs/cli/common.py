"""What the commands of `tomgs` share: the one error decorator, the group's class (signals, temporaries),
the shared options, the verbosity (-q / -v) and its notes, progress bars and lines, JSON reports."""

from __future__ import annotations

import contextlib
import functools
import signal
import sys
import threading
import time

import click

import tomgs
from tomgs.errors import InputError, RenderError
from tomgs.cli.params import FOCAL, FPS, SIDE, Colour


class UsageError(click.ClickException):
    """A bad input: clear message, exit code 2, nothing written."""

    exit_code = 2


def user_errors(command):
    """Bad input found by the library (InputError, RenderError): exit 2 with its message. An OS
    error while reading or writing (disk full, a file removed under us, a file that ends early):
    exit 1 naming the file; so is running out of memory. Never a traceback."""
    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except (InputError, RenderError) as e:
            raise UsageError(str(e)) from None
        except (OSError, EOFError) as e:  # PyAV's errors are both FFmpegError and one of these
            where = f"{e.filename}: " if getattr(e, "filename", None) else ""
            raise click.ClickException(f"{where}{getattr(e, 'strerror', None) or e}") from None
        except MemoryError as e:
            raise click.ClickException(out_of_memory(e)) from None
        except RuntimeError as e:
            if "can't allocate memory" not in str(e):  # torch's host allocator
                raise
            raise click.ClickException(out_of_memory(e)) from None
    return wrapper


def out_of_memory(error: BaseException) -> str:
    """One line for an allocation that failed, naming the running command's options that give it less to hold."""
    detail = str(error).strip().splitlines()[-1][:160] if str(error).strip() else "the allocator refused"
    context = click.get_current_context(silent=True)
    has = {name for p in (context.command.params if context else ()) for name in getattr(p, "opts", ())}
    frames = [o for o in ("--frames", "--max-side") if o in has]
    return (f"out of memory ({detail}); give the command less to hold: fewer or smaller frames"
            + (f" ({', '.join(frames)})" if frames else "") + (", or a lower --cap" if "--cap" in has else ""))


class Group(click.Group):
    """The `tomgs` group. Every command runs with SIGINT, SIGTERM and SIGHUP raising an interrupt
    (tomgs.interrupts), so its writers release their files and remove their temporaries on the way
    out; an interrupted command says so in one line and exits 128 + the signal (130 for Ctrl-C,
    also while it imports). Whatever ends a command, none of its temporaries is left. A command's
    usage mistake (a missing option, an unknown one) is one line, as every other mistake is, naming
    where the help is, instead of click's usage block."""

    def invoke(self, ctx):
        from tomgs.interrupts import held, ignore_stop_signals, raising, signal_name
        from tomgs.outputs import remove_temporaries

        with raising():
            try:
                return super().invoke(ctx)
            except click.UsageError as e:
                where = e.ctx.command_path if e.ctx is not None else ctx.command_path
                raise UsageError(f"{e.format_message()} (see '{where} -h')") from None
            except KeyboardInterrupt as e:
                signum = getattr(e, "signum", signal.SIGINT)
                ignore_stop_signals()  # a second signal while this one is said and cleaned up: no traceback
                click.echo(f"\ninterrupted ({signal_name(signum)}): stopped, nothing half-written left", err=True)
                raise SystemExit(128 + signum) from None
            finally:
                with held():
                    remove_temporaries()


OUTPUT_HELP = "an .mp4/.avi/.mov/.mkv file, or a folder (no suffix) for PNG frames"


def clip_options(f):
    """--frames, --max-side, --masks and --focal, as `poses` and `fit` read a clip."""
    for option in reversed([
        click.option("--frames", default=None, help="frame range start:stop:step of the source, e.g. 0:80 or ::2"),
        click.option("--max-side", type=SIDE, default=None, help="resize frames so that max(W, H) <= N"),
        click.option("--masks", type=click.Path(path_type=str), default=None,
                     help="folder of masks, one per source frame, white on the moving object (left out of poses)"),
        click.option("--focal", type=FOCAL, default=None, help="focal length in pixels of the (resized) frames"),
    ]):
        f = option(f)
    return f


device_option = click.option("--device", default="auto", show_default=True, help="auto, cpu, cuda or cuda:N")
overwrite_option = click.option(
    "-y", "--overwrite", is_flag=True,
    help="replace existing outputs (in a folder of frames only its numbered PNGs; other files are kept)")


def render_options(f):
    """--frames, --device, --background, --fps and --overwrite, as `tomgs render` has them."""
    for option in reversed([
        click.option("--frames", default=None, help="frame range start:stop:step in the scene's frame numbers"),
        device_option,
        click.option("--background", type=Colour(), default=None,
                     help="r,g,b in [0, 1]; default: the scene's, else black"),
        click.option("--fps", type=FPS, default=None,
                     help="frame rate of a video output; default: the scene's, else 25"),
        overwrite_option,
    ]):
        f = option(f)
    return f


_VERBOSITY = {"level": 1}  # 0: -q, 1: default, 2: -v (set by the group for the command it runs)


def set_verbosity(quiet: bool, verbose: bool) -> None:
    """-q / -v given before the command (`tomgs -q render ...`)."""
    if quiet and verbose:
        raise UsageError("-q and -v contradict each other: give one")
    _VERBOSITY["level"] = 0 if quiet else 2 if verbose else 1


def say(text: str, level: int = 1) -> None:
    """A note on stderr, shown from verbosity `level` up."""
    if _VERBOSITY["level"] >= level:
        click.echo(text, err=True)


def json_option(what: str):
    return click.option("--json", "json_out", type=click.Path(path_type=str), default=None,
                        help=f"also write {what} as JSON to this file ('-' for stdout, then nothing else is printed)")


def write_json(json_out: str | None, value) -> None:
    """`value` as JSON to `json_out` ('-': stdout), non-finite floats as null."""
    from tomgs.outputs import json_text, write_text

    if json_out == "-":
        click.echo(json_text(value))
    elif json_out:
        write_text(json_out, json_text(value))


def selector_paths(selectors) -> list[str]:
    """The files and folders that `--select` selectors read (index:FILE, mask:FOLDER): a command's inputs."""
    return [rest.strip() for kind, _, rest in (str(s).partition(":") for s in selectors)
            if kind.strip().lower() in ("index", "mask") and rest.strip()]


def check_json(json_out: str | None, overwrite: bool) -> bool:
    """Check a --json file before any work; True when the JSON goes to stdout (print nothing else)."""
    from tomgs.outputs import check_file_output

    if json_out and json_out != "-":
        check_file_output(json_out, overwrite, what="JSON report")
    return json_out == "-"


SELECT_HELP = ("pick Gaussians (repeat to intersect): box:x0,y0,z0,x1,y1,z1 | sphere:x,y,z,r | time:t0,t1 (clip "
                "time 0..1) | index:FILE.txt | mask:FOLDER (world axes: x right, y down, z forward)")


OVER_HELP = ("a scene to render behind (e.g. a background from `fit --layer background`), with its own cameras "
              "at the same frames; the rendered scene is composited over it as `render --layer` does")


LINE_INTERVAL = 5.0  # seconds between progress lines where stderr is not a terminal (a log file, CI, `| tee`)


def _terminal() -> bool:
    return sys.stderr.isatty()


class ProgressLines:
    """Progress for a log, where a bar cannot redraw: a line when a phase starts and then every
    LINE_INTERVAL seconds from a thread, whatever the work is doing (a long step, a compilation):
    the command's time so far, the phase, how far it is, what it reported last and its ETA."""

    def __init__(self, interval: float = LINE_INTERVAL):
        self.state = None  # (label, phase start, fraction done, text)
        self.stopped = threading.Event()
        self.thread = threading.Thread(target=self._run, args=(interval,), name="tomgs-progress", daemon=True)
        self.thread.start()

    def update(self, label: str, fraction: float, text: str | None = None) -> None:
        now = time.monotonic()
        new = self.state is None or self.state[0] != label
        self.state = (label, now if new else self.state[1], min(max(fraction, 0.0), 1.0), text)
        if new:
            self._line()

    def close(self) -> None:
        self.stopped.set()
        self.thread.join()

    def _line(self) -> None:
        label, began, fraction, text = self.state
        now = time.monotonic()
        eta = ""
        if 0.02 <= fraction < 1.0:
            eta = f", ETA {_seconds((now - began) * (1 - fraction) / fraction)}"
        since = time.perf_counter() - tomgs.STARTED  # the command's time so far, as its budget counts it
        click.echo(f"[{_seconds(since):>7s}] {label.strip()} {fraction:.0%}"
                   + (f": {text}" if text else "") + eta, err=True)

    def _run(self, interval: float) -> None:
        while not self.stopped.wait(interval):
            if self.state is not None:
                self._line()


def _seconds(value: float) -> str:
    return f"{value:.0f} s" if value < 120 else f"{value / 60:.1f} min"


@contextlib.contextmanager
def progress_bar(length: int, label: str, **options):
    """A progress bar with rate and ETA on stderr (stdout carries results only), lines for a log
    where stderr is not a terminal (ProgressLines), none with -q; yields progress(done, item=None)."""
    if _VERBOSITY["level"] == 0:
        yield lambda done, item=None: None
        return
    if not _terminal():
        lines = ProgressLines()
        try:
            yield lambda done, item=None: lines.update(label, done / max(length, 1), f"{done}/{length}")
        finally:
            lines.close()
        return
    with click.progressbar(length=length, label=label, file=sys.stderr, show_eta=True, show_percent=True,
                           **options) as bar:
        yield lambda done, item=None: bar.update(done - bar.pos, item)


STEPS = 1000  # a phase bar's length: phases count frames, iterations or seconds, shown as a fraction
PHASE_LABELS = {"load": "loading", "read": "reading", "poses": "poses", "compile": "compiling", "init": "initialising",
                "train": "training", "save": "saving"}


@contextlib.contextmanager
def phase_bars(min_interval: float = 0.25):
    """One progress bar per phase on stderr, each with rate and ETA (lines for a log where stderr is
    not a terminal: ProgressLines; none with -q); yields update(phase, done, total, text=None): a
    new phase name ends the previous bar at 100% (it is done) and opens its own; redraws at most
    every `min_interval` seconds, so a caller may tick every step."""
    if _VERBOSITY["level"] == 0:
        yield lambda phase, done, total, text=None: None
        return
    if not _terminal():
        lines = ProgressLines()
        try:
            yield lambda phase, done, total, text=None: lines.update(
                PHASE_LABELS.get(phase, phase), done / total if total > 0 else 0.0, text)
        finally:
            lines.close()
        return
    state = dict(phase=None, bar=None, shown=0.0, text=None)

    def close(done: bool):
        if state["bar"] is not None:
            if done:  # the phase ended: its bar says so, wherever its estimate of the work had it
                state["bar"].update(STEPS - state["bar"].pos, state["text"])
            state["bar"].__exit__(None, None, None)
            state["bar"] = None

    def update(phase, done, total, text=None):
        now = time.monotonic()
        if phase != state["phase"]:
            close(done=True)
            label = f"{PHASE_LABELS.get(phase, phase):12s}"
            bar = click.progressbar(length=STEPS, label=label, file=sys.stderr, show_eta=True, show_percent=True,
                                    item_show_func=lambda item: item)
            state.update(phase=phase, bar=bar.__enter__(), shown=0.0)
        state["text"] = text
        bar = state["bar"]
        if done < total and now - state["shown"] < min_interval:
            return
        state["shown"] = now
        bar.update(round(STEPS * min(done / total, 1.0)) - bar.pos if total > 0 else 0, text)

    finished = False
    try:
        yield update
        finished = True
    finally:
        close(done=finished)


def render_planned(scene, gaussians, plan, fps, layers=()) -> None:
    """Run a planned render (tomgs.render.jobs) with a progress bar and print its report."""
    from tomgs.render.jobs import run_render

    with progress_bar(len(plan.positions), "render") as progress:
        report = run_render(plan, scene, gaussians, fps, layers, progress=progress)
    click.echo(report.summary())


scene_cameras_option = click.option(
    "--cameras", "cameras_path", type=click.Path(path_type=str), default=None,
    help="the clip's cameras (a cameras.json from `tomgs export --cameras-out` or `tomgs poses`), for a scene "
         "that another tool re-saved without them (SuperSplat, splat-transform); replaces the scene's own")


SCENE_SUFFIXES = (".ply", ".tsog")  # a PLY scene, or a compressed one (tomgs.io.tsog)


def is_scene_path(path: str) -> bool:
    return path.lower().endswith(SCENE_SUFFIXES)


def _set_verbosity(ctx, param, value) -> None:
    if not value:
        return
    if ctx.meta.setdefault("tomgs.verbosity", param.name) != param.name:
        raise UsageError("-q and -v contradict each other: give one")
    _VERBOSITY["level"] = 0 if param.name == "quiet" else 2


VERBOSE_COMMANDS = ("fit",)  # the commands that train: -v shows their log rows


def verbosity_options(group: click.Group) -> None:
    """-q after the command too (`tomgs render ... -q` as well as `tomgs -q render ...`), and -v
    after the commands that train (VERBOSE_COMMANDS)."""
    for name, command in group.commands.items():
        if isinstance(command, click.Group):
            verbosity_options(command)
            continue
        command.params.append(
            click.Option(["-q", "--quiet"], is_flag=True, expose_value=False, callback=_set_verbosity,
                         help="no progress bars or notes on stderr: results and errors only"))
        if name in VERBOSE_COMMANDS:
            command.params.append(
                click.Option(["-v", "--verbose"], is_flag=True, expose_value=False, callback=_set_verbosity,
                             help="also every training log row on stderr"))
