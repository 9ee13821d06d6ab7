"""Edits of selected Gaussians: affine moves, duplicates, removal, keyframed motion, per-frame clouds.

Every move goes through the Gaussians' tetrahedra (`tomgs.edit.tets`): the selection's tets are
moved and the Gaussians follow (mean from the vertices, covariance F Sigma F^T), so an edit here
and the same motion done on exported tets in Blender give the same scene. Temporal parameters,
opacity and colour are carried over unchanged.

A static edit gives a new GaussianModel (a normal scene file). A time-varying edit (keyframes) or
an imported vertex sequence gives a per-frame cloud: a callable k -> the rasterizer's keyword
arguments for scene frame k, which `tomgs.render.render_sequence` renders with frame k's camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from tomgs.edit.tets import THICKEN, deform, gaussians_to_tets
from tomgs.errors import InputError
from tomgs.geometry import quat_to_rotmat, rotmat_to_quat

# ---- affine maps -------------------------------------------------------------------------------


def euler_to_rotmat(degrees) -> np.ndarray:
    """[3,3] rotation by rx, ry, rz degrees about the world x, then y, then z axis (R = Rz Ry Rx)."""
    rx, ry, rz = np.radians(np.asarray(degrees, dtype=np.float64))

    def axis(i, a):
        c, s = math.cos(a), math.sin(a)
        j, k = (i + 1) % 3, (i + 2) % 3
        R = np.eye(3)
        R[j, j], R[j, k], R[k, j], R[k, k] = c, -s, s, c
        return R

    return axis(2, rz) @ axis(1, ry) @ axis(0, rx)


def affine(translate=(0.0, 0.0, 0.0), rotate=(0.0, 0.0, 0.0), scale=1.0, centre=(0.0, 0.0, 0.0)) -> np.ndarray:
    """[4,4]: p -> centre + R diag(scale) (p - centre) + translate (rotate in degrees, `euler_to_rotmat`;
    scale a number or one per world axis)."""
    A = euler_to_rotmat(rotate) * np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,))[None, :]
    return _matrix(A, np.asarray(centre, dtype=np.float64), np.asarray(translate, dtype=np.float64))


def _matrix(A: np.ndarray, centre: np.ndarray, translate: np.ndarray) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = A
    M[:3, 3] = centre - A @ centre + translate
    return M


def selection_centre(model, indices) -> np.ndarray:
    """[3]: midpoint of the bounding box of the selected means (what rotate and scale turn about)."""
    means = model.means.detach().cpu().double().numpy()[indices]
    return 0.5 * (means.min(0) + means.max(0))


def transform_gaussians(means, quats, scales, matrix) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gaussians (means [n,3], quats [n,4], scales [n,3]) moved by the affine `matrix` [4,4] through
    their tets: the vertices are mapped and `deform` rebuilds them. float64 out."""
    M = np.asarray(matrix, dtype=np.float64)
    rest = gaussians_to_tets(means, quats, scales, thicken=THICKEN)
    return deform(rest, rest @ M[:3, :3].T + M[:3, 3], means, quats, scales)


# ---- static edits ------------------------------------------------------------------------------


def _geometry(model, indices) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return tuple(t.detach().cpu().double().numpy()[indices] for t in (model.means, model.quats, model.scales))


def _stored(model) -> dict[str, torch.Tensor]:
    from tomgs.model import PARAM_NAMES

    return {name: getattr(model, name).detach().clone() for name in PARAM_NAMES}


def _rebuilt(model, tensors):
    from tomgs.model import GaussianModel

    return GaussianModel(**tensors, sh_degree=model.sh_degree)


def _set_geometry(tensors: dict, rows, means, quats, scales) -> None:
    """Write float64 geometry into the stored tensors (log scales) at `rows`, in place."""
    from tomgs.model import stored_scales

    like = tensors["means"]
    tensors["means"][rows] = torch.as_tensor(means, dtype=like.dtype, device=like.device)
    tensors["quats"][rows] = torch.as_tensor(quats, dtype=like.dtype, device=like.device)
    tensors["log_scales"][rows] = torch.as_tensor(stored_scales(scales), dtype=like.dtype, device=like.device)


def edit_model(model, indices, matrix=None, duplicate=None, remove: bool = False):
    """(new GaussianModel, int64 indices of the edited Gaussians in it).

    remove: drop the selection `indices`. duplicate (dx, dy, dz): keep the selection and append a
    copy moved by `matrix` (when given) and then by the offset; the copy's indices are returned.
    Otherwise the selection is moved by `matrix` [4,4] in place. Everything else is unchanged."""
    indices = np.asarray(indices, dtype=np.int64)
    tensors = _stored(model)
    if remove:
        keep = torch.ones(len(model), dtype=torch.bool)
        keep[torch.as_tensor(indices)] = False
        keep = keep.to(tensors["means"].device)
        return _rebuilt(model, {k: v[keep] for k, v in tensors.items()}), np.zeros(0, dtype=np.int64)
    M = np.eye(4) if matrix is None else np.asarray(matrix, dtype=np.float64)
    if duplicate is not None:
        M = _matrix(np.eye(3), np.zeros(3), np.asarray(duplicate, dtype=np.float64)) @ M
    rows = indices
    if duplicate is not None:
        rows = np.arange(len(model), len(model) + len(indices))
        sel = torch.as_tensor(indices, device=tensors["means"].device)
        tensors = {k: torch.cat([v, v[sel]]) for k, v in tensors.items()}
    if not np.array_equal(M, np.eye(4)):
        _set_geometry(tensors, torch.as_tensor(rows), *transform_gaussians(*_geometry(model, indices), M))
    return _rebuilt(model, tensors), rows


# ---- keyframes ---------------------------------------------------------------------------------


def _slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    dot = float(q0 @ q1)
    if dot < 0:  # the shorter way round
        q1, dot = -q1, -dot
    if dot > 1 - 1e-12:
        q = q0 + u * (q1 - q0)
    else:
        theta = math.acos(dot)
        q = (math.sin((1 - u) * theta) * q0 + math.sin(u * theta) * q1) / math.sin(theta)
    return q / np.linalg.norm(q)


@dataclass
class Keyframes:
    """Keyframed transforms over clip time: times [K] ascending, translate [K,3], rotations [K,4]
    (quaternions w x y z), scale [K,3]; `hold` keeps the end poses outside [times[0], times[-1]]
    (else the selection is untouched there); `centre` [3] or None (the selection's centre)."""

    times: np.ndarray
    translate: np.ndarray
    rotations: np.ndarray
    scale: np.ndarray
    hold: bool = False
    centre: np.ndarray | None = None

    def matrix(self, t: float, centre) -> np.ndarray | None:
        """[4,4] at clip time t about `centre` (self.centre wins), or None outside the window."""
        times = self.times
        if not self.hold and not times[0] <= t <= times[-1]:
            return None
        t = min(max(t, times[0]), times[-1])
        i = min(int(np.searchsorted(times, t, side="right")) - 1, len(times) - 1)
        j = min(i + 1, len(times) - 1)
        u = 0.0 if j == i else (t - times[i]) / (times[j] - times[i])
        q = _slerp(self.rotations[i], self.rotations[j], u)
        A = quat_to_rotmat(q[None])[0] * ((1 - u) * self.scale[i] + u * self.scale[j])[None, :]
        c = np.asarray(centre if self.centre is None else self.centre, dtype=np.float64)
        return _matrix(A, c, (1 - u) * self.translate[i] + u * self.translate[j])


def load_keyframes(path, cameras) -> Keyframes:
    """Keyframes from JSON: {"keyframes": [{"t": 0.2 or "frame": 25, "translate": [dx,dy,dz],
    "rotate": [rx,ry,rz] (degrees), "scale": s or [sx,sy,sz]}, ...], "hold": false, "centre": [x,y,z]}.
    A key given by "frame" (a scene frame number) sits at that frame's time. Missing fields are the
    identity. InputError when malformed."""
    path = Path(path)
    fix = ('write {"keyframes": [{"t": 0.0, "translate": [0, 0, 0]}, {"t": 1.0, "translate": [0.5, 0, 0], '
           '"rotate": [0, 90, 0], "scale": 1.0}]}')
    if not path.is_file():
        raise InputError(f"keyframes file {path} does not exist: {fix}")
    from tomgs.io.cameras import load_json

    data = load_json(path, fix)
    try:
        if not isinstance(data, dict):
            raise ValueError("the file must hold a JSON object")
        keys = data["keyframes"]
        if not isinstance(keys, list) or not keys:
            raise ValueError("'keyframes' must be a non-empty list")
        frame_time = {int(n): float(t) for n, t in zip(cameras.frame_indices, cameras.times)}
        times, moves, rots, scales = [], [], [], []
        for key in keys:
            if not isinstance(key, dict):
                raise ValueError(f"each keyframe is an object, got {str(key)[:40]!r}")
            if "t" in key:
                times.append(float(key["t"]))
            elif int(key["frame"]) in frame_time:
                times.append(frame_time[int(key["frame"])])
            else:
                raise ValueError(f"frame {key['frame']} is not one of the scene's frames")
            moves.append(np.asarray(key.get("translate", (0, 0, 0)), dtype=np.float64).reshape(3))
            rots.append(rotmat_to_quat(euler_to_rotmat(np.asarray(key.get("rotate", (0, 0, 0)), dtype=np.float64)
                                                       .reshape(3))[None])[0])
            scales.append(np.broadcast_to(np.asarray(key.get("scale", 1.0), dtype=np.float64), (3,)).copy())
        centre = data.get("centre")
        centre = None if centre is None else np.asarray(centre, dtype=np.float64).reshape(3)
        hold = data.get("hold", False)
        if not isinstance(hold, bool):
            raise ValueError("'hold' must be true or false")
    except (KeyError, TypeError, ValueError, AttributeError, OverflowError, RecursionError) as e:
        raise InputError(f"{path}: bad keyframes ({type(e).__name__}: {str(e)[:200]}): {fix}") from None
    order = np.argsort(times, kind="stable")
    times = np.asarray(times)[order]
    if np.any(np.diff(times) <= 0):
        raise InputError(f"{path}: two keyframes share the time {times[np.argmin(np.diff(times))]}: {fix}")
    arrays = [np.stack(a)[order] for a in (moves, rots, scales)]
    if not all(np.isfinite(a).all() for a in [times, *arrays]) or (arrays[2] <= 0).any():
        raise InputError(f"{path}: keyframe values must be finite and scales positive: {fix}")
    return Keyframes(times, *arrays, hold=hold, centre=centre)


# ---- per-frame clouds --------------------------------------------------------------------------


def _replaced(base: dict, rows, means, quats, scales) -> dict:
    """A copy of render inputs `base` with the geometry of `rows` replaced (float64 -> float32)."""
    out = dict(base)
    rows = torch.as_tensor(rows)
    for name, value in (("means", means), ("quats", quats), ("scales", scales)):
        out[name] = base[name].clone()
        out[name][rows] = torch.as_tensor(value, dtype=base[name].dtype, device=base[name].device)
    return out


def _render_inputs(model) -> dict:
    with torch.no_grad():
        return {k: v.detach() for k, v in model.render_inputs().items()}


def keyframed_clouds(model, cameras, indices, keyframes: Keyframes):
    """k -> render inputs of scene frame k with the selection `indices` moved by `keyframes` at the
    frame's time about the selection's centre; frames outside the window get the unedited inputs."""
    base = _render_inputs(model)
    geometry = _geometry(model, indices)
    centre = selection_centre(model, indices)

    def cloud(k: int) -> dict:
        M = keyframes.matrix(float(cameras.times[k]), centre)
        if M is None:
            return base
        return _replaced(base, indices, *transform_gaussians(*geometry, M))

    return cloud


def deformed_geometry(model, tets, vertices) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The bound Gaussians (`tets.gaussians`) of `model` after the tets file's mesh moved to
    `vertices` [V,3] (world axes): (means, quats, scales) float64."""
    return deform(tets.gaussian_tets(), tets.gaussian_tets(vertices), *_geometry(model, tets.gaussians))


def sequence_clouds(model, tets, vertices, rows: dict[int, int]):
    """k -> render inputs of scene frame k (a position in the scene's cameras) with the bound Gaussians
    carried by row rows[k] of `vertices` [F,V,3] (world axes)."""
    base = _render_inputs(model)

    def cloud(k: int) -> dict:
        return _replaced(base, tets.gaussians, *deformed_geometry(model, tets, vertices[rows[k]]))

    return cloud


def deformed_model(model, tets, vertices):
    """A new GaussianModel: `model` with the bound Gaussians carried by `vertices` [V,3] (world axes)."""
    tensors = _stored(model)
    _set_geometry(tensors, torch.as_tensor(tets.gaussians), *deformed_geometry(model, tets, vertices))
    return _rebuilt(model, tensors)


def check_bound(model, tets, path) -> None:
    """InputError unless every Gaussian index of `tets` (read from `path`) exists in `model`."""
    if len(tets.gaussians) and (tets.gaussians.min() < 0 or tets.gaussians.max() >= len(model)):
        raise InputError(f"{path} binds Gaussian {int(tets.gaussians.max())} but the scene has {len(model):,}: "
                         f"import against the scene the tets were exported from")


# ---- scenes ------------------------------------------------------------------------------------


def edit_scene(scene, selectors=(), *, translate=None, rotate=None, scale=None, centre=None, duplicate=None,
               remove: bool = False):
    """(new Scene, int64 indices of the edited Gaussians in it) for the Gaussians `selectors` pick
    (`tomgs.edit.selection`; none = all): moved by translate (dx,dy,dz), rotate (rx,ry,rz degrees)
    and scale (s or sx,sy,sz) about `centre` (default the selection's centre), duplicated with an
    offset, or removed. Same cameras; the info gains an "edits" entry describing the edit."""
    from tomgs.edit.selection import select
    from tomgs.io.scene import Scene

    moving = any(v is not None for v in (translate, rotate, scale, duplicate))
    if remove and moving:
        raise InputError("remove deletes the selection: it cannot be combined with translate, rotate, scale or "
                         "duplicate (CLI: --remove with --translate, ...); make two edits")
    indices = select(scene.model, scene.cameras, selectors)
    if remove and len(indices) == len(scene.model):
        raise InputError("remove would delete every Gaussian of the scene: narrow the selection (CLI: --select)")
    c = selection_centre(scene.model, indices) if centre is None else np.asarray(centre, dtype=np.float64)
    matrix = None
    if any(v is not None for v in (translate, rotate, scale)):
        matrix = affine(translate if translate is not None else (0, 0, 0),
                        rotate if rotate is not None else (0, 0, 0), 1.0 if scale is None else scale, c)
    model, rows = edit_model(scene.model, indices, matrix, duplicate=duplicate, remove=remove)
    record = {"select": [getattr(s, "text", s) for s in selectors], "selected": int(len(indices)),
              "centre": c.tolist(), "translate": translate, "rotate": rotate, "scale": scale,
              "duplicate": duplicate, "remove": remove}
    record = {k: (list(v) if isinstance(v, tuple) else v) for k, v in record.items() if v not in (None, False)}
    info = {**scene.info, "edits": [*scene.info.get("edits", []), record]}
    return Scene(model, scene.cameras, info), rows


def sequence_rows(cameras, count: int, frames=None) -> dict[int, int]:
    """{camera position k: sequence row} for a sequence of `count` rows whose scene frame numbers are
    `frames` [count] (None: the scene's first `count` frames). InputError when a row has no frame."""
    if frames is None:
        if count > len(cameras):
            raise InputError(f"the sequence has {count} frames but the scene only {len(cameras)}: give at most "
                             f"{len(cameras)} rows, or an .npz 'frames' array naming each row's scene frame")
        return {k: k for k in range(count)}
    position = {int(n): k for k, n in enumerate(cameras.frame_indices)}
    missing = [int(n) for n in frames if int(n) not in position]
    if missing:
        raise InputError(f"the sequence's frame {missing[0]} is not a frame of the scene (numbers "
                         f"{int(cameras.frame_indices.min())}..{int(cameras.frame_indices.max())})")
    return {position[int(n)]: row for row, n in enumerate(frames)}
