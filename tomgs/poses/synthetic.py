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
    """RGB uint8 [H,W,3] and the index of the visible plane int [H,W] (-1: nothing).

    A plane maps to the image by a homography (one cv2.warpPerspective of its texture) and its
    inverse depth is affine in pixel coordinates, so the nearest plane wins a z-buffer on 1/z:
    ~0.15 s for a 1080p frame where a per-pixel ray cast took 0.7 s.
    """
    R, eye = c2w[:3, :3], c2w[:3, 3]
    img = np.zeros((height, width, 3), np.uint8)
    hit = np.full((height, width), -1)
    best = np.zeros((height, width), np.float32)  # 1/z of the nearest hit so far (0: none)
    xs = (np.arange(width, dtype=np.float32) + 0.5)[None, :]
    ys = (np.arange(height, dtype=np.float32) + 0.5)[:, None]
    Kinv = np.linalg.inv(K)
    to_cv = np.array([[1, 0, -0.5], [0, 1, -0.5], [0, 0, 1.0]])  # +0.5 centres -> OpenCV's integer centres
    for i, p in enumerate(planes):
        th, tw = p.texture.shape[:2]
        # texture pixel (OpenCV centres) -> plane (a, b) -> image pixel (OpenCV centres)
        tex_to_ab = np.array([[1 / tw, 0, 0.5 / tw], [0, 1 / th, 0.5 / th], [0, 0, 1.0]])
        Hm = to_cv @ K @ R.T @ np.stack([p.u, p.v, p.o - eye], 1) @ tex_to_ab
        n_cam = R.T @ np.cross(p.u, p.v)  # plane normal in camera axes
        dist = (p.o - eye) @ np.cross(p.u, p.v)
        if abs(dist) < 1e-12:
            continue
        a, b, c = (n_cam @ Kinv) / dist  # 1/z = a x + b y + c at pixel (x, y), +0.5 centres
        inv_z = (a * xs + b * ys + c).astype(np.float32)
        inside = cv2.warpPerspective(np.ones((th, tw), np.uint8), Hm, (width, height), flags=cv2.INTER_NEAREST,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        m = (inside > 0) & (inv_z > 1e-6) & (inv_z > best)
        if not m.any():
            continue
        tex = cv2.warpPerspective(p.texture, Hm, (width, height), flags=cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_REFLECT)
        np.copyto(img, tex, where=m[:, :, None])
        np.copyto(best, inv_z, where=m)
        hit[m] = i
    return img, hit


@dataclass
class SyntheticClip:
    frames: np.ndarray  # uint8 [T,H,W,3] (or a RenderedClip's frames: rendered when read)
    masks: np.ndarray  # bool [T,H,W], True on the moving card (likewise)
    c2w: np.ndarray  # [T,4,4] ground truth, frame 0 = identity
    K: np.ndarray  # [3,3]


class RenderedClip:
    """Frames rendered when read, for clips too long to hold (900 frames of 1080p are 5.6 GB).

    `frames[k]` is uint8 [H,W,3] and `masks[k]` bool [H,W]; the last frame rendered is kept, so
    reading a frame and then its mask renders once. `seconds`: time spent rendering, which a
    benchmark subtracts from what it measures.
    """

    def __init__(self, scene_at, c2w: np.ndarray, K: np.ndarray, width: int, height: int, n_static: int):
        self.scene_at, self.c2w, self.K, self.size, self.n_static = scene_at, c2w, K, (width, height), n_static
        self.seconds = 0.0
        self._last = (-1, None, None)
        self.frames = _View(self, 1)
        self.masks = _View(self, 2)

    def __len__(self) -> int:
        return len(self.c2w)

    def render(self, k: int):
        """(uint8 [H,W,3], bool [H,W]) of frame k."""
        if self._last[0] != k:
            import time

            t0 = time.perf_counter()
            img, hit = render(self.scene_at(k), self.c2w[k], self.K, *self.size)
            self._last = (k, img, hit >= self.n_static)
            self.seconds += time.perf_counter() - t0
        return self._last


class _View:
    """frames or masks of a RenderedClip as a sequence."""

    def __init__(self, clip: RenderedClip, part: int):
        self.clip, self.part = clip, part

    def __len__(self) -> int:
        return len(self.clip)

    def __getitem__(self, k):
        if not 0 <= k < len(self.clip):
            raise IndexError(k)
        return self.clip.render(int(k))[self.part]


def make_clip(c2w: np.ndarray, width: int = 320, height: int = 240, focal: float = 300.0,
              mover: bool = True, seed: int = 0, lazy: bool = False) -> SyntheticClip:
    """Render the room along c2w [T,4,4] (re-anchored so frame 0 = identity); with `mover`, a
    textured card slides across the view independently of the camera. lazy: frames and masks
    are rendered when read (a RenderedClip's sequences) instead of all at once."""
    rng = np.random.default_rng(seed)
    planes = room(rng)
    K = intrinsics(focal, width, height)
    c2w = np.linalg.inv(c2w[0]) @ c2w
    card = textured(rng, [0, 0, 0], [1.0, 0, 0.2], [0, 1.0, 0])
    T = len(c2w)

    def scene_at(k):
        s = k / max(T - 1, 1)
        card_k = Plane(np.array([-1.2 + 0.8 * s, -1.6 + 2.2 * s, 2.4]), card.u, card.v, card.texture)
        return planes + [card_k] if mover else planes

    clip = RenderedClip(scene_at, c2w, K, width, height, len(planes))
    if lazy:
        return SyntheticClip(clip.frames, clip.masks, c2w, K)
    out = [clip.render(k)[1:] for k in range(T)]
    return SyntheticClip(np.stack([f for f, _ in out]), np.stack([m for _, m in out]), c2w, K)


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


def umeyama(src: np.ndarray, dst: np.ndarray):
    """Similarity (s, R, t) minimising |s R src + t - dst|^2; src, dst [N,3]."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    S, D = src - mu_s, dst - mu_d
    U, sig, Vt = np.linalg.svd(D.T @ S / len(src))
    E = np.eye(3)
    if np.linalg.det(U @ Vt) < 0:
        E[2, 2] = -1
    s = np.trace(np.diag(sig) @ E) / max((S ** 2).sum(1).mean(), 1e-300)
    R = U @ E @ Vt
    return s, R, mu_d - s * R @ mu_s


def trajectory_errors(est: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
    """(max position error / path length, max rotation error in degrees) of c2w [T,4,4] against
    ground truth [T,4,4], after a similarity alignment of the camera centres; rotations are
    compared relative to frame 0, which both share as the identity."""
    s, R, t = umeyama(est[:, :3, 3], gt[:, :3, 3])
    pos = np.linalg.norm(s * est[:, :3, 3] @ R.T + t - gt[:, :3, 3], axis=1)
    path = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum()
    cos = (np.einsum("kij,kij->k", gt[:, :3, :3], est[:, :3, :3]) - 1) / 2
    return (pos.max() / path if path > 0 else 0.0), float(np.degrees(np.arccos(np.clip(cos, -1, 1))).max())
