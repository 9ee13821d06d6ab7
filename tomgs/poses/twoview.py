"""Two-view geometry of the tracker (tomgs.poses.auto): triangulation, the pose an essential matrix holds,
the nearest rotation, intrinsics of a resized image, and points at depth 1 where nothing gives a depth.
Arrays are numpy, pixels in the +0.5 convention."""

from __future__ import annotations

import cv2
import numpy as np


def sample_colors(images: np.ndarray, frame_idx: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Colours float32 [N,3] in [0,1] of images uint8 [T,h,w,3] sampled (nearest pixel) at
    +0.5-convention pixels xy [N,2] of those images."""
    T, H, W, _ = images.shape
    xi = np.clip(np.floor(xy[:, 0]).astype(int), 0, W - 1)
    yi = np.clip(np.floor(xy[:, 1]).astype(int), 0, H - 1)
    return images[frame_idx, yi, xi].astype(np.float32) / 255.0


def scale_K(K: np.ndarray, s: float) -> np.ndarray:
    """Intrinsics [3,3] of an image resized by s (pixel centres at +0.5, so cx scales with it)."""
    return np.diag([s, s, 1.0]) @ K


def unit_depth_points(image: np.ndarray, K: np.ndarray, n: int = 4000, static: np.ndarray | None = None):
    """Points at depth 1 on a grid of a frame's pixels (no parallax to do better): ([P,3], [P,3]).

    image uint8 [H,W,3] with intrinsics K [3,3]; static bool [h,w] (any size, True = usable) or None."""
    H, W, _ = image.shape
    step = max(1, int(np.sqrt(H * W / n)))
    ys, xs = np.mgrid[0:H:step, 0:W:step]
    xy = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], 1)
    if static is not None:
        sh, sw = static.shape
        xy = xy[static[(ys.ravel() * sh) // H, (xs.ravel() * sw) // W]]
    pts = np.concatenate([(xy - K[:2, 2]) / np.diag(K)[:2], np.ones((len(xy), 1))], 1)
    return pts, sample_colors(image[None], np.zeros(len(xy), int), xy)


def triangulate(Ra, ta, Rb, tb, xa, xb, K):
    """Two-view DLT for many points, each with its own pair of w2c cameras.

    Ra, Rb [N,3,3]; ta, tb [N,3]; xa, xb [N,2] pixels -> X [N,3], parallax angle [N] (degrees).
    """
    Kinv = np.linalg.inv(K)
    na = (np.concatenate([xa, np.ones((len(xa), 1))], 1) @ Kinv.T)
    nb = (np.concatenate([xb, np.ones((len(xb), 1))], 1) @ Kinv.T)
    Pa = np.concatenate([Ra, ta[:, :, None]], 2)
    Pb = np.concatenate([Rb, tb[:, :, None]], 2)
    A = np.stack([na[:, 0:1] * Pa[:, 2] - Pa[:, 0], na[:, 1:2] * Pa[:, 2] - Pa[:, 1],
                  nb[:, 0:1] * Pb[:, 2] - Pb[:, 0], nb[:, 1:2] * Pb[:, 2] - Pb[:, 1]], 1)
    A /= np.linalg.norm(A, axis=2, keepdims=True)
    Xh = np.linalg.svd(A)[2][:, -1]
    X = Xh[:, :3] / np.where(np.abs(Xh[:, 3:]) > 1e-12, Xh[:, 3:], 1e-12)
    # rays in world frame: R^T (K^-1 x)
    da = np.einsum("nji,nj->ni", Ra, na)
    db = np.einsum("nji,nj->ni", Rb, nb)
    cos = (da * db).sum(1) / (np.linalg.norm(da, axis=1) * np.linalg.norm(db, axis=1))
    return X, np.degrees(np.arccos(np.clip(cos, -1, 1)))


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """Nearest rotation to a 3x3 matrix."""
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1, 1, -1]) @ Vt
    return R


def recover_pose(E, xa, xb, K, inl):
    """Pick among the four (R, t) of an essential matrix the one that puts most inliers in front
    of both cameras. Unlike cv2.recoverPose's default, far points (small parallax) vote too.
    Returns R [3,3], t [3] (unit) and the inliers in front (bool [N])."""
    R1, R2, t = cv2.decomposeEssentialMat(E)
    n = int(inl.sum())
    best = (-1, None, None, None)
    for R, tt in ((R1, t), (R1, -t), (R2, t), (R2, -t)):
        X, _ = triangulate(np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)), np.tile(R, (n, 1, 1)),
                           np.tile(tt.ravel(), (n, 1)), xa[inl], xb[inl], K)
        front = (X[:, 2] > 0) & ((X @ R.T + tt.ravel())[:, 2] > 0)
        if front.sum() > best[0]:
            ok = inl.copy()
            ok[inl] = front
            best = (int(front.sum()), R, tt.ravel(), ok)
    return best[1], best[2], best[3]
