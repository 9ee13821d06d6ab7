"""Camera files: the readers under `Cameras.load`, `Cameras.from_colmap` and `Cameras.from_anycam`
(tomgs.cameras, the value type, builds its cameras from what these return).

    load_json     a JSON file's value (tomgs cameras, keyframes), InputError naming the file
    load_npy      a numeric .npy array, its header checked before anything is allocated
    npy_header    the checked header of an .npy stream (also read inside .npz files)
    load_array    an array given as itself, an .npy file or a text file of numbers
    parse_colmap  COLMAP's text model: cameras.txt and images.txt
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from tomgs.errors import InputError


def parse_colmap(cams_txt: Path, imgs_txt: Path):
    """(camera id -> (K, w, h), [(name, camera id, R w2c, t w2c)]) from COLMAP text files."""
    cams = {}
    for line in cams_txt.read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        p = line.split()
        cam_id, model, w, h, params = p[0], p[1], int(p[2]), int(p[3]), [float(x) for x in p[4:]]
        if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE"):
            fx = fy = params[0]
            cx, cy = params[1], params[2]
        elif model in ("PINHOLE", "OPENCV", "OPENCV_FISHEYE", "FULL_OPENCV"):
            fx, fy, cx, cy = params[:4]
        else:
            raise InputError(f"{cams_txt}: camera model {model} is not supported")
        cams[cam_id] = (np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), w, h)
    lines = [l.strip() for l in imgs_txt.read_text().splitlines() if not l.startswith("#")]
    entries, i = [], 0
    while i < len(lines):  # each image takes two lines: its pose, then its 2D points (may be blank)
        if not lines[i]:
            i += 1
            continue
        p = lines[i].split()
        qw, qx, qy, qz, tx, ty, tz = map(float, p[1:8])
        entries.append((p[9], p[8], _quat_to_R(np.array([qw, qx, qy, qz])), np.array([tx, ty, tz])))
        i += 2
    return cams, entries


def _quat_to_R(q: np.ndarray) -> np.ndarray:
    """COLMAP's quaternion (w, x, y, z) of any finite, non-zero norm -> rotation matrix [3,3]."""
    from tomgs.geometry import quat_to_rotmat

    norm = np.linalg.norm(q)
    if not (np.isfinite(norm) and norm > 0):
        raise ValueError(f"quaternion {q.tolist()} is not a rotation")
    return quat_to_rotmat(q / norm)  # unit first: a norm below QUAT_EPS is still a rotation here


def load_array(a, what: str) -> np.ndarray:
    if isinstance(a, (str, Path)):
        p = Path(a)
        if not p.is_file():
            raise InputError(f"{what} file {p} does not exist")
        if p.suffix == ".npy":
            a = load_npy(p, what)
        else:
            try:
                a = np.loadtxt(p, dtype=np.float64, ndmin=1)
            except (ValueError, OverflowError, IndexError) as e:
                raise InputError(f"cannot read {what} from {p} ({str(e)[:200]}): write it as numbers, "
                                 "one matrix row per line") from None
    try:
        return np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as e:
        raise InputError(f"{what} must be an array of numbers ({e})") from None


def load_json(path: Path, fix: str):
    """The JSON value in file `path`; InputError naming the file for bad text, bad JSON or nesting too
    deep for Python (never RecursionError). Memory follows the file's size (Python objects)."""
    try:
        return json.loads(Path(path).read_bytes())
    except RecursionError:
        raise InputError(f"{path}: the JSON is nested too deeply to read: {fix}") from None
    except (ValueError, UnicodeDecodeError) as e:  # JSONDecodeError, more than 4300 digits in a number
        raise InputError(f"{path} is not valid JSON ({str(e)[:200]}): {fix}") from None
    except OSError as e:
        raise InputError(f"cannot read {path} ({e})") from None


def load_npy(path: Path, what: str) -> np.ndarray:
    """A numeric array from an .npy file, its header checked first: the shape and dtype it declares
    must take exactly the bytes that follow the header (so nothing is allocated that the file does
    not hold), no pickled objects. InputError otherwise."""
    path = Path(path)
    fix = f"save the {what} array with numpy.save"
    size = path.stat().st_size
    try:
        with open(path, "rb") as f:
            shape, dtype, fortran, offset = npy_header(f, path)
            nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
            if offset + nbytes != size:
                raise InputError(f"{path}: its header declares a {dtype} array of shape {list(shape)} "
                                 f"({nbytes:,} bytes) but {size - offset:,} bytes follow: {fix}")
            data = np.fromfile(f, dtype=dtype, count=int(np.prod(shape)))
            return data.reshape(shape, order="F" if fortran else "C")
    except InputError:
        raise
    except (ValueError, OSError) as e:
        raise InputError(f"cannot read {what} from {path} ({e}): {fix}") from None


def npy_header(stream, source) -> tuple[tuple[int, ...], np.dtype, bool, int]:
    """(shape, dtype, Fortran order, bytes read) of the .npy header at the start of `stream`;
    InputError unless it is an array of numbers (bool, int, float). Reads at most the header, and
    the header only when the length it declares is under 10,000 bytes (numpy's own limit)."""
    import io

    from numpy.lib import format as npformat

    prefix = stream.read(8)
    if len(prefix) < 8 or prefix[:6] != b"\x93NUMPY" or prefix[6] not in (1, 2, 3):
        raise InputError(f"{source} is not a .npy array (no '\\x93NUMPY' magic of version 1, 2 or 3)")
    length = stream.read(2 if prefix[6] == 1 else 4)
    size = int.from_bytes(length, "little")
    if len(length) < (2 if prefix[6] == 1 else 4) or size > 10_000:
        raise InputError(f"{source}: the .npy header declares {size:,} bytes; numpy writes headers under 10,000")
    header = stream.read(size)
    if len(header) < size:
        raise InputError(f"{source}: the .npy header is truncated")
    read = npformat.read_array_header_1_0 if prefix[6] == 1 else npformat.read_array_header_2_0
    try:
        shape, fortran, dtype = read(io.BytesIO(length + header))
    except Exception as e:  # noqa: BLE001 -- numpy's header parser raises assorted types for garbage
        raise InputError(f"{source} is not a .npy array ({type(e).__name__}: {str(e)[:200]})") from None
    if not isinstance(dtype, np.dtype) or dtype.kind not in "biuf" or dtype.hasobject or dtype.shape or dtype.names:
        raise InputError(f"{source} holds a {dtype} array; an array of numbers is expected")
    if any(int(n) < 0 for n in shape):
        raise InputError(f"{source}: the .npy header declares shape {list(shape)}")
    return tuple(int(n) for n in shape), dtype, bool(fortran), 8 + len(length) + size
