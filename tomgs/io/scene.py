"""Scene files: one PLY holds the Gaussians, the cameras and the frame-to-time mapping.

`save_scene(path, model, cameras, info)` writes it atomically; `load_scene(path)` reads it back
exactly (float32 parameters and float64 cameras bit for bit, the active SH degree, `info`). A path
ending in .tsog is written compressed (tomgs.io.tsog: the Gaussians quantised, the clip the same), and
`load_scene` reads a file by its first bytes, so every command that reads a scene reads either.

Layout (format "tomgs-scene" version 2; docs/scene-format.md has the why and the readers tried):

    ply
    format binary_little_endian 1.0
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
    comment tomgs-scene 2: ...            one short line saying where the rest is
    end_header
    N rows of vertex data
    the clip, after the PLY data ("trailer"):
      b"\ntomgs-scene-data\n"            18 bytes
      u64 little endian L                 length of the JSON that follows
      L bytes of JSON                     {"format": "tomgs-scene", "version": 2, "width": W,
                                           "height": H, "K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]],
                                           "sh_degree": d, "max_sh_degree": D, "tomgs": "0.1.0",
                                           "cameras": T, "info": {...}}
      T camera records, 144 bytes each    c2w float64 [16] (row-major, OpenCV axes), time float64,
                                          index int64 (source frame number), little endian

Why this shape: 3DGS readers take one `vertex` element of float32 properties and match them by name
or prefix (`f_rest_`, `scale_`, `rot`), so the INRIA properties come first in INRIA's order and the
temporal ones after them under names without those prefixes. Some readers add every `property` line
of the header into one row stride (antimatter15/splat, gsplat.js: a second element breaks them),
read only the first 10 kB for the header (antimatter15/splat) or abort on a header line over about
1,000 bytes (open3d's RPly). Every reader stops at the end of the vertex rows, so the cameras, the
frame times and the settings travel after them, where readers do not look, in float64 bit for bit;
the JSON (Python's float repr) reads back exactly too. `max_sh_degree` D is the SH degree stored
(K = (D + 1)^2 coefficients per channel), `sh_degree` the active one. `info` is any JSON object,
e.g. the fit's settings and results (NaN and Infinity written as Python's JSON writes them); `fps`
and `background` are used by `tomgs render` when present.

A tool that re-saves the PLY (SuperSplat, splat-transform) keeps the vertex properties, temporal ones
included, and drops the comment and the trailer; `load_scene(path, cameras=...)` (`--cameras`) reads
such a file with the clip's cameras given back, and without them says so. Version 1 files (the
JSON in a header comment, the cameras as a second PLY element `camera`) still load.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from tomgs.cameras import Cameras
from tomgs.errors import InputError, short_repr
from tomgs.io import tsog
from tomgs.io.kinds import SCENE_FIX, check_scene_path
from tomgs.outputs import atomic_file

if TYPE_CHECKING:  # for the annotation only; load_scene imports the model when it builds one
    from tomgs.model import GaussianModel

FORMAT = "tomgs-scene"
VERSION = 2
READS = (1, 2)  # versions load_scene reads
COMMENT_TAG = FORMAT  # the header comment that marks a tomgs scene starts with this word
HEADER_NOTE = (f"{COMMENT_TAG} {VERSION}: the clip's cameras, frame times and settings follow the vertex "
               "data; tomgs.load_scene reads them")
TRAILER_MAGIC = b"\ntomgs-scene-data\n"
MAX_TRAILER_JSON = 64 << 20  # settings, notes and edit history: kilobytes; a bigger claim is a damaged file
CAMERA_RECORD = np.dtype([("c2w", "<f8", (16,)), ("time", "<f8"), ("index", "<i8")])
TEMPORAL_PROPERTIES = ("t_mean", "t_log_sigma")
SAVE_CHUNK = 1 << 18  # vertex rows written at a time (64 MiB at SH degree 3)
NORMALS = ("nx", "ny", "nz")
_C2W = tuple(f"c2w_{r}{c}" for r in range(4) for c in range(4))  # version 1's camera element


def inria_properties(max_sh_degree: int) -> list[str]:
    """The INRIA 3DGS vertex property names, in order, for SH of `max_sh_degree`."""
    rest = 3 * ((max_sh_degree + 1) ** 2 - 1)
    return (["x", "y", "z", *NORMALS, "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def vertex_properties(max_sh_degree: int) -> list[str]:
    """Every vertex property of a tomgs scene: the INRIA ones, then the temporal ones."""
    return inria_properties(max_sh_degree) + list(TEMPORAL_PROPERTIES)


def vertex_bytes(count: int, max_sh_degree: int) -> int:
    """The bytes of `count` Gaussians' vertex rows in a scene file (float32 each property): what the
    scene's size follows (the header and the clip's cameras after the rows are a few kilobytes)."""
    return 4 * len(vertex_properties(max_sh_degree)) * int(count)


def ply_header(names, count: int, comments=()) -> bytes:
    """A binary little-endian PLY header of one `vertex` element of `count` rows of float32
    properties `names`, `comments` after them (so `element vertex` is the third line, where SIBR's
    viewer looks). Every line is short: a property name or a comment of at most 200 characters."""
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {count}",
             *(f"property float {name}" for name in names), *(f"comment {c}" for c in comments), "end_header"]
    assert all(len(line) <= 200 for line in lines[3:])
    return ("\n".join(lines) + "\n").encode("ascii")


@dataclass
class Scene:
    """What a scene file holds: the Gaussians, the cameras (with frame times) and free-form info."""

    model: GaussianModel
    cameras: Cameras
    info: dict = field(default_factory=dict)


def bits_per_pixel(nbytes: int, cameras: Cameras) -> float:
    """Bits of a scene file of `nbytes` bytes per pixel of the clip its `cameras` were fitted to
    (8 nbytes / (width x height x frames)): what the scene costs beside its clip's frames (JPEG
    frames take ~1.3 bits a pixel, H.264 ~0.1-0.2)."""
    return 8.0 * nbytes / (cameras.width * cameras.height * len(cameras))


# ---- writing -----------------------------------------------------------------------------------

def save_scene(path, model, cameras: Cameras, info: dict | None = None, *, means_bits: int = tsog.MEANS_BITS,
               t_bits: int = tsog.T_MEANS_BITS) -> Path:
    """Write `model` (a GaussianModel), `cameras` and `info` (a JSON-serialisable dict) to the scene
    file `path`, atomically: a temporary file in the same folder, renamed at the end. A path ending
    in .tsog is a compressed scene (tomgs.io.tsog), its means and t_means quantised to `means_bits`
    (an axis) and `t_bits` (1..16); any other path a PLY scene, exact."""
    path = Path(path)
    info = {} if info is None else info
    if not isinstance(info, dict):
        raise TypeError(f"info must be a dict, got {type(info).__name__}")
    if len(cameras) == 0:
        raise ValueError("a scene needs at least one camera")

    import torch

    n, degree = len(model), model.max_sh_degree
    with torch.no_grad():  # where the model lives: rows go to the host a chunk at a time (below)
        params = {name: getattr(model, name).detach() for name in
                  ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest", "t_means", "log_t_scales")}
    bad = [name for name, value in params.items() if not bool(torch.isfinite(value).all())]
    if bad:
        raise ValueError(f"cannot save a scene with non-finite parameters ({', '.join(bad)})")
    records = np.empty(len(cameras), CAMERA_RECORD)
    records["c2w"] = cameras.c2w.reshape(len(cameras), 16)
    records["time"] = cameras.times
    records["index"] = cameras.frame_indices

    from tomgs import __version__

    clip = {"format": FORMAT, "version": VERSION, "width": cameras.width, "height": cameras.height,
            "K": cameras.K.tolist(), "sh_degree": int(model.sh_degree), "max_sh_degree": int(degree),
            "tomgs": __version__, "cameras": len(cameras), "info": info}
    try:  # NaN and infinities are written as Python's JSON does (NaN, Infinity) and read back
        text = json.dumps(clip, ensure_ascii=True, separators=(",", ":")).encode("ascii")
    except (TypeError, ValueError) as e:
        raise ValueError(f"info must be JSON-serialisable ({e})") from None
    if path.suffix.lower() == tsog.SUFFIX:
        arrays = {name: value.cpu().numpy() for name, value in params.items()}
        return tsog.write_tsog(path, arrays, clip, records, means_bits, t_bits)
    names = vertex_properties(degree)

    def rows(start: int, stop: int) -> bytes:
        """Vertex rows start..stop as little-endian float32 bytes, in `names` order."""
        p = {name: value[start:stop] for name, value in params.items()}
        m = stop - start
        columns = [p["means"], torch.zeros(m, 3, device=p["means"].device), p["sh_dc"].reshape(m, 3),
                   p["sh_rest"].transpose(1, 2).reshape(m, -1),  # [M,3,K-1]: channel-major, as INRIA
                   p["opacity_logits"].reshape(m, 1), p["log_scales"], p["quats"], p["t_means"].reshape(m, 1),
                   p["log_t_scales"].reshape(m, 1)]
        block = torch.cat([c.float() for c in columns], dim=1).cpu().numpy()
        assert block.shape == (m, len(names))
        return block.astype("<f4", copy=False).tobytes()

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path, durable=True) as tmp, open(tmp, "wb") as f:
        f.write(ply_header(names, n, [HEADER_NOTE]))
        for start in range(0, n, SAVE_CHUNK):  # a chunk at a time: no host copy of the whole cloud
            f.write(rows(start, min(start + SAVE_CHUNK, n)))
        f.write(TRAILER_MAGIC + struct.pack("<Q", len(text)) + text)
        f.write(records.tobytes())
    return path


# ---- reading -----------------------------------------------------------------------------------

def load_scene(path, device="cpu", cameras=None) -> Scene:
    """Read a scene written by `save_scene` (or by an earlier tomgs): a PLY scene, or a compressed
    one (.tsog, known by its first bytes whatever its name); the model's parameters are put on
    `device`. `cameras` (a Cameras, or the path of a cameras JSON from `tomgs export --cameras-out`
    or `tomgs poses`) replaces the file's own, and gives a scene back its cameras after a tool that
    re-saved the PLY (SuperSplat, splat-transform) dropped them. Raises `tomgs.InputError` naming the
    file and the fix when it is missing or malformed."""
    import torch

    from tomgs.model import GaussianModel

    path = check_scene_path(path)
    fix = SCENE_FIX
    given = _given_cameras(cameras)
    if tsog.is_tsog(path):
        header, stored, arrays = tsog.read_tsog(path, CAMERA_RECORD, lambda clip: _checked_clip(clip, path, fix))
    else:
        header, stored, arrays = _read_ply_scene(path, given, fix)
    n = len(arrays["means"])
    bad = {name: int((~np.isfinite(a.reshape(n, a[0].size if n else 0))).any(axis=1).sum())
           for name, a in arrays.items()}
    bad = {name: count for name, count in bad.items() if count}
    if bad:
        raise InputError(f"{path}: non-finite values (NaN or infinity) in "
                         + ", ".join(f"{name} of {count} Gaussians" for name, count in bad.items())
                         + ": the file is corrupt or came from a diverged fit; refit or remove those Gaussians")

    scene_cameras = given if given is not None else _cameras(header, stored, path)

    tensors = {name: torch.from_numpy(np.ascontiguousarray(a)).to(device) for name, a in arrays.items()}
    model = GaussianModel(**tensors, sh_degree=header["sh_degree"])
    return Scene(model=model, cameras=scene_cameras, info=header["info"])


def _read_ply_scene(path: Path, given: Cameras | None, fix: str) -> tuple[dict, np.ndarray | None, dict]:
    """(clip header, camera records or None, the stored parameters as float32 numpy) of a PLY scene."""
    from tomgs.io.ply import ply_layout, read_ply

    # header read with a byte cap, element counts checked against the file's size, then memory-mapped:
    # each column is copied out once below
    fix = SCENE_FIX
    layout = ply_layout(path, "scene file", fix)
    ply = read_ply(path, "scene file", fix)
    names = [e.name for e in ply.elements]
    if not names or names[0] != "vertex":
        raise InputError(f"{path} has elements {names}; a scene's Gaussians are its first element, 'vertex': {fix}")
    vertex = ply["vertex"].data
    comments = list(ply.comments) + [c for e in ply.elements for c in e.comments]
    version = _version(comments, path, fix)
    if version == 2:
        header, stored = _read_trailer(path, layout.data_end, fix)
    elif version == 1:
        header, stored = _read_version_1(ply, comments, path, fix)
    else:  # no tomgs comment: a plain 3DGS file, or a scene that another tool re-saved
        header, stored = _bare_header(vertex, path), None
    degree = header["max_sh_degree"]

    not_numbers = [p for p in (vertex.dtype.names or ()) if vertex.dtype[p].kind not in "iuf"]
    if not_numbers:
        raise InputError(f"{path}: properties {', '.join(not_numbers[:6])} are lists; a scene's vertex properties "
                         f"are numbers: {fix}")
    required = [p for p in vertex_properties(degree) if p not in NORMALS]
    missing = [p for p in required if p not in (vertex.dtype.names or ())]
    if missing:
        shown = ", ".join(missing[:6]) + (f" and {len(missing) - 6} more" if len(missing) > 6 else "")
        plain = " (a static 3DGS file: it has no temporal opacity)" if set(TEMPORAL_PROPERTIES) <= set(missing) else ""
        raise InputError(f"{path}: vertex element lacks properties {shown} (SH degree {degree}){plain}: {fix}")
    extra_rest = [p for p in vertex.dtype.names if p.startswith("f_rest_") and p not in required]
    if extra_rest:
        raise InputError(f"{path}: vertex has {len(extra_rest)} more f_rest_ properties than SH degree {degree} "
                         f"allows (the header and the data disagree): {fix}")
    if stored is None and given is None:
        raise InputError(f"{path} holds Gaussians with temporal opacity but no cameras or frame times: a tool that "
                         "re-saved it (SuperSplat, splat-transform) drops them. Give them back with --cameras "
                         "cameras.json (tomgs.load_scene(..., cameras=...)); `tomgs export SCENE --cameras-out DIR` "
                         "writes that file from the original scene, `tomgs poses` from the video")

    n = len(vertex)

    def col(names_):  # float32 [N, len(names_)]
        return np.stack([np.asarray(vertex[p], dtype=np.float32) for p in names_], axis=1) if names_ \
            else np.zeros((n, 0), np.float32)

    rest = 3 * ((degree + 1) ** 2 - 1)
    arrays = {
        "means": col(["x", "y", "z"]),
        "sh_dc": col(["f_dc_0", "f_dc_1", "f_dc_2"]).reshape(n, 1, 3),
        "sh_rest": col([f"f_rest_{i}" for i in range(rest)]).reshape(n, 3, rest // 3).transpose(0, 2, 1),
        "opacity_logits": col(["opacity"])[:, 0],
        "log_scales": col(["scale_0", "scale_1", "scale_2"]),
        "quats": col(["rot_0", "rot_1", "rot_2", "rot_3"]),
        "t_means": col(["t_mean"])[:, 0],
        "log_t_scales": col(["t_log_sigma"])[:, 0],
    }
    return header, stored, arrays


def read_scene_clip(path, cameras=None) -> tuple[Cameras, dict]:
    """(cameras, info) of the scene file `path` without reading its Gaussians (nor importing torch):
    what a command checks its other arguments against before any work. `cameras` as `load_scene`
    takes it replaces the file's own. InputError as `load_scene` raises it for the header and the
    clip's data; the Gaussians themselves are checked when they are loaded."""
    from tomgs.io.ply import ply_layout, read_ply

    path = check_scene_path(path)
    given = _given_cameras(cameras)
    if tsog.is_tsog(path):
        header, stored = tsog.read_tsog_clip(path, CAMERA_RECORD, lambda clip: _checked_clip(clip, path, SCENE_FIX))
        return (given if given is not None else _cameras(header, stored, path)), header["info"]
    layout = ply_layout(path, "scene file", SCENE_FIX)
    if not layout.elements or layout.elements[0][0] != "vertex":
        names = [name for name, _ in layout.elements]
        raise InputError(f"{path} has elements {names}; a scene's Gaussians are its first element, 'vertex': "
                         f"{SCENE_FIX}")
    version = _version(layout.comments, path, SCENE_FIX)
    if version == 2:
        header, stored = _read_trailer(path, layout.data_end, SCENE_FIX)
    elif version == 1:
        ply = read_ply(path, "scene file", SCENE_FIX)
        header, stored = _read_version_1(ply, layout.comments, path, SCENE_FIX)
    else:
        header, stored = {"info": {}}, None
    if given is not None:
        return given, header["info"]
    if stored is None:
        raise InputError(f"{path} holds no cameras or frame times (a static 3DGS file, or a scene that another tool "
                         "re-saved): give them back with --cameras cameras.json; `tomgs export SCENE --cameras-out "
                         "DIR` writes that file from the original scene")
    return _cameras(header, stored, path), header["info"]


def _cameras(header: dict, stored: np.ndarray, path: Path) -> Cameras:
    """The Cameras of a scene's header and camera records (InputError naming the file when bad)."""
    try:  # Cameras checks sizes, poses, K, times and frame numbers
        return Cameras(stored["c2w"].reshape(-1, 4, 4), np.asarray(header["K"], dtype=np.float64),
                       header["width"], header["height"], stored["time"], stored["index"])
    except (ValueError, TypeError, OverflowError) as e:  # InputError from Cameras, or a K it cannot hold
        raise InputError(f"{path}: bad cameras ({str(e).removeprefix('Cameras: ')}): {SCENE_FIX}") from None


def _given_cameras(cameras) -> Cameras | None:
    """`load_scene`'s `cameras`: None, a Cameras, or the path of a cameras JSON (InputError if bad)."""
    if cameras is None or isinstance(cameras, Cameras):
        return cameras
    if isinstance(cameras, (str, Path)):
        return Cameras.load(cameras)
    raise TypeError(f"cameras must be a Cameras or the path of a cameras JSON file, got {type(cameras).__name__}")


def _version(comments: list[str], path: Path, fix: str) -> int | None:
    """The scene version its header comment declares: 2 ('tomgs-scene 2: ...'), 1 ('tomgs-scene {json}',
    the JSON checked later) or None when no comment starts with the tag."""
    tagged = [c.split(None, 1)[1:] for c in comments if c.split(None, 1)[:1] == [COMMENT_TAG]]
    if not tagged:
        return None
    rest = tagged[0][0].strip() if tagged[0] else ""
    if rest.startswith("{"):
        return 1
    number = rest.split(":", 1)[0].strip()
    if number.isascii() and number.isdigit() and int(number) in READS:
        return int(number)
    raise InputError(f"{path} is tomgs scene version {number[:20]}; this tomgs reads versions "
                     f"{', '.join(map(str, READS))}: install the tomgs that wrote it, or refit")


def _read_trailer(path: Path, data_end: int | None, fix: str) -> tuple[dict, np.ndarray]:
    """(header JSON, camera records [T] of CAMERA_RECORD) from the bytes after the vertex rows."""
    damaged = f"{path} is a damaged or truncated tomgs scene"
    size = path.stat().st_size
    lead = len(TRAILER_MAGIC) + 8
    if data_end is None or size < data_end + lead:
        raise InputError(f"{damaged}: the clip's cameras and settings after the Gaussians are missing: {fix}")
    with open(path, "rb") as f:
        f.seek(data_end)
        start = f.read(lead)
        if start[:len(TRAILER_MAGIC)] != TRAILER_MAGIC:
            raise InputError(f"{damaged}: the bytes after the Gaussians do not start the clip's data: {fix}")
        (length,) = struct.unpack("<Q", start[len(TRAILER_MAGIC):])
        if length > min(MAX_TRAILER_JSON, size - data_end - lead):
            raise InputError(f"{damaged}: its settings claim {length:,} bytes, more than the file holds after the "
                             f"Gaussians: {fix}")
        text = f.read(length)
    header = _checked_header(text, path, fix)
    count = header.get("cameras")
    left = size - data_end - lead - length
    if not (isinstance(count, int) and not isinstance(count, bool) and count >= 1
            and left == count * CAMERA_RECORD.itemsize):
        raise InputError(f"{damaged}: it declares {short_repr(count)} cameras but holds {left:,} bytes of camera "
                         f"records ({CAMERA_RECORD.itemsize} bytes each): {fix}")
    records = np.fromfile(path, dtype=CAMERA_RECORD, count=count, offset=data_end + lead + length)
    return header, records


def _read_version_1(ply, comments: list[str], path: Path, fix: str) -> tuple[dict, np.ndarray]:
    """Version 1: the header JSON in the tagged comment, the cameras in a PLY element `camera`."""
    text = next(c for c in comments if c.split(None, 1)[:1] == [COMMENT_TAG]).split(None, 1)[1]
    header = _checked_header(text, path, fix)
    if "camera" not in [e.name for e in ply.elements]:
        raise InputError(f"{path} has no 'camera' element; a version 1 tomgs scene keeps its cameras there "
                         f"(a tool that re-saved it may have dropped them): {fix}")
    camera = ply["camera"].data
    missing = [p for p in (*_C2W, "time", "index") if p not in (camera.dtype.names or ())]
    if missing:
        raise InputError(f"{path}: camera element lacks properties {', '.join(missing)}: {fix}")
    if any(camera.dtype[p].kind not in "iuf" for p in camera.dtype.names):
        raise InputError(f"{path}: camera properties must be numbers, not lists: {fix}")
    if len(camera) == 0:
        raise InputError(f"{path} holds zero cameras: a scene needs one per frame ({fix})")
    records = np.empty(len(camera), CAMERA_RECORD)
    records["c2w"] = np.stack([np.asarray(camera[p], dtype=np.float64) for p in _C2W], axis=1)
    records["time"] = camera["time"]
    try:
        records["index"] = camera["index"]
    except (OverflowError, ValueError, TypeError) as e:
        raise InputError(f"{path}: bad camera frame numbers ({e}): {fix}") from None
    return header, records


def _bare_header(vertex, path: Path) -> dict:
    """What a PLY without tomgs's comment implies: the SH degree from its f_rest_ count, all active,
    no info (its cameras must be given). Raises for an f_rest_ count no SH degree has."""
    rest = sum(1 for p in (vertex.dtype.names or ()) if p.startswith("f_rest_"))
    degrees = {3 * ((d + 1) ** 2 - 1): d for d in range(4)}
    if rest not in degrees:
        raise InputError(f"{path}: {rest} f_rest_ properties; SH degrees 0..3 have 0, 9, 24 or 45")
    return {"max_sh_degree": degrees[rest], "sh_degree": degrees[rest], "info": {}}


def _checked_header(text, path: Path, fix: str) -> dict:
    """The scene's header JSON (`text`, str or bytes), checked."""
    try:
        header = json.loads(text)
    except RecursionError:
        raise InputError(f"{path}: the scene's settings nest too deeply to read: {fix}") from None
    except (ValueError, UnicodeDecodeError) as e:  # JSONDecodeError, or a number of more than 4300 digits
        raise InputError(f"{path}: the scene's settings are not valid JSON ({str(e)[:200]}): {fix}") from None
    return _checked_clip(header, path, fix)


def _checked_clip(header, path: Path, fix: str) -> dict:
    """The scene's clip object (decoded JSON: size, K, SH degrees, info), its fields checked."""
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise InputError(f"{path}: the scene's settings lack \"format\": \"{FORMAT}\": {fix}")
    if header.get("version") not in READS:
        raise InputError(f"{path} is tomgs scene version {short_repr(header.get('version'))}; this tomgs reads "
                         f"versions {', '.join(map(str, READS))}: install the tomgs that wrote it, or refit")
    if _depth(header) > MAX_HEADER_DEPTH:
        raise InputError(f"{path}: the scene's settings nest deeper than {MAX_HEADER_DEPTH} levels; "
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
