"""2D side of pose estimation: moving-content masks from dense flow, and KLT feature tracks.

All image coordinates leaving this module follow tomgs' pixel convention (centres at +0.5):
OpenCV's feature coordinates put centres at integers, so 0.5 is added on the way out.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


def robust_fit(fn, *args):
    """Call an OpenCV robust estimator (findFundamentalMat, findHomography, ...); (None, None)
    when it fails: USAC asserts instead of returning nothing on degenerate input."""
    try:
        out = fn(*args)
    except cv2.error:
        return None, None
    return out[0], out[1]


def to_gray(frames: np.ndarray) -> np.ndarray:
    """uint8 [T,H,W,3] RGB -> uint8 [T,H,W]."""
    return np.stack([cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames])


def _sampson(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """First-order geometric error (px) of correspondences x1 [N,2] -> x2 [N,2] under F."""
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], 1)
    h2 = np.concatenate([x2, np.ones((len(x2), 1))], 1)
    Fx1 = h1 @ F.T
    Ftx2 = h2 @ F
    num = np.einsum("ij,ij->i", h2, Fx1) ** 2
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-12))


def flow_motion_masks(gray: np.ndarray, work_side: int = 320, thresh_px: float = 1.0,
                      dilate_frac: float = 0.02) -> np.ndarray:
    """Moving content by flow residuals: bool [T,H,W] (True = moving).

    Per consecutive pair: dense DIS flow at `work_side`, a fundamental matrix fitted to a grid of
    flow vectors with LMEDS (robust while the background covers half of the image), and the
    Sampson distance of every pixel's flow to it; pixels above `thresh_px` (work scale) are moving.
    A frame's mask is the union of its two pairs, opened then dilated.
    """
    T, H, W = gray.shape
    s = min(1.0, work_side / max(H, W))
    h, w = max(8, round(H * s)), max(8, round(W * s))
    small = [cv2.resize(g, (w, h), interpolation=cv2.INTER_AREA) for g in gray]
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_FAST)
    ys, xs = np.mgrid[0:h, 0:w]
    grid = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
    step = max(1, int(np.sqrt(h * w / 2000)))  # ~2000 samples for the robust fit
    sub = (ys[::step, ::step] * w + xs[::step, ::step]).ravel()
    pair = np.zeros((max(T - 1, 0), h, w), dtype=bool)
    for k in range(T - 1):
        flow = dis.calc(small[k], small[k + 1], None).reshape(-1, 2).astype(np.float64)
        x2 = grid + flow
        if np.median(np.linalg.norm(flow[sub], axis=1)) < 0.05:
            # a still background makes F degenerate: the flow magnitude is the residual
            err = np.linalg.norm(flow, axis=1)
        else:
            F, _ = robust_fit(cv2.findFundamentalMat, grid[sub], x2[sub], cv2.FM_LMEDS)
            if F is None or F.shape != (3, 3):
                continue
            err = _sampson(F, grid, x2)
        pair[k] = (err > thresh_px).reshape(h, w)
    r = max(1, round(dilate_frac * max(h, w)))
    open_k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
    dil_k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    out = np.zeros((T, H, W), dtype=bool)
    for k in range(T):
        m = np.zeros((h, w), dtype=bool)
        if k > 0:
            m |= pair[k - 1]
        if k < T - 1:
            m |= pair[k]
        m = cv2.morphologyEx(m.astype(np.uint8), cv2.MORPH_OPEN, open_k)
        m = cv2.dilate(m, dil_k)
        out[k] = cv2.resize(m, (W, H), interpolation=cv2.INTER_NEAREST) > 0
    return out


@dataclass
class Tracks:
    """Observations of feature tracks, sorted by frame.

    frame: int64 [N]; track: int64 [N] (ids 0..n_tracks-1); xy: float64 [N,2] pixels (+0.5 centres).
    """

    frame: np.ndarray
    track: np.ndarray
    xy: np.ndarray
    n_tracks: int

    def in_frame(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(track ids [n], xy [n,2]) observed in frame k."""
        lo, hi = np.searchsorted(self.frame, [k, k + 1])
        return self.track[lo:hi], self.xy[lo:hi]

    def common(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(track ids, xy in a, xy in b) of tracks seen in both frames."""
        ta, xa = self.in_frame(a)
        tb, xb = self.in_frame(b)
        ids, ia, ib = np.intersect1d(ta, tb, assume_unique=True, return_indices=True)
        return ids, xa[ia], xb[ib]


def klt_tracks(gray: np.ndarray, static: np.ndarray | None, max_corners: int = 1500,
               fb_thresh: float = 0.7, progress=None) -> Tracks:
    """KLT tracks over consecutive frames.

    gray: uint8 [T,H,W]; static: bool [T,H,W] (True = usable background) or None.
    Each step tracks forward and back and keeps points whose round trip lands within
    `fb_thresh` px, that stay inside the image and on static content, and that agree with a
    robust fundamental matrix of the pair. New corners fill the image where tracks are sparse.
    """
    T, H, W = gray.shape
    min_dist = max(5, round(0.012 * max(H, W)))
    lk = dict(winSize=(15, 15), maxLevel=3, criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    frames_l, tracks_l, xy_l = [], [], []
    pts = np.empty((0, 2), np.float32)
    ids = np.empty(0, np.int64)
    next_id = 0
    for k in range(T):
        if k > 0 and len(pts):
            nxt, st, _ = cv2.calcOpticalFlowPyrLK(gray[k - 1], gray[k], pts.reshape(-1, 1, 2), None, **lk)
            back, st2, _ = cv2.calcOpticalFlowPyrLK(gray[k], gray[k - 1], nxt, None, **lk)
            nxt, back = nxt.reshape(-1, 2), back.reshape(-1, 2)
            ok = (st.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(back - pts, axis=1) < fb_thresh)
            ok &= (nxt[:, 0] >= 0) & (nxt[:, 0] <= W - 1) & (nxt[:, 1] >= 0) & (nxt[:, 1] <= H - 1)
            if static is not None:
                xi = np.clip(np.rint(nxt[:, 0]).astype(int), 0, W - 1)
                yi = np.clip(np.rint(nxt[:, 1]).astype(int), 0, H - 1)
                ok &= static[k, yi, xi]
            if ok.sum() >= 16 and np.median(np.linalg.norm(nxt[ok] - pts[ok], axis=1)) > 0.1:
                F, inl = robust_fit(cv2.findFundamentalMat, pts[ok], nxt[ok], cv2.USAC_MAGSAC, 1.0, 0.999)
                if F is not None and inl is not None and inl.sum() >= 0.5 * ok.sum():
                    ok[np.flatnonzero(ok)[inl.ravel() == 0]] = False
            pts, ids = nxt[ok], ids[ok]
        if len(pts) < 0.8 * max_corners:
            mask = np.full((H, W), 255, np.uint8) if static is None else static[k].astype(np.uint8) * 255
            for x, y in pts:
                cv2.circle(mask, (int(x), int(y)), min_dist, 0, -1)
            new = cv2.goodFeaturesToTrack(gray[k], max_corners - len(pts), 0.01, min_dist, mask=mask, blockSize=7)
            if new is not None:
                new = new.reshape(-1, 2).astype(np.float32)
                pts = np.concatenate([pts, new])
                ids = np.concatenate([ids, np.arange(next_id, next_id + len(new))])
                next_id += len(new)
        frames_l.append(np.full(len(pts), k, np.int64))
        tracks_l.append(ids.copy())
        xy_l.append(pts.astype(np.float64) + 0.5)
        if progress is not None:
            progress(k)
    return Tracks(np.concatenate(frames_l), np.concatenate(tracks_l), np.concatenate(xy_l), next_id)
