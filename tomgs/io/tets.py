"""Tetrahedra files (PLY) and per-frame vertex sequences, the formats Blender and the simulator share.

Tets file, binary little endian PLY, coordinates in Blender axes (Z up):
    p_blender = W p_world, W = [[1,0,0],[0,0,1],[0,-1,0]] (det +1: orientation kept); loading
    applies W^T. So world (0,-1,0), "up" in OpenCV axes, is z = +1 in the file.
    comments: `tomgs tets 1`, `kind gaussian` or `kind cage`, `axes blender`
    element vertex V      float x, y, z
    element face 4T       list uchar int vertex_indices: 4 outward triangles per tet (Blender shows
                          each tet as a closed surface; a cage lists shared faces twice)
    element tet T         list uchar int vertex_indices: 4 each, positive volume
    element gaussian G    int index: the scene index of each bound Gaussian, in order
    element binding 4G    (cage only) int tet, float b0 b1 b2 b3: Gaussian-tet vertex r of Gaussian g
                          (row 4g + r) = sum_j b_j * vertex[tet[tet_row][j]]
Kind `gaussian`: V = 4G and Gaussian g owns vertices 4g..4g+3 in the order of
`tomgs.edit.tets.DIRECTIONS`; its `tet` row lists them as 4g + POSITIVE_ORDER (0, 1, 3, 2), of positive volume.
Kind `cage`: a connected tet mesh (what a soft body moves) with every Gaussian tet bound into it.
Blender imports vertex + face and skips the rest; keep "merge vertices" off so the order survives.

Sequence: an `.npz` with `vertices` float32 [F,V,3] (Blender axes) and optional `frames` int [F] (the
scene frame numbers of the rows; default the scene's first F frames), or a folder of PLY files (any
names, natural sort order) or a single PLY file, each with a `vertex` element of V vertices.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tomgs.errors import InputError
from tomgs.geometry import signed_volumes
from tomgs.io.ply import read_ply
from tomgs.outputs import atomic_file

W = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # world (OpenCV) -> Blender axes
KINDS = ("gaussian", "cage")
# outward triangles of a positively oriented tet (a, b, c, d), as positions into its 4 vertices
FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
POSITIVE_ORDER = (0, 1, 3, 2)  # a Gaussian's 4 vertices (in DIRECTIONS' order) as a tet of positive volume


def to_blender(points) -> np.ndarray:
    """World (OpenCV) points [..., 3] -> Blender axes."""
    return np.asarray(points, dtype=np.float64) @ W.T


def from_blender(points) -> np.ndarray:
    """Blender-axes points [..., 3] -> world (OpenCV) axes."""
    return np.asarray(points, dtype=np.float64) @ W


@dataclass
class Tets:
    """A tets file in memory, world axes. vertices float64 [V,3] (rest pose); tets int64 [T,4]
    (positive volume); gaussians int64 [G] (scene indices); for a cage binding_tet int64 [4G] and
    binding_weights float64 [4G,4] (rows sum to 1), else None."""

    kind: str
    vertices: np.ndarray
    tets: np.ndarray
    gaussians: np.ndarray
    binding_tet: np.ndarray | None = None
    binding_weights: np.ndarray | None = None

    def gaussian_tets(self, vertices=None) -> np.ndarray:
        """[G,4,3]: each bound Gaussian's tet for cage/mesh vertices [V,3] (default: the rest pose)."""
        x = self.vertices if vertices is None else np.asarray(vertices, dtype=np.float64)
        if self.kind == "gaussian":
            return x.reshape(-1, 4, 3)
        corners = x[self.tets[self.binding_tet]]  # [4G,4,3]
        return np.einsum("nj,njc->nc", self.binding_weights, corners).reshape(-1, 4, 3)


def gaussian_tet_indices(count: int) -> np.ndarray:
    """[G,4]: the positive-volume `tet` rows of a `gaussian` tets file of G Gaussians."""
    return 4 * np.arange(count, dtype=np.int64)[:, None] + np.array(POSITIVE_ORDER)


# ---- tets files --------------------------------------------------------------------------------

def save_tets(path, tets: Tets) -> Path:
    """Write `tets` to the PLY file `path` in Blender axes, atomically."""
    from plyfile import PlyData, PlyElement

    path = Path(path)
    if tets.kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {tets.kind!r}")
    V, T, G = len(tets.vertices), len(tets.tets), len(tets.gaussians)
    vertex = np.empty(V, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    blender = to_blender(tets.vertices)
    for j, name in enumerate("xyz"):
        vertex[name] = blender[:, j]
    faces = np.empty(4 * T, dtype=[("vertex_indices", "<i4", (3,))])
    faces["vertex_indices"] = tets.tets[:, FACES].reshape(-1, 3)
    rows = np.empty(T, dtype=[("vertex_indices", "<i4", (4,))])
    rows["vertex_indices"] = tets.tets
    gaussian = np.empty(G, dtype=[("index", "<i4")])
    gaussian["index"] = tets.gaussians
    lists = dict(len_types={"vertex_indices": "u1"}, val_types={"vertex_indices": "i4"})
    elements = [PlyElement.describe(vertex, "vertex"), PlyElement.describe(faces, "face", **lists),
                PlyElement.describe(rows, "tet", **lists), PlyElement.describe(gaussian, "gaussian")]
    if tets.kind == "cage":
        binding = np.empty(4 * G, dtype=[("tet", "<i4")] + [(f"b{j}", "<f4") for j in range(4)])
        binding["tet"] = tets.binding_tet
        for j in range(4):
            binding[f"b{j}"] = tets.binding_weights[:, j]
        elements.append(PlyElement.describe(binding, "binding"))
    ply = PlyData(elements, text=False, byte_order="<",
                  comments=["tomgs tets 1", f"kind {tets.kind}", "axes blender"])
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        ply.write(f)
    return path


def _xyz(ply, path: Path) -> np.ndarray:
    """[V,3] float64 Blender-axes positions of the `vertex` element."""
    try:
        v = ply["vertex"].data
        if any(v.dtype[c].kind not in "iuf" for c in "xyz"):
            raise ValueError("x, y and z must be numbers, not lists")
        return np.stack([np.asarray(v[c], dtype=np.float64) for c in "xyz"], axis=1)
    except (KeyError, ValueError, TypeError) as e:
        raise InputError(f"{path}: no vertex element with x, y, z ({e})") from None


def _integers(values, what: str) -> np.ndarray:
    """int64 copy of an integer column (a list property's rows stacked); ValueError for anything else."""
    values = np.asarray(values)
    if values.dtype == object:  # a variable-length list property: one array per row
        values = np.stack([np.asarray(r) for r in values]) if len(values) else np.zeros((0, 4), np.int64)
    if values.dtype.kind not in "iu":
        raise ValueError(f"{what} must be integers, got {values.dtype}")
    return values.astype(np.int64)


def load_tets(path) -> Tets:
    """Read a tets file written by `save_tets` (world axes back); InputError when malformed."""
    path = Path(path)
    fix = "export one with `tomgs tets export`"
    ply = read_ply(path, "tets file", fix, known_list_len={"face": {"vertex_indices": 3}, "tet": {"vertex_indices": 4}})
    comments = [c.strip() for c in ply.comments]
    if "tomgs tets 1" not in comments:
        raise InputError(f"{path} is not a tomgs tets file (no 'tomgs tets 1' comment): {fix}")
    kinds = [c.split()[1] for c in comments if c.startswith("kind ") and len(c.split()) == 2]
    if len(kinds) != 1 or kinds[0] not in KINDS or "axes blender" not in comments:
        raise InputError(f"{path}: the comments must name one kind ({' or '.join(KINDS)}) and 'axes blender': {fix}")
    kind = kinds[0]
    names = {e.name for e in ply.elements}
    need = {"vertex", "tet", "gaussian"} | ({"binding"} if kind == "cage" else set())
    if need - names:
        raise InputError(f"{path} lacks element(s) {', '.join(sorted(need - names))}: {fix}")
    vertices = from_blender(_xyz(ply, path))
    try:
        tets = _integers(ply["tet"].data["vertex_indices"], "tet vertex indices")
        gaussians = _integers(ply["gaussian"].data["index"], "gaussian indices")
        if gaussians.ndim != 1:
            raise ValueError("gaussian indices must be one integer per row")
    except (ValueError, KeyError, TypeError) as e:
        raise InputError(f"{path}: bad tet or gaussian element ({e}): {fix}") from None
    V, G = len(vertices), len(gaussians)
    if tets.ndim != 2 or tets.shape[1] != 4 or len(tets) == 0 or tets.min() < 0 or tets.max() >= V:
        raise InputError(f"{path}: tets must be rows of 4 vertex indices in 0..{V - 1}: {fix}")
    if not np.isfinite(vertices).all():
        raise InputError(f"{path}: non-finite vertex coordinates: {fix}")
    bad = np.flatnonzero(signed_volumes(vertices, tets) <= 0)
    if len(bad):
        raise InputError(f"{path}: tet {bad[0]} (and {len(bad) - 1} more) has non-positive volume: {fix}")
    out = Tets(kind, vertices, tets, gaussians)
    if kind == "gaussian":
        if V != 4 * G or not np.array_equal(tets, gaussian_tet_indices(G)):
            raise InputError(f"{path}: a 'gaussian' tets file holds 4 vertices and one tet per Gaussian "
                             f"(has {V} vertices, {len(tets)} tets, {G} Gaussians): {fix}")
        return out
    b = ply["binding"].data
    try:
        out.binding_tet = _integers(b["tet"], "binding tets")
        if out.binding_tet.ndim != 1 or any(b.dtype[f"b{j}"].kind not in "iuf" for j in range(4)):
            raise ValueError("the binding has one tet index and four numbers b0..b3 per row")
        weights = np.stack([np.asarray(b[f"b{j}"], dtype=np.float64) for j in range(4)], axis=1)
    except (ValueError, KeyError, TypeError) as e:
        raise InputError(f"{path}: bad binding element ({e}): {fix}") from None
    in_range = len(out.binding_tet) == 0 or (out.binding_tet.min() >= 0 and out.binding_tet.max() < len(tets))
    if len(out.binding_tet) != 4 * G or not in_range \
            or not np.isfinite(weights).all() or (np.abs(weights.sum(1) - 1) > 1e-3).any():
        raise InputError(f"{path}: the binding must have 4 rows per Gaussian ({4 * G}), tet indices below "
                         f"{len(tets)} and weights summing to 1: {fix}")
    out.binding_weights = weights / weights.sum(1, keepdims=True)  # float32 on disk: sum exactly 1 again
    return out


# ---- sequences ---------------------------------------------------------------------------------

def save_sequence(path, vertices, frames=None) -> Path:
    """Write per-frame vertices [F,V,3] (world axes) and optional scene frame numbers [F] as an .npz
    (Blender axes, float32), atomically."""
    path = Path(path)
    if path.suffix.lower() != ".npz":
        raise InputError(f"{path}: a vertex sequence is written as .npz; give a path ending in .npz")
    arrays = {"vertices": to_blender(vertices).astype(np.float32)}
    if frames is not None:
        arrays["frames"] = np.asarray(frames, dtype=np.int64)
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)
    return path


DEFLATE_MAX_RATIO = 1032
"""Deflate codes at most 258 bytes in a match of at least 2 bits: no deflated member expands to more
than about 1032 times its compressed size, so a zip directory that says more is lying."""


def read_npz(path, check, names, fix: str, required=()) -> dict:
    """{name: array} for each of `names` that the .npz at `path` holds (those in `required` must be
    there), read without trusting any size in the file: the zip directory's uncompressed size of a
    member must be what its compressed bytes can hold (stored: equal; deflated: DEFLATE_MAX_RATIO
    times) and exactly the .npy header plus the array that header declares; `check(name, shape,
    dtype)` sees the declared shape and dtype (and raises InputError) before any data is decompressed.
    InputError naming the file for anything else: not a zip, a bad CRC, pickled objects, ..."""
    import zipfile
    import zlib

    from tomgs.io.cameras import npy_header

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path} does not exist" + (" (it is a folder)" if path.is_dir() else "") + f": {fix}")
    out = {}
    try:
        with zipfile.ZipFile(path) as z:
            members = {info.filename: info for info in z.infolist()}
            for name in names:
                info = members.get(name + ".npy")
                if info is None:
                    if name in required:
                        raise InputError(f"{path} has no array {name!r} (it holds "
                                         f"{', '.join(sorted(members))[:200] or 'nothing'}): {fix}")
                    continue
                where = f"{path}, array {name!r}"
                if info.compress_type == zipfile.ZIP_STORED:
                    can_hold = info.compress_size
                elif info.compress_type == zipfile.ZIP_DEFLATED:
                    can_hold = DEFLATE_MAX_RATIO * info.compress_size + 1024
                else:
                    raise InputError(f"{where}: compression method {info.compress_type} is not one numpy writes "
                                     f"(stored or deflated): {fix}")
                if info.file_size > can_hold or info.compress_size > path.stat().st_size:
                    raise InputError(f"{where}: the zip directory says it expands to {info.file_size:,} bytes, "
                                     f"more than its {info.compress_size:,} compressed bytes can hold: {fix}")
                with z.open(info) as f:
                    shape, dtype, fortran, offset = npy_header(f, where)
                    nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
                    if info.file_size != offset + nbytes:
                        raise InputError(f"{where}: its header declares a {dtype} array of shape {list(shape)} "
                                         f"({nbytes:,} bytes), but the zip says {info.file_size - offset:,} bytes "
                                         f"follow: {fix}")
                    check(name, shape, dtype)
                    buffer = bytearray(nbytes)
                    view, got = memoryview(buffer), 0
                    while got < nbytes:
                        n = f.readinto(view[got:])
                        if not n:
                            raise InputError(f"{where}: the data ends after {got:,} of {nbytes:,} bytes: {fix}")
                        got += n
                    f.read(1)  # reach the end, where zipfile checks the CRC
                out[name] = np.frombuffer(buffer, dtype=dtype).reshape(shape, order="F" if fortran else "C")
    except InputError:
        raise
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, NotImplementedError, KeyError,
            OverflowError, RuntimeError) as e:  # RuntimeError: an encrypted member
        raise InputError(f"{path} is not a readable .npz file ({str(e)[:200]}): {fix}") from None
    return out


def load_sequence(path, like: Tets, max_frames: int | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """(vertices float64 [F,V,3] in world axes, frames int64 [F] or None) from an .npz, a folder of
    PLY files or one PLY file. Checked against `like` (the tets file the vertices move): the vertex
    count, finite values and no inverted tet, else InputError naming the frame. `max_frames` (the
    scene's frame count, when known): more rows are refused before they are read."""
    from tomgs.io.video import natural_key

    path = Path(path)
    V = len(like.vertices)
    frames = None
    fix = "an .npz sequence holds 'vertices' [F,V,3] (Blender axes) and optional 'frames' [F]"

    def check_count(count: int, where) -> None:
        if max_frames is not None and count > max_frames:
            raise InputError(f"{where} has {count:,} frames but the scene only {max_frames:,}: give at most "
                             f"{max_frames:,}, one per scene frame")

    if path.is_dir():
        files = sorted((p for p in path.iterdir() if p.suffix.lower() == ".ply"), key=natural_key)
        if not files:
            raise InputError(f"sequence folder {path} holds no .ply files: give one PLY of moved vertices per frame")
        check_count(len(files), path)
        names = [str(p) for p in files]
        rows = [_xyz(read_ply(p, "sequence frame"), p) for p in files]
    elif path.suffix.lower() == ".ply":
        names, rows = [str(path)], [_xyz(read_ply(path, "sequence file"), path)]
    elif path.suffix.lower() == ".npz":
        if not path.is_file():
            raise InputError(f"sequence file {path} does not exist")

        def check(name, shape, dtype):
            if name == "vertices":
                if len(shape) != 3 or shape[2] != 3 or shape[0] < 1:
                    raise InputError(f"{path}: 'vertices' must have shape [F,V,3] with F >= 1, got {list(shape)}")
                if shape[1] != V:
                    raise InputError(f"{path} row 0: {shape[1]} vertices, but the tets file has {V}: move the "
                                     f"exported vertices without adding or removing any")
                check_count(shape[0], path)
                if dtype.kind != "f":
                    raise InputError(f"{path}: 'vertices' must be floats, got {dtype}")
            elif shape != (len(arrays["vertices"]),) or dtype.kind not in "iu":
                raise InputError(f"{path}: 'frames' must have one scene frame number per row "
                                 f"({len(arrays['vertices'])}), got {dtype} of shape {list(shape)}")

        arrays = {}
        arrays.update(read_npz(path, check, ["vertices"], fix, required=["vertices"]))
        arrays.update(read_npz(path, check, ["frames"], fix))
        rows = arrays["vertices"].astype(np.float64)
        if "frames" in arrays:
            frames = arrays["frames"].astype(np.int64)
        names = [f"{path} row {f}" for f in range(len(rows))]
    else:
        raise InputError(f"{path}: a vertex sequence is an .npz file, a folder of .ply files or one .ply file")
    for name, row in zip(names, rows):
        if row.shape != (V, 3):
            raise InputError(f"{name}: {row.shape[0]} vertices, but the tets file has {V}: "
                             f"move the exported vertices without adding or removing any")
        if not np.isfinite(row).all():
            raise InputError(f"{name}: NaN or infinite vertex coordinates; re-export the frame")
    vertices = from_blender(rows if isinstance(rows, np.ndarray) else np.stack(rows))
    inverted = signed_volumes(vertices, like.tets) <= 0  # [F,T]
    if inverted.any():
        f, t = np.argwhere(inverted)[0]
        raise InputError(f"{names[f]}: tet {t} is inverted (non-positive volume) with {int(inverted[f].sum())} "
                         f"others in that frame; the motion turned tets inside out: simulate with smaller steps "
                         f"or stiffer tets")
    return vertices, frames
