"""A connected tet cage over selected Gaussians, with every Gaussian tet bound into it.

A soft body (Blender's, or `tomgs.edit.physics.simulate`) needs one connected mesh, not one loose
tet per Gaussian. The cage is a voxel grid over the Gaussians' means (cell size `cell`, default
1/8 of the largest extent), each occupied cell cut into the 6 tets of the Kuhn (Freudenthal)
split, whose shared faces match across neighbouring cells without alternating the pattern.

Binding: each of a Gaussian tet's 4 vertices gets barycentric weights in one cage tet (the one
containing it; when it lies outside the cage, the best tet of the nearest occupied cell). Weights
are not clamped, so interpolating the rest cage gives the Gaussian tets back exactly and any
affine motion of the cage moves them by the same affine map; after a cage moves,
`Tets.gaussian_tets(moved)` and `tomgs.edit.tets.deform` give the Gaussians.
"""

from __future__ import annotations

import itertools

import numpy as np

from tomgs.errors import InputError
from tomgs.io.tets import Tets

CELLS_PER_EXTENT = 8  # default cell size: the selection's largest extent / 8
MIN_CELL = 1e-6  # the finest cell: this share of the selection's size or distance from the origin
CHUNK = 4_000_000  # points x cells per batch in the nearest-cell search of points outside the cage


def _kuhn_tets() -> np.ndarray:
    """[6,4,3] corner offsets in {0,1}^3 of the unit cube's 6 tets along the diagonal 000-111,
    each ordered to positive volume."""
    out = []
    for a, b, _ in itertools.permutations(range(3)):
        e = np.eye(3, dtype=np.int64)
        tet = np.stack([np.zeros(3, dtype=np.int64), e[a], e[a] + e[b], np.ones(3, dtype=np.int64)])
        if np.linalg.det((tet[1:] - tet[0]).T.astype(float)) < 0:
            tet = tet[[0, 1, 3, 2]]
        out.append(tet)
    return np.stack(out)


KUHN = _kuhn_tets()


def default_cell(means) -> float:
    """The default cell size for Gaussians at `means` [N,3]: largest extent / 8 (1.0 for one point)."""
    means = np.asarray(means, dtype=np.float64)
    extent = float((means.max(0) - means.min(0)).max()) if len(means) else 0.0
    return extent / CELLS_PER_EXTENT if extent > 0 else 1.0


def build_cage(gaussian_tets, means, gaussians, cell: float | None = None) -> Tets:
    """A `cage` Tets over the Gaussians with rest tets `gaussian_tets` [G,4,3] and `means` [G,3]
    (scene indices `gaussians` [G]); `cell` is the grid spacing in scene units."""
    gaussian_tets = np.asarray(gaussian_tets, dtype=np.float64)
    means = np.asarray(means, dtype=np.float64)
    h = default_cell(means) if cell is None else float(cell)
    if not np.isfinite(h) or h <= 0:
        raise ValueError(f"cell size must be positive, got {cell}")
    origin = means.min(0)
    # a grid point is origin + k h in float32 (the tets file): h must stay above its resolution there
    finest = MIN_CELL * max(float(np.abs(means).max()) if len(means) else 0.0, default_cell(means), 1.0)
    if h < finest:
        raise InputError(f"--cell {cell:g}: a cage cell under {finest:.3g} scene units cannot be told apart from "
                         f"its neighbour where the selection lies (float32); give a larger --cell, or leave it out")
    top = np.maximum(np.ceil((means.max(0) - origin) / h).astype(np.int64) - 1, 0)  # the far faces close the grid
    cells = np.unique(np.minimum(np.floor((means - origin) / h).astype(np.int64), top), axis=0)  # [M,3] sorted
    corners = cells[:, None, None, :] + KUHN[None]  # [M,6,4,3] integer grid points
    grid, inverse = np.unique(corners.reshape(-1, 3), axis=0, return_inverse=True)
    tets = inverse.reshape(-1, 4).astype(np.int64)  # cell m owns tets 6m..6m+5
    vertices = origin + grid * h

    points = gaussian_tets.reshape(-1, 3)
    rest = vertices[tets]  # [T,4,3]
    inv_edges = np.linalg.inv(np.swapaxes(rest[:, 1:] - rest[:, :1], -1, -2))  # [T,3,3]
    cell_of = _cell_of(points, cells, origin, h)
    outside = np.flatnonzero(cell_of < 0)
    centres = origin + (cells + 0.5) * h
    step = max(1, CHUNK // len(cells))
    for start in range(0, len(outside), step):  # nearest occupied cell: distance from the point to its box
        rows = outside[start:start + step]
        gap = np.maximum(np.abs(points[rows, None, :] - centres[None]) - 0.5 * h, 0.0)
        cell_of[rows] = np.argmin((gap * gap).sum(-1), axis=1)
    binding_tet = np.empty(len(points), dtype=np.int64)
    weights = np.empty((len(points), 4))
    for start in range(0, len(points), CHUNK // 64):
        p = points[start:start + CHUNK // 64]
        candidates = 6 * cell_of[start:start + len(p), None] + np.arange(6)  # [P,6] the cell's tets
        lam = np.einsum("pkij,pkj->pki", inv_edges[candidates], p[:, None, :] - rest[candidates, 0])  # [P,6,3]
        bary = np.concatenate([1.0 - lam.sum(-1, keepdims=True), lam], axis=-1)  # [P,6,4]
        best = np.argmax(bary.min(-1), axis=1)  # inside: min >= 0; outside: the least extrapolated
        rows = np.arange(len(p))
        binding_tet[start:start + len(p)], weights[start:start + len(p)] = candidates[rows, best], bary[rows, best]
    return Tets("cage", vertices, tets, np.asarray(gaussians, dtype=np.int64), binding_tet, weights)


def _cell_of(points, cells, origin, h) -> np.ndarray:
    """[P] row in `cells` [M,3] (sorted, unique) of the grid cell holding each point, -1 if unoccupied."""
    lo, hi = cells.min(0), cells.max(0)
    dims = hi - lo + 1
    ijk = np.floor((points - origin) / h).astype(np.int64)
    inside = ((ijk >= lo) & (ijk <= hi)).all(1)

    def key(c):
        return ((c[:, 0] - lo[0]) * dims[1] + (c[:, 1] - lo[1])) * dims[2] + (c[:, 2] - lo[2])

    keys = key(cells)  # ascending: np.unique sorts rows lexicographically
    found = np.full(len(points), -1, dtype=np.int64)
    k = key(ijk[inside])
    pos = np.minimum(np.searchsorted(keys, k), len(keys) - 1)
    found[np.flatnonzero(inside)] = np.where(keys[pos] == k, pos, -1)
    return found


def make_tets(model, indices, kind: str = "gaussian", cell: float | None = None) -> Tets:
    """The tets of the Gaussians `indices` of `model` (a GaussianModel), world axes: kind `gaussian`
    (one tet per Gaussian, thin axes thickened by `THICKEN`) or `cage` (bound into a voxel cage of
    spacing `cell`, default 1/8 of the selection's largest extent)."""
    from tomgs.edit.tets import THICKEN, gaussians_to_tets
    from tomgs.io.tets import gaussian_tet_indices

    indices = np.asarray(indices, dtype=np.int64)
    means, quats, scales = (t.detach().cpu().double().numpy()[indices] for t in (model.means, model.quats,
                                                                                   model.scales))
    tets = gaussians_to_tets(means, quats, scales, thicken=THICKEN)
    if kind == "gaussian":
        return Tets("gaussian", tets.reshape(-1, 3), gaussian_tet_indices(len(indices)), indices)
    if kind == "cage":
        return build_cage(tets, means, indices, cell)
    raise ValueError(f"kind must be 'gaussian' or 'cage', got {kind!r}")


def shot_config(model, indices, frames: int, fps: float, size: float = 1.0, drop: float = 0.0, spin=None,
                velocity=None, stiffness: float | None = None, damping: float | None = None):
    """The SimConfig of `tomgs simulate`: gravity scaled so that the selection (Gaussians `indices`
    of `model`), whose largest side is `size` metres, falls like a real body of that size (+y is
    down in OpenCV axes); raised `drop` scene units; `spin` (rad/s, world axes) and `velocity`
    (scene units / s) at the start; `stiffness` is the inverse edge compliance; None keeps
    SimConfig's default."""
    from tomgs.edit.physics import EARTH_GRAVITY, SimConfig

    means = model.means.detach().cpu().double().numpy()[indices]
    extent = max(float((means.max(0) - means.min(0)).max()), 1e-9)
    optional = dict(initial_spin=spin, initial_velocity=velocity, damping=damping,
                    edge_compliance=None if stiffness is None else 1.0 / stiffness)
    return SimConfig(frames=frames, fps=fps, drop_height=drop, gravity=(0.0, EARTH_GRAVITY * extent / size, 0.0),
                     **{k: v for k, v in optional.items() if v is not None})


def simulate_selection(model, indices, config, cell: float | None = None, device: str = "cpu"):
    """(cage Tets, vertices float64 [F,V,3] world axes): a cage over the Gaussians `indices` of
    `model`, moved by `tomgs.edit.physics.simulate_with_stats` with `config` (a SimConfig) on `device`.
    Raises InputError when a cage tet turned inside out in some frame: the Gaussians bound to it would
    be mirrored, so the shot would be broken rather than merely soft."""
    from tomgs.edit.physics import simulate_with_stats
    from tomgs.errors import InputError

    cage = make_tets(model, indices, "cage", cell)
    result = simulate_with_stats(cage.vertices, cage.tets, config, device=device)
    if result.inverted_frames:
        frames = result.inverted_frames
        raise InputError(f"the simulation turned cage tets inside out in {len(frames)} frame(s), first frame "
                         f"{frames[0]} (smallest volume ratio {result.min_volume_ratio:.3g}): use a larger cage cell, stiffer edges (a smaller "
                         "edge_compliance) or a gentler start (drop_height, initial_spin, initial_velocity; CLI: "
                         "--cell, --stiffness, --drop, --spin, --velocity)")
    return cage, result.vertices
