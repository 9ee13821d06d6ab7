"""Scene files: one PLY holds the Gaussians, the cameras and the frame-to-time mapping.

`save_scene(path, model, cameras, info)` writes it atomically; `load_scene(path)` reads it back
exactly (float32 parameters and float64 cameras bit for bit, the active SH degree, `info`).

Layout (binary little endian, format "tomgs-scene" version 1):

    ply
    format binary_little_endian 1.0
    comment tomgs-scene {"format": "tomgs-scene", "version": 1, "width": W, "height": H,
                         "K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "sh_degree": d,
                         "max_sh_degree": D, "tomgs": "0.1.0", "info": {...}}   (one line)
    element vertex N                      one per Gaussian, all float32, in this order:
      x y z                               mean
      nx ny nz                            zeros (INRIA writes them; nothing reads them)
      f_dc_0 f_dc_1 f_dc_2                SH DC coefficient, R G B
      f_rest_0 .. f_rest_{3(K-1)-1}       SH rest, channel-major: K-1 coefficients of R, then G,
                                          then B (INRIA's features_rest [N,K-1,3] transposed to
                                          [N,3,K-1] and flattened); none for degree 0
      opacity                             base opacity, logit
      scale_0 scale_1 scale_2             log scales
      rot_0 rot_1 rot_2 rot_3             raw quaternion w x y z
      t_mean                              temporal centre (clip time, t in [0, 1])
      t_log_sigma                         log of the temporal sigma (clip time)
    element camera T                      one per frame, in clip order:
      c2w_00 .. c2w_33  double            camera-to-world, row-major, OpenCV axes
      time              double            frame time in [0, 1]
      index             int               source frame number

Why this shape: 3DGS loaders and viewers read the first element, `vertex`, and match its
properties by name or prefix (`f_rest_`, `scale_`, `rot`), so the INRIA properties come first and
in INRIA's order and the temporal ones after them under names without those prefixes; tools that
read only the vertex block stop before the `camera` element, which is stored after it. Cameras are
binary float64 so poses survive bit for bit; K and the image size are per clip and travel in the
header comment as JSON, whose float text (Python's repr) also reads back exactly. `max_sh_degree`
D is the SH degree stored (K = (D + 1)^2 coefficients per channel), `sh_degree` the active one.
`info` is any JSON object, e.g. the fit's settings and results (non-finite numbers are written as
Python's JSON writes them, NaN and Infinity); `fps` and `background` are used by `tomgs render`
when present. A tool that re-saves the PLY may drop the comment or the camera element;
`load_scene` then says so.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from tomgs.cameras import Cameras, short_repr
from tomgs.errors import InputError
from tomgs.outputs import atomic_file

if TYPE_CHECKING:  # for the annotation only; load_scene imports the model when it builds one
    from tomgs.model import GaussianModel

FORMAT = "tomgs-scene"
VERSION = 1
COMMENT_TAG = FORMAT  # the header comment that carries the JSON starts with this word
TEMPORAL_PROPERTIES = ("t_mean", "t_log_sigma")
_C2W = tuple(f"c2w_{r}{c}" for r in range(4) for c in range(4))


def inria_properties(max_sh_degree: int) -> list[str]:
    """The INRIA 3DGS vertex property names, in order, for SH of `max_sh_degree`."""
    rest = 3 * ((max_sh_degree + 1) ** 2 - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def vertex_properties(max_sh_degree: int) -> list[str]:
    """Every vertex property of a tomgs scene: the INRIA ones, then the temporal ones."""
    return inria_properties(max_sh_degree) + list(TEMPORAL_PROPERTIES)


@dataclass
class Scene:
    """What a scene file holds: the Gaussians, the cameras (with frame times) and free-form info."""

    model: GaussianModel
    cameras: Cameras
    info: dict = field(default_factory=dict)


# ---- writing -----------------------------------------------------------------------------------

def save_scene(path, model, cameras: Cameras, info: dict | None = None) -> Path:
    """Write `model` (a GaussianModel), `cameras` and `info` (a JSON-serialisable dict) to the PLY
    file `path`, atomically: a temporary file in the same folder, renamed at the end."""
    from plyfile import PlyData, PlyElement

    path = Path(path)
    info = {} if info is None else info
    if not isinstance(info, dict):
        raise TypeError(f"info must be a dict, got {type(info).__name__}")
    if len(cameras) == 0:
        raise ValueError("a scene needs at least one camera")
    if not (np.abs(cameras.frame_indices) < 2**31).all():
        raise ValueError("frame indices must fit in int32")

    n, degree = len(model), model.max_sh_degree
    with torch.no_grad():
        params = {name: getattr(model, name).detach().cpu() for name in
                  ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest", "t_means", "log_t_scales")}
    bad = [name for name, value in params.items() if not bool(torch.isfinite(value).all())]
    if bad:
        raise ValueError(f"cannot save a scene with non-finite parameters ({', '.join(bad)})")
    columns = [
        params["means"],
        torch.zeros(n, 3),
        params["sh_dc"].reshape(n, 3),
        params["sh_rest"].transpose(1, 2).reshape(n, 3 * (params["sh_rest"].shape[1])),  # [N,3,K-1]: channel-major
        params["opacity_logits"].reshape(n, 1),
        params["log_scales"],
        params["quats"],
        params["t_means"].reshape(n, 1),
        params["log_t_scales"].reshape(n, 1),
    ]
    flat = torch.cat([c.float() for c in columns], dim=1).numpy()
    names = vertex_properties(degree)
    assert flat.shape == (n, len(names))
    vertex = np.empty(n, dtype=[(name, "<f4") for name in names])
    for j, name in enumerate(names):
        vertex[name] = flat[:, j]

    camera = np.empty(len(cameras), dtype=[(name, "<f8") for name in _C2W] + [("time", "<f8"), ("index", "<i4")])
    c2w = cameras.c2w.reshape(len(cameras), 16)
    for j, name in enumerate(_C2W):
        camera[name] = c2w[:, j]
    camera["time"] = cameras.times
    camera["index"] = cameras.frame_indices

    from tomgs import __version__

    header = {"format": FORMAT, "version": VERSION, "width": cameras.width, "height": cameras.height,
              "K": cameras.K.tolist(), "sh_degree": int(model.sh_degree), "max_sh_degree": int(degree),
              "tomgs": __version__, "info": info}
    try:  # NaN and infinities are written as Python's JSON does (NaN, Infinity) and read back
        text = json.dumps(header, ensure_ascii=True, separators=(",", ":"))
    except (TypeError, ValueError) as e:
        raise ValueError(f"info must be JSON-serialisable ({e})") from None
    text = text.replace("end_header", "end\\u005fheader")  # never spell the header terminator in a comment
    ply = PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(camera, "camera")],
                  text=False, byte_order="<", comments=[f"{COMMENT_TAG} {text}"])

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path, durable=True) as tmp, open(tmp, "wb") as f:
        ply.write(f)
    return path


# ---- reading -----------------------------------------------------------------------------------

def load_scene(path, device="cpu") -> Scene:
    """Read a scene written by `save_scene`; the model's parameters are put on `device`.
    Raises `tomgs.InputError` naming the file and the fix when it is missing or malformed."""
    from tomgs.io.ply import read_ply
    from tomgs.model import GaussianModel

    path = Path(path)
    fix = "write scenes with `tomgs fit` or tomgs.save_scene"
    if not path.is_file():
        raise InputError(f"scene file {path} does not exist" + (" (it is a folder)" if path.is_dir() else "")
                         + f": give the path of a .ply scene ({fix})")
    # header read with a byte cap, element counts checked against the file's size, then memory-mapped:
    # each column is copied out once below
    ply = read_ply(path, "scene file", fix)

    header = _header(ply, path, fix)
    names = [e.name for e in ply.elements]
    if not names or names[0] != "vertex" or "camera" not in names:
        raise InputError(f"{path} has elements {names}; a tomgs scene has 'vertex' first and then 'camera' "
                         f"(a tool that re-saved it may have dropped the cameras): {fix}")
    degree = header["max_sh_degree"]
    vertex = ply["vertex"].data
    not_numbers = [p for e in (vertex, ply["camera"].data) for p in (e.dtype.names or ())
                   if e.dtype[p].kind not in "iuf"]
    if not_numbers:
        raise InputError(f"{path}: properties {', '.join(not_numbers[:6])} are lists; a scene's vertex and camera "
                         f"properties are numbers: {fix}")
    missing = [p for p in vertex_properties(degree) if p not in (vertex.dtype.names or ())]
    if missing:
        shown = ", ".join(missing[:6]) + (f" and {len(missing) - 6} more" if len(missing) > 6 else "")
        raise InputError(f"{path}: vertex element lacks properties {shown} (SH degree {degree} per the header): {fix}")
    extra_rest = [p for p in vertex.dtype.names if p.startswith("f_rest_") and p not in vertex_properties(degree)]
    if extra_rest:
        raise InputError(f"{path}: vertex has {len(extra_rest)} more f_rest_ properties than SH degree {degree} "
                         f"allows (the header and the data disagree): {fix}")
    camera = ply["camera"].data
    missing = [p for p in (*_C2W, "time", "index") if p not in (camera.dtype.names or ())]
    if missing:
        raise InputError(f"{path}: camera element lacks properties {', '.join(missing)}: {fix}")
    if len(camera) == 0:
        raise InputError(f"{path} holds zero cameras: a scene needs one per frame ({fix})")

    n = len(vertex)

    def col(names_):  # float32 [N, len(names_)]
        return np.stack([np.asarray(vertex[p], dtype=np.float32) for p in names_], axis=1) if names_ \
            else np.zeros((n, 0), np.float32)

    rest = 3 * ((degree + 1) ** 2 - 1)
    arrays = dict(
        means=col(["x", "y", "z"]),
        sh_dc=col(["f_dc_0", "f_dc_1", "f_dc_2"]).reshape(n, 1, 3),
        sh_rest=col([f"f_rest_{i}" for i in range(rest)]).reshape(n, 3, rest // 3).transpose(0, 2, 1),
        opacity_logits=col(["opacity"])[:, 0],
        log_scales=col(["scale_0", "scale_1", "scale_2"]),
        quats=col(["rot_0", "rot_1", "rot_2", "rot_3"]),
        t_means=col(["t_mean"])[:, 0],
        log_t_scales=col(["t_log_sigma"])[:, 0],
    )
    bad = {name: int((~np.isfinite(a.reshape(n, a[0].size if n else 0))).any(axis=1).sum())
           for name, a in arrays.items()}
    bad = {name: count for name, count in bad.items() if count}
    if bad:
        raise InputError(f"{path}: non-finite values (NaN or infinity) in "
                         + ", ".join(f"{name} of {count} Gaussians" for name, count in bad.items())
                         + ": the file is corrupt or came from a diverged fit; refit or remove those Gaussians")

    try:  # Cameras checks sizes, poses, K, times and frame numbers
        c2w = np.stack([np.asarray(camera[p], dtype=np.float64) for p in _C2W], axis=1).reshape(-1, 4, 4)
        cameras = Cameras(c2w, np.asarray(header["K"], dtype=np.float64), header["width"], header["height"],
                          np.array(camera["time"], dtype=np.float64), np.array(camera["index"]))
    except (ValueError, TypeError, OverflowError) as e:  # InputError from Cameras, or a K it cannot hold
        raise InputError(f"{path}: bad cameras ({str(e).removeprefix('Cameras: ')}): {fix}") from None

    tensors = {name: torch.from_numpy(np.ascontiguousarray(a)).to(device) for name, a in arrays.items()}
    model = GaussianModel(**tensors, sh_degree=header["sh_degree"])
    return Scene(model=model, cameras=cameras, info=header["info"])


def _header(ply, path: Path, fix: str) -> dict:
    """The JSON header comment, checked."""
    tagged = [c for c in ply.comments if c.split(None, 1)[:1] == [COMMENT_TAG]]
    if not tagged:
        raise InputError(f"{path} is a PLY file but not a tomgs scene (no '{COMMENT_TAG}' header comment; "
                         f"a plain 3DGS PLY has no cameras or frame times): {fix}")
    try:
        header = json.loads(tagged[0].split(None, 1)[1])
    except RecursionError:
        raise InputError(f"{path}: the '{COMMENT_TAG}' header comment nests too deeply to read: {fix}") from None
    except (IndexError, ValueError) as e:  # JSONDecodeError, or a number of more than 4300 digits
        raise InputError(f"{path}: the '{COMMENT_TAG}' header comment is not valid JSON ({str(e)[:200]}): {fix}") \
            from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise InputError(f"{path}: the '{COMMENT_TAG}' header comment lacks \"format\": \"{FORMAT}\": {fix}")
    if header.get("version") != VERSION:
        raise InputError(f"{path} is tomgs scene version {short_repr(header.get('version'))}; this tomgs reads "
                         f"version {VERSION}: install the tomgs that wrote it, or refit")
    if _depth(header) > MAX_HEADER_DEPTH:
        raise InputError(f"{path}: the '{COMMENT_TAG}' header comment nests deeper than {MAX_HEADER_DEPTH} levels; "
                         f"what tomgs writes there is a few levels deep: {fix}")

    def integer(v):
        return isinstance(v, int) and not isinstance(v, bool)

    def number(v):
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    checks = {
        "width": integer,
        "height": integer,
        "K": lambda v: isinstance(v, list) and len(v) == 3 and all(
            isinstance(row, list) and len(row) == 3 and all(number(x) for x in row) for row in v),
        "max_sh_degree": lambda v: integer(v) and 0 <= v <= 3,
        "sh_degree": lambda v: integer(v) and 0 <= v <= header.get("max_sh_degree", -1),
        "info": lambda v: isinstance(v, dict),
    }
    for key, ok in checks.items():
        if key not in header or not ok(header[key]):
            raise InputError(f"{path}: header field {key!r} is missing or invalid ({short_repr(header.get(key), 80)}): "
                             f"{fix}")
    return header


MAX_HEADER_DEPTH = 64
"""Deepest nesting of the header JSON: its info holds settings, notes and edits, a few levels deep;
64 keeps every later json.dumps and repr of it far from Python's recursion limit."""


def _depth(value) -> int:
    """Nesting depth of a JSON value (0 for a scalar), without recursion."""
    deepest, stack = 0, [(value, 0)]
    while stack:
        item, depth = stack.pop()
        deepest = max(deepest, depth)
        if deepest > MAX_HEADER_DEPTH:
            break
        if isinstance(item, dict):
            stack.extend((v, depth + 1) for v in item.values())
        elif isinstance(item, list):
            stack.extend((v, depth + 1) for v in item)
    return deepest
