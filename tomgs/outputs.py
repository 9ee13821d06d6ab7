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
    check_fit_outputs(...) the files a fit writes (fit_output_paths), its checkpoint's rule

Temporary names start with '.' and end with '.tmp'; `remove_stale_temporaries` removes those a
killed process left behind.
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from tomgs.errors import InputError

TMP_SUFFIX = ".tmp"
OVERWRITE_HINT = "pass --overwrite (-y) to replace it (Python: overwrite=True), or choose another path"


def _default_mode(is_dir: bool) -> int:
    umask = os.umask(0)
    os.umask(umask)
    return (0o777 if is_dir else 0o666) & ~umask


def publish(tmp, path) -> Path:
    """chmod `tmp` to the process's default mode for a new file or folder (mkstemp/mkdtemp made it
    private), then rename it over `path` (atomic within one file system)."""
    os.chmod(tmp, _default_mode(os.path.isdir(tmp)))
    os.replace(tmp, path)
    return Path(path)


@contextmanager
def atomic_file(path, durable: bool = False) -> Iterator[Path]:
    """Yield a fresh temporary path beside `path`; write it, and on a normal exit it replaces
    `path` in one rename (when `durable`: the file fsync'd before, its folder after). On an
    exception (KeyboardInterrupt included) the temporary file is removed and `path` is left as it
    was."""
    path = Path(path)
    folder = _existing_folder(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=TMP_SUFFIX, dir=folder)
    except OSError as e:
        raise InputError(f"{path}: cannot write in {folder} ({e.strerror}); choose another output path") from None
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        if durable:
            with open(tmp, "rb") as f:
                os.fsync(f.fileno())
        publish(tmp, path)
        if durable:  # the rename itself survives a power cut only once the folder is on disk
            _fsync_folder(folder)
    except BaseException:
        tmp.unlink(missing_ok=True)
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
        fd, tmp = tempfile.mkstemp(prefix=".tomgs-probe.", suffix=TMP_SUFFIX, dir=folder)
    except OSError as e:
        raise InputError(f"{path}: cannot write in {folder} ({e.strerror}); choose another output path") from None
    os.close(fd)
    os.unlink(tmp)


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
    if paths["scene"].suffix.lower() != ".ply":
        raise InputError(f"{output}: a scene is written as .ply; name the output like scene.ply")
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


def remove_stale_temporaries(path, older_than_s: float = 60.0) -> list[Path]:
    """Remove the temporary files of `path` ('.NAME.*.tmp' beside it) that a killed process left,
    if older than `older_than_s` (a running writer's are fresh). Returns what was removed."""
    path = Path(path)
    removed = []
    if not path.parent.is_dir():
        return removed
    now = time.time()
    for tmp in path.parent.glob(f".{path.name}.*{TMP_SUFFIX}"):
        try:
            if tmp.is_file() and not tmp.is_symlink() and now - tmp.stat().st_mtime > older_than_s:
                tmp.unlink()
                removed.append(tmp)
        except OSError:
            pass  # gone already, or not ours to remove
    return removed
