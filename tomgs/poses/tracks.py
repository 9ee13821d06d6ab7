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


WORK_SIDE = 960  # long side (px) the tracker works at: KLT is sharp there, 1080p and 4K cost the same
COLOR_SIDE = 480  # long side of the copies kept for point colours (they only seed the Gaussians)


@dataclass
class WorkingClip:
    """A clip as the tracker keeps it: small copies made one frame at a time, never full frames.

    gray: uint8 [T,h,w] at the working size; colors: uint8 [T,hc,wc,3] RGB (long side at most
    COLOR_SIDE); moving: bool [T,h,w] (given masks, resized; True = moving) or None;
    size: (W, H) of the input frames; scale: working / input pixels (<= 1).
    """

    gray: np.ndarray
    colors: np.ndarray
    moving: np.ndarray | None
    size: tuple[int, int]
    scale: float


def _small(side: int, W: int, H: int) -> tuple[int, int]:
    """(w, h) with the long side at most `side`, aspect kept."""
    s = min(1.0, side / max(W, H))
    return max(1, round(W * s)), max(1, round(H * s))


def read_working(frames, masks=None, work_side: int = WORK_SIDE, progress=None) -> WorkingClip:
    """Read a clip one frame at a time into a WorkingClip.

    frames: uint8 [T,H,W,3] RGB or any sequence of uint8 [H,W,3] frames; masks: bool [T,H,W] or a
    sequence of bool [H,W] (True = moving), or None. Each frame is resized (area averaging) and
    converted to gray once. progress: callable(k) after frame k. Raises InputError on bad frames.
    """
    from tomgs.errors import InputError

    T = len(frames)
    first = np.asarray(frames[0])
    if first.ndim != 3 or first.shape[-1] != 3 or first.dtype != np.uint8:
        raise InputError(f"frames must be uint8 [T,H,W,3] with T >= 1, got frame 0 as {first.dtype} {first.shape}")
    H, W = first.shape[:2]
    if masks is not None and len(masks) != T:
        raise InputError(f"masks must be bool [T,H,W] = {(T, H, W)} like the frames, got {len(masks)} masks")
    w, h = _small(work_side, W, H)
    wc, hc = _small(COLOR_SIDE, w, h)
    gray = np.empty((T, h, w), np.uint8)
    colors = np.empty((T, hc, wc, 3), np.uint8)
    moving = None if masks is None else np.empty((T, h, w), bool)
    for k in range(T):
        f = first if k == 0 else np.asarray(frames[k])
        if f.shape != first.shape or f.dtype != np.uint8:
            raise InputError(f"frames must all be uint8 [H,W,3] = {first.shape}: frame {k} is {f.dtype} {f.shape}")
        small = f if (w, h) == (W, H) else cv2.resize(f, (w, h), interpolation=cv2.INTER_AREA)
        gray[k] = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY)
        colors[k] = small if (wc, hc) == (w, h) else cv2.resize(small, (wc, hc), interpolation=cv2.INTER_AREA)
        if masks is not None:
            m = np.asarray(masks[k])
            if m.shape != (H, W):
                raise InputError(f"masks must be bool [T,H,W] = {(T, H, W)} like the frames, got {m.shape} for "
                                 f"frame {k}")
            # any moving pixel under a working pixel makes it moving
            moving[k] = m if (w, h) == (W, H) else cv2.resize(m.astype(bool).astype(np.uint8) * 255, (w, h),
                                                                interpolation=cv2.INTER_AREA) > 0
        if progress is not None:
            progress(k)
    return WorkingClip(gray, colors, moving, (W, H), w / W)


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

    def subset(self, frames: np.ndarray) -> tuple["Tracks", np.ndarray]:
        """The observations in `frames` (sorted int [K]), renumbered 0..K-1 (track ids kept), and
        their indices int [n] in self."""
        sel = np.flatnonzero(np.isin(self.frame, frames))
        renum = np.full(int(frames[-1]) + 1, -1)
        renum[frames] = np.arange(len(frames))
        return Tracks(renum[self.frame[sel]], self.track[sel], self.xy[sel], self.n_tracks), sel


def select_keyframes(tracks: Tracks, T: int, side: int, min_shared: float = 0.7, max_move: float = 0.02,
                     max_gap: int = 10) -> np.ndarray:
    """Frames (sorted int [K], first and last included) to solve in the bundle; the others are
    registered to them. A new keyframe starts when fewer than `min_shared` of the last keyframe's
    tracks survive, when they moved by more than `max_move` x `side` px (median), or after
    `max_gap` frames; a slow clip gets few, a fast one many."""
    keys = [0]
    ids0, xy0 = tracks.in_frame(0)
    for k in range(1, T):
        ids, xy = tracks.in_frame(k)
        _, i0, i1 = np.intersect1d(ids0, ids, assume_unique=True, return_indices=True)
        moved = float(np.median(np.linalg.norm(xy[i1] - xy0[i0], axis=1))) if len(i0) else np.inf
        if len(i0) < min_shared * len(ids0) or moved > max_move * side or k - keys[-1] >= max_gap or k == T - 1:
            keys.append(k)
            ids0, xy0 = ids, xy
    return np.array(keys, dtype=np.int64)


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
