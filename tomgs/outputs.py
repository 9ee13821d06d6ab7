"""Writing outputs safely: one atomic write for every file tomgs writes, and the checks that run
before any work so that a long run never fails at its end or replaces what the user did not ask
to replace.

    atomic_file(path)      a context manager: yields a private temporary path in the target's
                           folder (created exclusively, never through an existing link); on
                           success it is renamed over `path`, on any exit path it is removed
    check_file_output(...) an output file: its folder exists and is writable, it is not a folder,
                           and an existing file is replaced only with overwrite=True
    check_folder_output(...) an output folder of numbered frames: not a file, writable, and an
                           existing non-empty folder is written into only with overwrite=True
    check_distinct(...)    no output of a command is another of its outputs or one of its inputs
    output_lock(path)      one writer of an output at a time: an advisory lock beside it, shared by
                           every file of its stem (a fit's log, plot and checkpoint)
    check_fit_outputs(...) the files a fit writes (fit_output_paths), its checkpoint's rule

Temporary names are '.NAME.PID.XXXXXXXX.tmp' beside the target: a file, or a folder a writer
stages in (`temporary`). This process notes its own until they are published or discarded, so
`remove_temporaries` removes what an exception or signal cut short; `remove_stale_temporaries`
removes those whose process is gone. A write that fails (a full disk) is an OSError naming the
target and what was kept (`write_failed`), never the temporary's name.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from tomgs.errors import InputError
from tomgs.interrupts import held

TMP_SUFFIX = ".tmp"
LOCK_SUFFIX = ".lock"
OVERWRITE_HINT = "pass --overwrite (-y) to replace it (Python: overwrite=True), or choose another path"

_live: dict[Path, bool] = {}  # this process's temporaries not yet published or discarded: path -> is a folder


def _default_mode(is_dir: bool) -> int:
    umask = os.umask(0)
    os.umask(umask)
    return (0o777 if is_dir else 0o666) & ~umask


def temporary(path, folder: bool = False) -> Path:
    """A fresh private temporary file (or folder) beside `path`, '.NAME.PID.XXXXXXXX.tmp', created
    exclusively and noted as this process's until `publish` or `discard`. Stale temporaries of
    `path` (their process gone) are removed first."""
    path = Path(path)
    parent = _existing_folder(path)
    remove_stale_temporaries(path)
    prefix = f".{path.name}.{os.getpid()}."
    try:
        with held():  # made and noted together: a signal cannot leave one unnoted
            if folder:
                tmp = Path(tempfile.mkdtemp(prefix=prefix, suffix=TMP_SUFFIX, dir=parent))
            else:
                fd, name = tempfile.mkstemp(prefix=prefix, suffix=TMP_SUFFIX, dir=parent)
                os.close(fd)
                tmp = Path(name)
            _live[tmp] = folder
    except OSError as e:
        raise InputError(f"{path}: cannot write in {parent} ({e.strerror}); choose another output path") from None
    return tmp


def discard(tmp) -> None:
    """Remove the temporary `tmp` (a file or a staging folder) if it is there; signals wait meanwhile."""
    tmp = Path(tmp)
    with held():
        if tmp.is_dir() and not tmp.is_symlink():
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            try:
                tmp.unlink(missing_ok=True)
            except OSError:
                pass  # its folder went away: nothing of ours is left there
        _live.pop(tmp, None)


def remove_temporaries() -> list[Path]:
    """Remove every temporary of this process not yet published or discarded (what an exception or a
    signal cut short); the CLI calls it on every exit path. Returns what was removed."""
    removed = [tmp for tmp in list(_live) if tmp.exists() or tmp.is_symlink()]
    for tmp in list(_live):
        discard(tmp)
    return removed


def publish(tmp, path) -> Path:
    """chmod `tmp` to the process's default mode for a new file or folder (mkstemp/mkdtemp made it
    private), then rename it over `path` (atomic within one file system)."""
    with held():  # renamed and no longer noted as a temporary, together
        os.chmod(tmp, _default_mode(os.path.isdir(tmp)))
        os.replace(tmp, path)
        _live.pop(Path(tmp), None)
    return Path(path)


def write_failed(error: OSError, path, kept: str | None = None) -> OSError:
    """`error`, met while writing `path` (under a temporary name), as an OSError that names `path` and
    what is kept: `kept`, or by default the existing file or that nothing was written."""
    path = Path(path)
    if kept is None:
        kept = f"the existing {path.name} is kept" if path.exists() else "nothing was written"
    return OSError(error.errno, f"{error.strerror or error}; {kept}", str(path))


def _ours(error: OSError, tmp: Path) -> bool:
    """Whether `error` is about writing `tmp` (no file named, or the temporary itself)."""
    return error.filename is None or Path(error.filename) == tmp


@contextmanager
def atomic_file(path, durable: bool = False) -> Iterator[Path]:
    """Yield a fresh temporary path beside `path`; write it, and on a normal exit it replaces
    `path` in one rename (when `durable`: the file fsync'd before, its folder after). On an
    exception (KeyboardInterrupt included) the temporary file is removed and `path` is left as it
    was; an OSError writing it (a full disk) is raised as `write_failed` says."""
    path = Path(path)
    tmp = temporary(path)
    try:
        yield tmp
        if durable:
            with open(tmp, "rb") as f:
                os.fsync(f.fileno())
        publish(tmp, path)
        if durable:  # the rename itself survives a power cut only once the folder is on disk
            _fsync_folder(path.parent)
    except OSError as e:
        discard(tmp)
        if _ours(e, tmp):
            raise write_failed(e, path) from None
        raise
    except BaseException:
        discard(tmp)
        raise


def _fsync_folder(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return  # a platform without folder descriptors (Windows): the file itself was synced
    try:
        os.fsync(fd)
    except OSError:
        pass  # some file systems refuse fsync on folders; nothing more can be done there
    finally:
        os.close(fd)


def write_bytes(path, data: bytes, durable: bool = False) -> Path:
    """Write `data` to `path` atomically (see atomic_file)."""
    with atomic_file(path, durable=durable) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text(path, text: str, durable: bool = False) -> Path:
    return write_bytes(path, text.encode("utf-8"), durable=durable)


def json_text(value) -> str:
    """`value` as indented JSON; non-finite floats (JSON has none: a perfect frame's PSNR is inf)
    become null, recursively."""
    import json
    import math

    def finite(v):
        if isinstance(v, float):
            return v if math.isfinite(v) else None
        if isinstance(v, dict):
            return {k: finite(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [finite(x) for x in v]
        return v
    return json.dumps(finite(value), indent=1)


def _existing_folder(path: Path) -> Path:
    folder = path.parent
    if not folder.exists():
        raise InputError(f"{path}: folder {folder} does not exist; create it or choose another output path")
    if not folder.is_dir():
        raise InputError(f"{path}: {folder} is a file, not a folder; choose another output path")
    return folder


def _probe_writable(folder: Path, path: Path) -> None:
    """Create and remove a temporary file in `folder`: the one test that also catches read-only
    mounts and immutable folders (which os.access misses when running as root)."""
    try:
        with held():
            fd, tmp = tempfile.mkstemp(prefix=".tomgs-probe.", suffix=TMP_SUFFIX, dir=folder)
            os.close(fd)
            os.unlink(tmp)
    except OSError as e:
        raise InputError(f"{path}: cannot write in {folder} ({e.strerror}); choose another output path") from None


def check_file_output(path, overwrite: bool = False, what: str = "output") -> Path:
    """`path` as a Path when a file can be written there now, else InputError saying how to
    proceed: its folder must exist and be writable, `path` must not be a folder, and an existing
    file is accepted only with `overwrite`."""
    path = Path(path)
    folder = _existing_folder(path)
    if path.is_dir():
        raise InputError(f"{path} is a folder; the {what} is a file: give a file name")
    if path.exists() or path.is_symlink():
        if not overwrite:
            raise InputError(f"{path} exists; {OVERWRITE_HINT}")
        if not path.is_file():
            raise InputError(f"{path} exists and is not a regular file; choose another output path")
    _probe_writable(folder, path)
    return path


def check_folder_output(path, owned, overwrite: bool = False) -> Path:
    """`path` as a Path when a folder of frames can be written there now. An existing folder must
    be empty, or `overwrite` given; even then only the files `owned(name)` says tomgs writes there
    are replaced or removed, and everything else is kept."""
    path = Path(path)
    _existing_folder(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{path} is a file; a folder of frames goes here: give a new folder name")
    if path.is_dir():
        entries = list(os.scandir(path))
        if entries and not overwrite:
            raise InputError(f"{path} is a folder that is not empty ({len(entries)} entries); pass --overwrite (-y) "
                             f"to replace its frames (other files are kept; Python: overwrite=True), or choose a "
                             f"new folder")
        _probe_writable(path, path)
    else:
        _probe_writable(path.parent, path)
    return path


def fit_output_paths(scene_path) -> dict[str, Path]:
    """What `tomgs.fit` writes for the scene `scene_path`: the scene, its log (.csv), its PSNR plot
    (.psnr.png) and, while it runs, its checkpoint (.ckpt), by those keys."""
    scene = Path(scene_path)
    stem = scene.with_suffix("")
    return dict(scene=scene, csv=Path(f"{stem}.csv"), plot=Path(f"{stem}.psnr.png"), checkpoint=Path(f"{stem}.ckpt"))


def check_fit_outputs(output, resume: bool = False, overwrite: bool = False) -> dict[str, Path]:
    """fit_output_paths(output) once every one can be written: InputError saying how to proceed
    otherwise. Without `overwrite` an existing scene, log or plot is refused; a checkpoint is
    expected with `resume` (and the log may exist then), and refused without it."""
    paths = fit_output_paths(output)
    if paths["scene"].suffix.lower() not in (".ply", ".tsog"):
        raise InputError(f"{output}: a scene is written as .ply (or .tsog, compressed); name the output like "
                         f"scene.ply or scene.tsog")
    check_file_output(paths["scene"], overwrite, "scene")
    check_file_output(paths["plot"], overwrite, "PSNR plot")
    checkpoint = paths["checkpoint"]
    if resume:
        if not checkpoint.is_file():
            raise InputError(f"{checkpoint}: no checkpoint to resume from; run without --resume")
        check_file_output(checkpoint, True, "checkpoint")
        check_file_output(paths["csv"], True, "log")
    else:
        if (checkpoint.exists() or checkpoint.is_symlink()) and not overwrite:
            raise InputError(f"{checkpoint} holds an interrupted fit of {paths['scene'].name}: pass --resume to "
                             f"continue it, or --overwrite (-y) to start over (Python: resume=True or "
                             f"overwrite=True)")
        check_file_output(checkpoint, overwrite, "checkpoint")
        check_file_output(paths["csv"], overwrite, "log")
    return paths


def check_png_path(path) -> Path:
    """The plot's path, checked before any work: a .png in an existing folder, else InputError."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise InputError(f"{path}: the plot is a PNG; give a path ending in .png")
    if not path.parent.exists():
        raise InputError(f"{path}: folder {path.parent} does not exist; create it or choose another path")
    return path


def _paths(value) -> list[str]:
    """A path, None, '-' (stdout) or a list of them -> the paths named."""
    values = value if isinstance(value, (list, tuple)) else [value]
    return [str(v) for v in values if v is not None and str(v) != "-"]


def _same(a: str, b: str) -> bool:
    """Whether paths `a` and `b` name one file: equal once resolved (links followed), or one file
    under two names (hard links)."""
    if Path(a).resolve() == Path(b).resolve():
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def existing_path(value) -> str | None:
    """`value` when it names an existing file or folder, else None: an argument that is a path or a
    name (`--poses auto`), as check_distinct's input."""
    if isinstance(value, (str, os.PathLike)) and str(value) and Path(value).exists():
        return str(value)
    return None


def check_distinct(outputs: dict, inputs: dict | None = None) -> None:
    """InputError, before any work, when an output is another output or an input of the same command,
    or an output folder holds an input (paths resolved, links followed). `outputs` and `inputs` map
    what the user calls each (an option, an argument, "the log") to a path, a list of paths, or None
    (not given; '-' is stdout)."""
    seen: list[tuple[str, str]] = []
    for label, value in outputs.items():
        for path in _paths(value):
            for other_label, other in seen:
                if _same(path, other):
                    named = "" if other == path else f" ({other})"  # a path named once, another way twice
                    raise InputError(f"{label} {path} is also {other_label}{named}: one would overwrite the "
                                     f"other; give each output its own path")
            seen.append((label, path))
    for in_label, value in (inputs or {}).items():
        for source in _paths(value):
            for label, path in seen:
                if _same(path, source):
                    where = "is"
                elif Path(source).resolve().is_relative_to(Path(path).resolve()):
                    where = "holds"  # a folder of frames written where an input lies
                else:
                    continue
                named = "" if source == path else f" {source}"
                raise InputError(f"{label} {path} {where} the input {in_label}{named}: writing it would "
                                 f"replace what this command reads; choose another output path")


_TEMPORARY = re.compile(r"\.(?P<name>.+)\.(?P<pid>\d+)\.[A-Za-z0-9_]+" + re.escape(TMP_SUFFIX))
_OLD_TEMPORARY_AGE = 60.0  # seconds: a temporary without a process id (older tomgs) is stale after this


def _process_gone(pid: int) -> bool:
    if pid == os.getpid():
        return False
    if os.name != "posix":
        return False  # no cheap probe that does not signal the process: left for the age rule
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:
        return False  # alive, another user's
    return False


def _staged_only(folder: Path) -> bool:
    """Whether `folder` holds only what a frames writer stages there (tomgs.io.writer): regular files
    named out.SUFFIX or NNNNN.png."""
    try:
        return all(entry.is_file(follow_symlinks=False) and re.fullmatch(r"out\.\w+|\d{5,}\.png", entry.name)
                   for entry in os.scandir(folder))
    except OSError:
        return False


def remove_stale_temporaries(path, older_than_s: float = _OLD_TEMPORARY_AGE) -> list[Path]:
    """Remove the temporaries of `path` ('.NAME.PID.*.tmp' beside it, files, and folders holding only
    staged frames or a staged video) whose process is gone; one without a process id only when older
    than `older_than_s`. Another writer's live ones and anything else are kept. Returns what was
    removed."""
    path = Path(path)
    removed = []
    if not path.parent.is_dir():
        return removed
    now = time.time()
    for tmp in path.parent.glob(f".{path.name}.*{TMP_SUFFIX}"):
        if tmp in _live:
            continue
        try:
            named = _TEMPORARY.fullmatch(tmp.name)
            if named is not None and named["name"] == path.name:
                stale = _process_gone(int(named["pid"]))
            else:
                stale = now - tmp.lstat().st_mtime > older_than_s
            if not stale or tmp.is_symlink():
                continue
            if tmp.is_file():
                tmp.unlink()
            elif tmp.is_dir() and _staged_only(tmp):
                shutil.rmtree(tmp)
            else:
                continue
            removed.append(tmp)
        except OSError:
            pass  # gone already, or not ours to remove
    return removed


def check_unlocked(path, what: str = "fit") -> None:
    """InputError at once when another process holds `path`'s lock (output_lock): the door's look before
    any work; the work takes the lock itself (a process that takes it in between is refused then)."""
    with output_lock(path, what):
        pass


@contextmanager
def output_lock(path, what: str = "fit") -> Iterator[None]:
    """Hold an advisory lock on output `path` and the files beside it that share its stem (a fit's
    log, plot and checkpoint: fit_output_paths), '.STEM.lock' whatever its extension, while the block
    runs, released and removed on every exit path (the system releases it when a killed process ends).
    InputError at once when another process holds it; an OSError naming `path` (`write_failed`) when
    the lock cannot be written (a full disk). POSIX only (elsewhere: no lock)."""
    try:
        import fcntl
    except ImportError:
        yield
        return
    path = Path(path)
    lock = path.parent / f".{path.with_suffix('').name}{LOCK_SUFFIX}"
    if not path.parent.is_dir():  # nothing can be written there: the output's own check says so
        yield
        return
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o644)
        except OSError as e:
            raise InputError(f"{path}: cannot make its lock {lock} ({e.strerror}); choose another output path") \
                from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder, _, name = os.read(fd, 4096).decode("utf-8", "replace").strip().partition(" ")
            os.close(fd)
            writing = "it now" if name in ("", path.name) else \
                f"{name} now, whose log, plot and checkpoint are this output's too"
            raise InputError(f"{path}: another tomgs {what} (process {holder or 'unknown'}) is writing {writing}; "
                             f"wait for it to end, or choose another output path") from None
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(lock, follow_symlinks=False))
        except OSError:
            same = False
        if same:
            break
        os.close(fd)  # its holder removed it as we opened it: lock the one at the path now
    try:
        try:
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()} {path.name}".encode())
        except OSError as e:  # a full disk: not even the id fits, nor will the output
            raise write_failed(e, path) from None
        yield
    finally:
        with held():
            try:
                os.unlink(lock)
            except OSError:
                pass
            os.close(fd)
