"""The bundled examples: a small procedural TOM-GS scene (what `tomgs demo` renders) and the files
shipped in the package (`tomgs example`: a video clip to fit and the Blender soft-body script).

A checkered wall and floor made of flat static Gaussians, and a ball that moves, represented the
TOM-GS way: one copy of the ball per key position, each copy's opacity fading in and out around
its time, so the ball appears to travel although every Gaussian is static. The camera dollies
and pans across the clip.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from tomgs.cameras import Cameras, frame_times, intrinsics, look_at

GAUSSIAN_FIELDS = ("means", "quats", "scales", "opacities", "colors", "t_means", "t_scales")

# the files shipped in tomgs/data, each with what it is for
EXAMPLE_FILES = {
    "bunny.mp4": "32 frames of Big Buck Bunny at 128x72 to fit (licence: LICENSE-bunny.txt)",
    "blender_softbody.py": "drops a `tomgs tets export --cage` cage in Blender, headless",
    "LICENSE-bunny.txt": "the licence of bunny.mp4 (CC BY 3.0, Blender Foundation)",
}


def example_file(name: str) -> Path:
    """The installed path of a bundled example file (one of EXAMPLE_FILES)."""
    from importlib.resources import files

    from tomgs.errors import InputError

    if name not in EXAMPLE_FILES:
        raise InputError(f"no example file {name!r}; the examples are {', '.join(EXAMPLE_FILES)}")
    return Path(str(files("tomgs") / "data" / name))


def _plane(origin, u_axis, v_axis, nu: int, nv: int, spacing: float, palette) -> dict[str, np.ndarray]:
    """Flat Gaussians on a grid: a checkerboard of two colours with a soft gradient."""
    iu, iv = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    iu, iv = iu.ravel(), iv.ravel()
    u_axis, v_axis = np.asarray(u_axis, float), np.asarray(v_axis, float)
    means = np.asarray(origin, float) + np.outer(iu * spacing, u_axis) + np.outer(iv * spacing, v_axis)
    checker = ((iu // 3 + iv // 3) % 2)[:, None]
    shade = 0.75 + 0.25 * (iu / max(nu - 1, 1))[:, None]
    colors = np.where(checker == 1, palette[0], palette[1]) * shade
    normal = np.cross(u_axis, v_axis)
    rot = np.stack([u_axis, v_axis, normal], axis=1)  # columns: the Gaussian's axes
    quat = _quat_from_matrix(rot)
    n = means.shape[0]
    return dict(means=means, quats=np.tile(quat, (n, 1)), scales=np.tile([spacing * 0.6, spacing * 0.6, 1e-3], (n, 1)),
                opacities=np.full(n, 0.95), colors=colors, t_means=np.full(n, 0.5), t_scales=np.full(n, 10.0))


def _quat_from_matrix(r: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a proper rotation matrix."""
    w = math.sqrt(max(1.0 + r[0, 0] + r[1, 1] + r[2, 2], 1e-12)) / 2.0
    return np.array([w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w)])


def _ball(rng: np.random.Generator, keys: int, per_copy: int) -> dict[str, np.ndarray]:
    """`keys` copies of a ball along a bouncing path, copy k alive around t = k / (keys - 1)."""
    s = np.linspace(0.0, 1.0, keys)
    path = np.stack([-1.6 + 3.2 * s, 0.9 - 1.3 * np.abs(np.sin(2.5 * math.pi * s)), 4.2 + 0.0 * s], axis=1)
    offsets = rng.normal(size=(per_copy, 3))
    offsets = 0.28 * offsets / np.linalg.norm(offsets, axis=1, keepdims=True) * rng.uniform(0.3, 1.0, (per_copy, 1))
    means = (path[:, None, :] + offsets[None]).reshape(-1, 3)
    hue = np.clip(0.5 + offsets[:, 1:2] * 1.5, 0, 1)
    colors = np.tile(np.concatenate([0.95 * np.ones_like(hue), 0.35 + 0.4 * hue, 0.15 * np.ones_like(hue)], 1), (keys, 1))
    n = means.shape[0]
    sigma = 0.35 / (keys - 1)  # neighbouring copies overlap a little in time: the motion reads as continuous
    return dict(means=means, quats=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), scales=np.full((n, 3), 0.09),
                opacities=np.full(n, 0.9), colors=colors, t_means=np.repeat(s, per_copy),
                t_scales=np.full(n, sigma))


def demo_scene(num_frames: int = 48, width: int = 320, height: int = 180, seed: int = 0
               ) -> tuple[dict[str, torch.Tensor], Cameras]:
    """(Gaussians as float32 tensors keyed by GAUSSIAN_FIELDS, cameras of the clip)."""
    rng = np.random.default_rng(seed)
    wall = _plane([-3.6, -1.6, 6.0], [1, 0, 0], [0, 1, 0], 52, 20, 0.15, np.array([[0.85, 0.85, 0.8], [0.2, 0.35, 0.6]]))
    floor = _plane([-3.6, 1.4, 2.0], [1, 0, 0], [0, 0, 1], 52, 27, 0.15, np.array([[0.8, 0.8, 0.75], [0.3, 0.3, 0.3]]))
    ball = _ball(rng, keys=32, per_copy=40)
    parts = (wall, floor, ball)
    gaussians = {k: torch.as_tensor(np.concatenate([p[k] for p in parts]), dtype=torch.float32) for k in GAUSSIAN_FIELDS}

    t = frame_times(num_frames)
    c2w = np.stack([look_at([-0.4 + 0.8 * tk, -0.3, -0.3 * tk], [0.2 * tk, 0.2, 5.0]) for tk in t])
    to_first = np.linalg.inv(c2w[0])  # re-anchor the world so that frame 0 is the identity pose
    c2w = to_first @ c2w
    gaussians["means"] = gaussians["means"] @ torch.as_tensor(to_first[:3, :3].T, dtype=torch.float32) \
        + torch.as_tensor(to_first[:3, 3], dtype=torch.float32)
    gaussians["quats"] = _rotate_quats(gaussians["quats"], to_first[:3, :3])
    cams = Cameras.create(c2w, intrinsics(0.9 * width, width, height), width, height)
    return gaussians, cams


def _rotate_quats(quats: torch.Tensor, rot: np.ndarray) -> torch.Tensor:
    """Quaternions of R_world * R_i for a world rotation `rot`."""
    w0, x0, y0, z0 = torch.as_tensor(_quat_from_matrix(rot), dtype=quats.dtype)
    w, x, y, z = quats.unbind(-1)
    return torch.stack([w0 * w - x0 * x - y0 * y - z0 * z, w0 * x + x0 * w + y0 * z - z0 * y,
                        w0 * y - x0 * z + y0 * w + z0 * x, w0 * z + x0 * y - y0 * x + z0 * w], -1)
