"""The bundled examples: a small procedural TOM-GS scene (what `tomgs demo` renders) and the files
shipped in the package (`tomgs example`, tomgs.data: a clip to fit, with the masks of its moving
object, and the Blender soft-body script).

A checkered wall and floor made of flat static Gaussians, and a ball that moves, represented the
TOM-GS way: one copy of the ball per key position, each copy's opacity fading in and out around
its time, so the ball appears to travel although every Gaussian is static. The demo's camera
dollies and pans across the clip. The bundled clip (`write_example`, tomgs/data/ball.mp4) is the
same kind of room with a tiled wall and floor that a tracker can follow, a ball that bounces in front
of them, and a camera that moves sideways (parallax: the poses and depth of a fit are real); its
masks are the ball's own alpha.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from tomgs.cameras import Cameras, frame_times, intrinsics, look_at

GAUSSIAN_FIELDS = ("means", "quats", "scales", "opacities", "colors", "t_means", "t_scales")

EXAMPLE_CLIP = dict(num_frames=40, width=160, height=96)  # what write_example renders
EXAMPLE_BACKGROUND = (0.05, 0.05, 0.08)


def _plane(origin, u_axis, v_axis, nu: int, nv: int, spacing: float, palette=None, rng=None
           ) -> dict[str, np.ndarray]:
    """Flat Gaussians on a grid: a checkerboard of the two colours of `palette` with a soft gradient,
    or (palette None) tiles of 2 x 2 Gaussians in colours drawn from `rng`."""
    iu, iv = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    iu, iv = iu.ravel(), iv.ravel()
    u_axis, v_axis = np.asarray(u_axis, float), np.asarray(v_axis, float)
    means = np.asarray(origin, float) + np.outer(iu * spacing, u_axis) + np.outer(iv * spacing, v_axis)
    if palette is None:
        tiles = 0.2 + 0.7 * rng.uniform(0.0, 1.0, size=(nu // 2 + 1, nv // 2 + 1, 1)) ** 0.8 * \
            rng.uniform(0.5, 1.0, size=(nu // 2 + 1, nv // 2 + 1, 3))
        colors = tiles[iu // 2, iv // 2]
    else:
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


def _demo_path(s: np.ndarray) -> np.ndarray:
    """[K,3]: the demo's ball at clip times `s`, bouncing across the room."""
    return np.stack([-1.6 + 3.2 * s, 0.9 - 1.3 * np.abs(np.sin(2.5 * math.pi * s)), 4.2 + 0.0 * s], axis=1)


def _ball(rng: np.random.Generator, keys: int, per_copy: int, path=_demo_path, radius: float = 0.28,
          size: float = 0.09, sigma: float = 0.35) -> dict[str, np.ndarray]:
    """`keys` copies of a ball of `radius` along `path` (clip times [K] -> points [K,3]), each of
    `per_copy` Gaussians of scale `size`; copy k alive around t = k / (keys - 1) with a temporal sigma
    of `sigma` times the gap between copies."""
    s = np.linspace(0.0, 1.0, keys)
    path = path(s)
    offsets = rng.normal(size=(per_copy, 3))
    offsets = radius * offsets / np.linalg.norm(offsets, axis=1, keepdims=True) * rng.uniform(0.3, 1.0, (per_copy, 1))
    means = (path[:, None, :] + offsets[None]).reshape(-1, 3)
    hue = np.clip(0.5 + offsets[:, 1:2] * 1.5, 0, 1)
    colors = np.tile(np.concatenate([0.95 * np.ones_like(hue), 0.35 + 0.4 * hue, 0.15 * np.ones_like(hue)], 1), (keys, 1))
    n = means.shape[0]
    sigma = sigma / (keys - 1)  # neighbouring copies overlap a little in time: the motion reads as continuous
    return dict(means=means, quats=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), scales=np.full((n, 3), size),
                opacities=np.full(n, 0.9), colors=colors, t_means=np.repeat(s, per_copy),
                t_scales=np.full(n, sigma))


def demo_scene(num_frames: int = 48, width: int = 320, height: int = 180, seed: int = 0
               ) -> tuple[dict[str, torch.Tensor], Cameras]:
    """(Gaussians as float32 tensors keyed by GAUSSIAN_FIELDS, cameras of the clip)."""
    rng = np.random.default_rng(seed)
    wall = _plane([-3.6, -1.6, 6.0], [1, 0, 0], [0, 1, 0], 52, 20, 0.15, np.array([[0.85, 0.85, 0.8], [0.2, 0.35, 0.6]]))
    floor = _plane([-3.6, 1.4, 2.0], [1, 0, 0], [0, 0, 1], 52, 27, 0.15, np.array([[0.8, 0.8, 0.75], [0.3, 0.3, 0.3]]))
    ball = _ball(rng, keys=32, per_copy=40)
    t = frame_times(num_frames)
    c2w = np.stack([look_at([-0.4 + 0.8 * tk, -0.3, -0.3 * tk], [0.2 * tk, 0.2, 5.0]) for tk in t])
    return _anchored((wall, floor, ball), c2w, width, height)


def example_scene(num_frames: int = 40, width: int = 160, height: int = 96, seed: int = 1
                  ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor], Cameras]:
    """(the room's Gaussians, the ball's Gaussians, cameras) of the bundled clip: a wall and a floor of
    tiles in random colours (corners a tracker follows), a ball bouncing across in front of them, a
    camera that moves sideways along x (and a little forward) looking ahead."""
    rng = np.random.default_rng(seed)
    wall = _plane([-3.0, -1.6, 5.0], [1, 0, 0], [0, 1, 0], 50, 24, 0.12, rng=rng)
    floor = _plane([-3.0, 1.2, 0.8], [1, 0, 0], [0, 0, 1], 50, 36, 0.12, rng=rng)
    ball = _ball(rng, keys=num_frames, per_copy=80, path=_example_path, radius=0.3, size=0.1, sigma=0.3)
    t = frame_times(num_frames)
    c2w = np.stack([look_at([-0.7 + 1.4 * tk, -0.4, 0.3 * tk], [-0.35 + 0.7 * tk, 0.8, 5.0]) for tk in t])
    room, cams = _anchored((wall, floor), c2w, width, height)
    ball, _ = _anchored((ball,), c2w, width, height)
    return room, ball, cams


def _example_path(s: np.ndarray) -> np.ndarray:
    """[K,3]: the bundled clip's ball at clip times `s`: across the room from left to right, two bounces."""
    return np.stack([-1.1 + 2.2 * s, 0.9 - 1.0 * np.abs(np.sin(2.0 * math.pi * s)), 2.8 + 0.0 * s], axis=1)


def _anchored(parts, c2w: np.ndarray, width: int, height: int) -> tuple[dict[str, torch.Tensor], Cameras]:
    """(the Gaussians of `parts` joined as float32 tensors, Cameras of `c2w`), the world moved so that
    frame 0 is the identity pose."""
    gaussians = {k: torch.as_tensor(np.concatenate([p[k] for p in parts]), dtype=torch.float32) for k in GAUSSIAN_FIELDS}
    to_first = np.linalg.inv(c2w[0])
    c2w = to_first @ c2w
    gaussians["means"] = gaussians["means"] @ torch.as_tensor(to_first[:3, :3].T, dtype=torch.float32) \
        + torch.as_tensor(to_first[:3, 3], dtype=torch.float32)
    gaussians["quats"] = _rotate_quats(gaussians["quats"], to_first[:3, :3])
    return gaussians, Cameras.create(c2w, intrinsics(0.9 * width, width, height), width, height)


def write_example(folder) -> dict[str, Path]:
    """Render the bundled clip into `folder` (created): ball.mp4 (H.264) and ball_masks/NNNNN.png
    (white where the ball's alpha passes 1/2), what tomgs/data ships. Returns the paths by name."""
    from tomgs.io.writer import write_frames
    from tomgs.render.sequence import render_sequence

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    room, ball, cams = example_scene(**EXAMPLE_CLIP)
    both = {k: torch.cat([room[k], ball[k]]) for k in GAUSSIAN_FIELDS}
    frames = [(image.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
              for _, image, _ in render_sequence(both, cams, background=EXAMPLE_BACKGROUND)]
    white = {**ball, "colors": torch.ones_like(ball["colors"])}  # over black, the image is the ball's alpha
    masks = [np.where(image.numpy() > 0.5, 255, 0).astype(np.uint8)
             for _, image, _ in render_sequence(white, cams, background=(0.0, 0.0, 0.0))]
    paths = {"ball.mp4": folder / "ball.mp4", "ball_masks": folder / "ball_masks"}
    write_frames(frames, paths["ball.mp4"], fps=20.0, overwrite=True)
    write_frames(masks, paths["ball_masks"], overwrite=True)
    return paths


def _rotate_quats(quats: torch.Tensor, rot: np.ndarray) -> torch.Tensor:
    """Quaternions of R_world * R_i for a world rotation `rot`."""
    w0, x0, y0, z0 = torch.as_tensor(_quat_from_matrix(rot), dtype=quats.dtype)
    w, x, y, z = quats.unbind(-1)
    return torch.stack([w0 * w - x0 * x - y0 * y - z0 * z, w0 * x + x0 * w + y0 * z - z0 * y,
                        w0 * y - x0 * z + y0 * w + z0 * x, w0 * z + x0 * y - y0 * x + z0 * w], -1)
