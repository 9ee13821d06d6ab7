"""2D side of pose estimation: moving-content masks from dense flow, and KLT feature tracks, made
one frame at a time as the frames are read (nothing per frame is kept but the tracks).

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


def _small(side: int, W: int, H: int) -> tuple[int, int]:
    """(w, h) with the long side at most `side`, aspect kept."""
    s = min(1.0, side / max(W, H))
    return max(1, round(W * s)), max(1, round(H * s))


class WorkingFrames:
    """A clip read one frame at a time into small working copies, each frame once and in order. Nothing
    per frame is kept: the tracker keeps its tracks, never the copies (held for the whole clip they
    grew a fit's host memory by ~1.4 MiB a frame at 1080p, 2.5 GiB for 1800 frames).

    frames: uint8 [T,H,W,3] RGB or any sequence of uint8 [H,W,3]; masks: bool [T,H,W] or a sequence of
    bool [H,W] (True = moving), or None. Frame 0 is read on construction and its copies stay (`first`).
    size: (W, H) of the input frames; work: (w, h), long side at most `work_side`; colour: (wc, hc),
    long side at most COLOR_SIDE; scale: working / input pixels (<= 1). Iterating yields, per frame,
    (gray uint8 [h,w], colour uint8 [hc,wc,3] RGB, moving bool [h,w] or None). Raises InputError on
    bad frames or masks.
    """

    def __init__(self, frames, masks=None, work_side: int = WORK_SIDE):
        from tomgs.errors import InputError

        self.frames, self.masks, self.T = frames, masks, len(frames)
        first = np.asarray(frames[0])
        if first.ndim != 3 or first.shape[-1] != 3 or first.dtype != np.uint8:
            raise InputError(f"frames must be uint8 [T,H,W,3] with T >= 1, got frame 0 as {first.dtype} {first.shape}")
        self.shape = first.shape
        H, W = first.shape[:2]
        if masks is not None and len(masks) != self.T:
            raise InputError(f"masks must be bool [T,H,W] = {(self.T, H, W)} like the frames, got {len(masks)} masks")
        self.size, self.work = (W, H), _small(work_side, W, H)
        self.colour = _small(COLOR_SIDE, *self.work)
        self.scale = self.work[0] / W
        self.first = self._copies(first, 0)

    def __len__(self) -> int:
        return self.T

    def __iter__(self):
        yield self.first
        for k in range(1, self.T):
            yield self._copies(np.asarray(self.frames[k]), k)

    def _copies(self, f: np.ndarray, k: int):
        """(gray, colour, moving) of frame k from f uint8 [H,W,3]: resized by area averaging, gray once."""
        from tomgs.errors import InputError

        if f.shape != self.shape or f.dtype != np.uint8:
            raise InputError(f"frames must all be uint8 [H,W,3] = {self.shape}: frame {k} is {f.dtype} {f.shape}")
        (W, H), (w, h) = self.size, self.work
        small = f if (w, h) == (W, H) else cv2.resize(f, (w, h), interpolation=cv2.INTER_AREA)
        gray = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY)
        colour = small if self.colour == (w, h) else cv2.resize(small, self.colour, interpolation=cv2.INTER_AREA)
        moving = None
        if self.masks is not None:
            m = np.asarray(self.masks[k])
            if m.shape != (H, W):
                raise InputError(f"masks must be bool [T,H,W] = {(self.T, H, W)} like the frames, got {m.shape} for "
                                 f"frame {k}")
            # any moving pixel under a working pixel makes it moving
            moving = m.astype(bool) if (w, h) == (W, H) else cv2.resize(
                m.astype(bool).astype(np.uint8) * 255, (w, h), interpolation=cv2.INTER_AREA) > 0
        return gray, colour, moving


def _sampson(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """First-order geometric error (px) of correspondences x1 [N,2] -> x2 [N,2] under F."""
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], 1)
    h2 = np.concatenate([x2, np.ones((len(x2), 1))], 1)
    Fx1 = h1 @ F.T
    Ftx2 = h2 @ F
    num = np.einsum("ij,ij->i", h2, Fx1) ** 2
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-12))


class FlowMotion:
    """Moving content by flow residuals, one frame at a time: push each frame's gray uint8 [H,W] in
    order; a frame's mask (bool [H,W], True = moving) comes out when the next frame is in (it is the
    union of its two pairs), the last one from finish(). Only the previous frame's small copy and
    pair mask are kept.

    Per consecutive pair: dense DIS flow at `work_side`, a fundamental matrix fitted to a grid of
    flow vectors with LMEDS (robust while the background covers half of the image), and the
    Sampson distance of every pixel's flow to it; pixels above `thresh_px` (work scale) are moving.
    A frame's mask is the union of its two pairs, opened then dilated.
    """

    def __init__(self, H: int, W: int, work_side: int = 320, thresh_px: float = 1.0, dilate_frac: float = 0.02):
        s = min(1.0, work_side / max(H, W))
        self.H, self.W, self.thresh = H, W, thresh_px
        self.h, self.w = h, w = max(8, round(H * s)), max(8, round(W * s))
        self.dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_FAST)
        ys, xs = np.mgrid[0:h, 0:w]
        self.grid = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
        step = max(1, int(np.sqrt(h * w / 2000)))  # ~2000 samples for the robust fit
        self.sub = (ys[::step, ::step] * w + xs[::step, ::step]).ravel()
        r = max(1, round(dilate_frac * max(h, w)))
        self.open_k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
        self.dil_k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        self.small = None  # the previous frame at the flow size
        self.pair = None  # bool [h,w]: the previous frame's pair with the one before it (None: frame 0)

    def push(self, gray: np.ndarray) -> np.ndarray | None:
        """The previous frame's moving mask, complete now; None for the first frame."""
        small = cv2.resize(gray, (self.w, self.h), interpolation=cv2.INTER_AREA)
        out = None
        if self.small is not None:
            pair = self._pair(self.small, small)
            out = self._mask(self.pair, pair)
            self.pair = pair
        self.small = small
        return out

    def finish(self) -> np.ndarray:
        """The last frame's mask (its one pair; none for a single frame)."""
        return self._mask(self.pair, None)

    def _pair(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        flow = self.dis.calc(a, b, None).reshape(-1, 2).astype(np.float64)
        x2 = self.grid + flow
        if np.median(np.linalg.norm(flow[self.sub], axis=1)) < 0.05:
            # a still background makes F degenerate: the flow magnitude is the residual
            err = np.linalg.norm(flow, axis=1)
        else:
            F, _ = robust_fit(cv2.findFundamentalMat, self.grid[self.sub], x2[self.sub], cv2.FM_LMEDS)
            if F is None or F.shape != (3, 3):
                return np.zeros((self.h, self.w), dtype=bool)
            err = _sampson(F, self.grid, x2)
        return (err > self.thresh).reshape(self.h, self.w)

    def _mask(self, before: np.ndarray | None, after: np.ndarray | None) -> np.ndarray:
        m = np.zeros((self.h, self.w), dtype=bool)
        for pair in (before, after):
            if pair is not None:
                m |= pair
        m = cv2.morphologyEx(m.astype(np.uint8), cv2.MORPH_OPEN, self.open_k)
        m = cv2.dilate(m, self.dil_k)
        return cv2.resize(m, (self.W, self.H), interpolation=cv2.INTER_NEAREST) > 0


@dataclass
class Tracks:
    """Observations of feature tracks, sorted by frame.

    frame: int64 [N]; track: int64 [N] (ids 0..n_tracks-1); xy: float64 [N,2] pixels (+0.5 centres);
    colors: uint8 [n_tracks,3], each track's colour where it was first seen, or None.
    """

    frame: np.ndarray
    track: np.ndarray
    xy: np.ndarray
    n_tracks: int
    colors: np.ndarray | None = None

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
        return Tracks(renum[self.frame[sel]], self.track[sel], self.xy[sel], self.n_tracks, self.colors), sel


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


class KLT:
    """KLT tracks over consecutive frames, one frame at a time: add() each frame in order, then
    tracks(). Only the previous frame's gray is kept.

    Each step tracks forward and back and keeps points whose round trip lands within `fb_thresh`
    px, that stay inside the image and on static content, and that agree with a robust
    fundamental matrix of the pair. New corners fill the image where tracks are sparse; their
    colour is sampled (nearest pixel) from the frame's colour copy when one is given.
    """

    def __init__(self, max_corners: int = 1500, fb_thresh: float = 0.7):
        self.max_corners, self.fb_thresh = max_corners, fb_thresh
        self.lk = dict(winSize=(15, 15), maxLevel=3,
                       criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
        self.prev = None  # the previous frame's gray
        self.k = 0
        self.frames, self.ids, self.xy, self.colors = [], [], [], []
        self.pts = np.empty((0, 2), np.float32)
        self.live = np.empty(0, np.int64)  # the track id of each point in self.pts
        self.next_id = 0

    def add(self, gray: np.ndarray, static: np.ndarray | None = None, colour: np.ndarray | None = None) -> None:
        """Frame k (the k-th added): gray uint8 [H,W]; static bool [H,W] (True = usable background) or
        None; colour uint8 [h,w,3] of the same frame at any size, or None."""
        H, W = gray.shape
        min_dist = max(5, round(0.012 * max(H, W)))
        pts, ids = self.pts, self.live
        if self.prev is not None and len(pts):
            nxt, st, _ = cv2.calcOpticalFlowPyrLK(self.prev, gray, pts.reshape(-1, 1, 2), None, **self.lk)
            back, st2, _ = cv2.calcOpticalFlowPyrLK(gray, self.prev, nxt, None, **self.lk)
            nxt, back = nxt.reshape(-1, 2), back.reshape(-1, 2)
            ok = (st.ravel() == 1) & (st2.ravel() == 1) & (np.linalg.norm(back - pts, axis=1) < self.fb_thresh)
            ok &= (nxt[:, 0] >= 0) & (nxt[:, 0] <= W - 1) & (nxt[:, 1] >= 0) & (nxt[:, 1] <= H - 1)
            if static is not None:
                xi = np.clip(np.rint(nxt[:, 0]).astype(int), 0, W - 1)
                yi = np.clip(np.rint(nxt[:, 1]).astype(int), 0, H - 1)
                ok &= static[yi, xi]
            if ok.sum() >= 16 and np.median(np.linalg.norm(nxt[ok] - pts[ok], axis=1)) > 0.1:
                F, inl = robust_fit(cv2.findFundamentalMat, pts[ok], nxt[ok], cv2.USAC_MAGSAC, 1.0, 0.999)
                if F is not None and inl is not None and inl.sum() >= 0.5 * ok.sum():
                    ok[np.flatnonzero(ok)[inl.ravel() == 0]] = False
            pts, ids = nxt[ok], ids[ok]
        if len(pts) < 0.8 * self.max_corners:
            mask = np.full((H, W), 255, np.uint8) if static is None else static.astype(np.uint8) * 255
            for x, y in pts:
                cv2.circle(mask, (int(x), int(y)), min_dist, 0, -1)
            new = cv2.goodFeaturesToTrack(gray, self.max_corners - len(pts), 0.01, min_dist, mask=mask, blockSize=7)
            if new is not None:
                new = new.reshape(-1, 2).astype(np.float32)
                pts = np.concatenate([pts, new])
                ids = np.concatenate([ids, np.arange(self.next_id, self.next_id + len(new))])
                self.next_id += len(new)
                if colour is not None:
                    xy = (new.astype(np.float64) + 0.5) * (colour.shape[1] / W)
                    xi = np.clip(np.floor(xy[:, 0]).astype(int), 0, colour.shape[1] - 1)
                    yi = np.clip(np.floor(xy[:, 1]).astype(int), 0, colour.shape[0] - 1)
                    self.colors.append(colour[yi, xi])
        self.frames.append(np.full(len(pts), self.k, np.int64))
        self.ids.append(ids.copy())
        self.xy.append(pts.astype(np.float64) + 0.5)
        self.pts, self.live, self.prev = pts, ids, gray
        self.k += 1

    def tracks(self) -> Tracks:
        colors = np.concatenate(self.colors) if self.colors else np.empty((0, 3), np.uint8)
        return Tracks(np.concatenate(self.frames), np.concatenate(self.ids), np.concatenate(self.xy), self.next_id,
                      colors if len(colors) == self.next_id else None)
