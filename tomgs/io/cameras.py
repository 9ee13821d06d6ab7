"""Camera files and other tools' camera formats: the readers under `Cameras.load`, `Cameras.from_colmap`
and `Cameras.from_anycam`, and the writers of `tomgs export --cameras-out`.

tomgs.cameras, the value type, sits on a lower floor: its constructors import these readers inside
the method and build the cameras from the arrays they return; this module never imports it (the
writers read a Cameras' fields). The tomgs cameras JSON schema is the value's own (`Cameras.to_dict`).

    load_json     a JSON file's value (tomgs cameras, keyframes), InputError naming the file
    load_npy      a numeric .npy array, its header checked before anything is allocated
    npy_header    the checked header of an .npy stream (also read inside .npz files)
    load_array    an array given as itself, an .npy file or a text file of numbers
    read_anycam   AnyCam's output: camera-to-world poses and intrinsics
    read_colmap   COLMAP's text model (cameras.txt and images.txt) as camera-to-world poses
    colmap_text   a COLMAP text model of cameras
    nerfstudio    nerfstudio's transforms.json of cameras
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from tomgs.errors import InputError


def read_colmap(folder) -> tuple[np.ndarray, np.ndarray, int, int]:
    """(c2w float64 [T,4,4], K [3,3], width, height) of a COLMAP text model (folder with cameras.txt
    and images.txt; one shared camera), its images ordered by name (natural sort); COLMAP's
    world-to-camera (qw qx qy qz, t) poses inverted. Distortion parameters are dropped (undistort the
    frames first). InputError naming the file for anything it holds."""
    from tomgs.io.video import natural_key

    folder = Path(folder)
    cams_txt, imgs_txt = folder / "cameras.txt", folder / "images.txt"
    for f in (cams_txt, imgs_txt):
        if not f.is_file():
            raise InputError(f"{f} is missing: export the COLMAP model as text (colmap model_converter "
                             "--output_type TXT)")
    try:
        cams, entries = _parse_colmap(cams_txt, imgs_txt)
    except InputError:
        raise
    except (ValueError, IndexError, OverflowError) as e:
        raise InputError(f"{folder}: cannot parse the COLMAP text model ({str(e)[:200]}); export it with "
                         "colmap model_converter --output_type TXT") from None
    if not entries:
        raise InputError(f"{imgs_txt} lists no images")
    entries.sort(key=lambda e: natural_key(Path(e[0])))
    cam_ids = {e[1] for e in entries}
    if len(cam_ids) != 1 or not cam_ids <= set(cams):
        raise InputError(f"{folder}: tomgs needs one shared camera in cameras.txt, images use {sorted(cam_ids)}")
    K, w, h = cams[cam_ids.pop()]
    c2w = np.tile(np.eye(4), (len(entries), 1, 1))
    for k, (_, _, R, t) in enumerate(entries):
        c2w[k, :3, :3] = R.T
        c2w[k, :3, 3] = -R.T @ t
    return c2w, K, w, h


def _parse_colmap(cams_txt: Path, imgs_txt: Path):
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


def read_anycam(c2w, K) -> tuple[np.ndarray, np.ndarray, str]:
    """(c2w float64 [T,4,4], K [3,3], the source's name for messages) of AnyCam's output: c2w as an
    array or an .npy path, K [3,3] or [T,3,3] as an array or an .npy/.txt path (per-frame K are
    averaged). InputError naming the files for a wrong shape."""
    source = " and ".join(str(a) for a in (c2w, K) if isinstance(a, (str, Path))) or "AnyCam arrays"
    c2w = load_array(c2w, "c2w")
    K = load_array(K, "K")
    if c2w.ndim != 3 or c2w.shape[1:] != (4, 4) or len(c2w) == 0:
        raise InputError(f"{source}: AnyCam c2w must have shape [T,4,4], got {c2w.shape}")
    if K.shape == (len(c2w), 3, 3):
        K = K.mean(axis=0)
    if K.shape != (3, 3):
        raise InputError(f"{source}: AnyCam K must have shape [3,3] or [T,3,3], got {K.shape}")
    return c2w, K, source


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


def colmap_text(cameras) -> dict[str, str]:
    """A COLMAP text model of `cameras` (a tomgs.cameras.Cameras): {'cameras.txt', 'images.txt',
    'points3D.txt': text}, one shared PINHOLE camera, images named by `Cameras.frame_names` with
    COLMAP's world-to-camera quaternion (w x y z) and translation, no points. COLMAP's pixel centres
    are at +0.5 as ours; numbers in full precision (Python's repr), so `read_colmap` reads the poses back."""
    from tomgs.geometry import rotmat_to_quat

    K = cameras.K
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    w2c = np.linalg.inv(cameras.c2w)
    quats = rotmat_to_quat(w2c[:, :3, :3])
    images = ["# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then a line of points (none)"]
    for k, name in enumerate(cameras.frame_names()):
        numbers = " ".join(repr(float(v)) for v in (*quats[k], *w2c[k, :3, 3]))
        images += [f"{k + 1} {numbers} 1 {name}", ""]
    return {"cameras.txt": "# CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]\n"
                           f"1 PINHOLE {cameras.width} {cameras.height} {fx!r} {fy!r} {cx!r} {cy!r}\n",
            "images.txt": "\n".join(images) + "\n",
            "points3D.txt": "# POINT3D_ID X Y Z R G B ERROR TRACK[]\n"}


def nerfstudio(cameras, image_folder: str = "images") -> dict:
    """nerfstudio's transforms.json of `cameras` (a tomgs.cameras.Cameras): OpenGL camera axes (x right,
    y up, z back: c2w with y and z negated), pinhole intrinsics (pixel centres at +0.5 in both), each
    frame's file under `image_folder` and its clip time."""
    K = cameras.K
    opengl = cameras.c2w @ np.diag([1.0, -1.0, -1.0, 1.0])
    return {"camera_model": "OPENCV", "w": cameras.width, "h": cameras.height, "fl_x": float(K[0, 0]),
            "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
            "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
            "frames": [{"file_path": f"{image_folder}/{name}", "transform_matrix": m.tolist(), "time": float(t),
                        "frame_index": int(i)}
                       for name, m, t, i in zip(cameras.frame_names(), opengl, cameras.times, cameras.frame_indices)]}
