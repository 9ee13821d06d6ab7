"""Synthetic clips with known cameras (textured planes, optionally one independently moving card).

Used by the tests and benchmarks to check the tracker against ground truth; small and exact:
each pixel's ray is intersected with every plane and the nearest hit samples that plane's texture.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from tomgs.cameras import intrinsics


@dataclass
class Plane:
    """A textured rectangle: corner o [3], edge vectors u [3], v [3] (texture x along u, y along v)."""

    o: np.ndarray
    u: np.ndarray
    v: np.ndarray
    texture: np.ndarray  # uint8 [h, w, 3]


def noise_texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """uint8 [h, w, 3]: multi-scale blurred noise, rich in corners at several scales."""
    acc = np.zeros((h, w, 3), np.float32)
    for sigma, wt in ((1.5, 0.5), (4.0, 1.0), (12.0, 1.0)):
        n = cv2.GaussianBlur(rng.random((h, w, 3), dtype=np.float32), (0, 0), sigma)
        acc += wt * (n - n.mean()) / (n.std() + 1e-6)
    acc = (acc - acc.min()) / (acc.max() - acc.min())
    return (acc * 255).astype(np.uint8)


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """c2w [4,4] in OpenCV axes (z forward, y down) looking from eye at target."""
    eye, target, up = (np.asarray(a, float) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([x, y, z], 1)
    c2w[:3, 3] = eye
    return c2w


TEXELS_PER_UNIT = 80  # coarse enough that no plane is minified in the clips below (no aliasing)


def textured(rng: np.random.Generator, o, u, v) -> Plane:
    """A plane with a noise texture of TEXELS_PER_UNIT resolution."""
    o, u, v = (np.asarray(a, float) for a in (o, u, v))
    w, h = (max(8, round(TEXELS_PER_UNIT * np.linalg.norm(e))) for e in (u, v))
    return Plane(o, u, v, noise_texture(rng, h, w))


def room(rng: np.random.Generator) -> list[Plane]:
    """A back wall, a floor, a side wall and a box face at several depths (parallax everywhere)."""
    P = lambda o, u, v: textured(rng, o, u, v)
    return [
        P([-6, -4, 7], [12, 0, 0], [0, 6.5, 0]),       # back wall, z = 7
        P([-6, 2.5, 0.2], [12, 0, 0], [0, 0, 6.8]),    # floor, y = 2.5
        P([-3.5, -4, 0.2], [0, 0, 6.8], [0, 6.5, 0]),  # left wall, x = -3.5
        P([0.6, -0.8, 3.5], [1.6, 0, 0], [0, 3.3, 0]),  # box front, z = 3.5
        P([-1.8, -1.5, 4.5], [1.2, 0, -0.6], [0, 2.0, 0]),  # slanted panel
    ]


def render(planes: list[Plane], c2w: np.ndarray, K: np.ndarray, width: int, height: int):
    """RGB uint8 [H,W,3] and the index of the visible plane int [H,W] (-1: nothing)."""
    ys, xs = np.mgrid[0:height, 0:width]
    pix = np.stack([xs + 0.5, ys + 0.5, np.ones_like(xs, dtype=float)], -1).reshape(-1, 3)
    d = (pix @ np.linalg.inv(K).T) @ c2w[:3, :3].T
    eye = c2w[:3, 3]
    best = np.full(len(d), np.inf)
    img = np.zeros((len(d), 3), np.float32)
    hit = np.full(len(d), -1)
    for i, p in enumerate(planes):
        n = np.cross(p.u, p.v)
        denom = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((p.o - eye) @ n) / denom
        q = eye + t[:, None] * d - p.o
        a = q @ p.u / (p.u @ p.u)
        b = q @ p.v / (p.v @ p.v)
        m = (t > 1e-6) & (t < best) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
        if not m.any():
            continue
        th, tw = p.texture.shape[:2]
        mx = np.where(m, a * tw - 0.5, -1).astype(np.float32).reshape(height, width)
        my = np.where(m, b * th - 0.5, -1).astype(np.float32).reshape(height, width)
        tex = cv2.remap(p.texture, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        img[m] = tex.reshape(-1, 3)[m]
        best[m] = t[m]
        hit[m] = i
    return np.clip(img, 0, 255).astype(np.uint8).reshape(height, width, 3), hit.reshape(height, width)


@dataclass
class SyntheticClip:
    frames: np.ndarray  # uint8 [T,H,W,3]
    masks: np.ndarray  # bool [T,H,W], True on the moving card
    c2w: np.ndarray  # [T,4,4] ground truth, frame 0 = identity
    K: np.ndarray  # [3,3]


def make_clip(c2w: np.ndarray, width: int = 320, height: int = 240, focal: float = 300.0,
              mover: bool = True, seed: int = 0) -> SyntheticClip:
    """Render the room along c2w [T,4,4] (re-anchored so frame 0 = identity); with `mover`, a
    textured card slides across the view independently of the camera."""
    rng = np.random.default_rng(seed)
    planes = room(rng)
    K = intrinsics(focal, width, height)
    c2w = np.linalg.inv(c2w[0]) @ c2w
    card = textured(rng, [0, 0, 0], [1.0, 0, 0.2], [0, 1.0, 0])
    T = len(c2w)
    frames, masks = [], []
    for k in range(T):
        s = k / max(T - 1, 1)
        scene = list(planes)
        if mover:
            scene.append(Plane(np.array([-1.2 + 0.8 * s, -1.6 + 2.2 * s, 2.4]), card.u, card.v, card.texture))
        img, hit = render(scene, c2w[k], K, width, height)
        frames.append(img)
        masks.append(hit == len(planes) if mover else np.zeros_like(hit, bool))
    return SyntheticClip(np.stack(frames), np.stack(masks), c2w, K)


def orbit(T: int, strafe: float = 1.2, target=(0.0, 0.0, 5.0)) -> np.ndarray:
    """A sideways, slightly rising and advancing path looking at `target`: c2w [T,4,4]."""
    out = []
    for k in range(T):
        s = k / max(T - 1, 1)
        eye = np.array([strafe * (s - 0.5), -0.3 * np.sin(np.pi * s), 0.6 * s])
        out.append(look_at(eye, target))
    return np.stack(out)


def pan(T: int, yaw_deg: float = 20.0, pitch_deg: float = 6.0) -> np.ndarray:
    """Pure rotation about the camera centre: c2w [T,4,4]."""
    out = []
    for k in range(T):
        s = k / max(T - 1, 1)
        R = cv2.Rodrigues(np.radians([pitch_deg * s, yaw_deg * (s - 0.5), 0.0]))[0]
        c2w = np.eye(4)
        c2w[:3, :3] = R
        out.append(c2w)
    return np.stack(out)
