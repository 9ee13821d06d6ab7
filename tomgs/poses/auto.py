"""The built-in, weight-free camera tracker (REFERENCES.md, "Camera poses").

frames (+ moving masks) -> static-region masks -> KLT tracks -> [fixed camera? -> identity]
-> init pair (0, j) chosen by parallax left after a homography -> focal, when unknown, by
self-calibration on a log grid and trial reconstructions -> essential matrix (USAC_MAGSAC) + a
chirality vote + triangulation -> PnP (RANSAC + LM) per new frame, triangulating new tracks,
windowed bundle adjustment -> final robust bundle adjustment (focal refined) -> frame 0 =
identity, median depth of frame 0's points = 1.
A clip whose views are all related by homographies (pure rotation, or a very distant scene)
is solved with rotation-only cameras.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from tomgs.cameras import intrinsics
from tomgs.poses.ba import bundle_adjust, reprojection_errors
from tomgs.poses.tracks import flow_motion_masks, klt_tracks, robust_fit, to_gray


@dataclass
class Solution:
    """What the tracker found. c2w [T,4,4]; K [3,3]; points [P,3]; colors float32 [P,3] in [0,1]."""

    c2w: np.ndarray
    K: np.ndarray
    points: np.ndarray
    colors: np.ndarray
    mode: str  # "fixed", "rotation" or "general"
    reproj_px: float  # median reprojection error of the background observations kept (nan: none)
    notes: list = field(default_factory=list)
    timings: dict = field(default_factory=dict)
    reproj_all_px: float = float("nan")  # the same median over every observation of those tracks
    rejected: float = 0.0  # fraction of those observations rejected as outliers
    point_frames: np.ndarray | None = None  # int [P,2]: first and last frame a point was tracked in


def static_masks(masks: np.ndarray | None, gray: np.ndarray, notes: list) -> np.ndarray:
    """bool [T,H,W], True where pixels may be used: given masks [T,H,W] (dilated) or, without
    them, flow residuals of gray [T,H,W]."""
    T, H, W = gray.shape
    if masks is not None:
        r = max(1, round(0.01 * max(H, W)))
        kern = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        moving = np.stack([cv2.dilate(m.astype(np.uint8), kern) > 0 for m in masks])
    elif T >= 2:
        moving = flow_motion_masks(gray)
    else:
        return np.ones((T, H, W), bool)
    static = ~moving
    bad = static.reshape(T, -1).mean(1) < 0.15
    if bad.any():  # a mask that leaves almost nothing is more likely wrong than the scene
        static[bad] = True
        notes.append(f"{int(bad.sum())} frame(s) masked over 85%: their masks were ignored")
    return static


def is_fixed_camera(gray: np.ndarray, static: np.ndarray, thresh_px: float = 0.3) -> bool:
    """True if static corners of frame 0 stay within `thresh_px` in a handful of later frames."""
    T = len(gray)
    pts = cv2.goodFeaturesToTrack(gray[0], 400, 0.01, 8, mask=static[0].astype(np.uint8) * 255)
    if pts is None or len(pts) < 20:
        return False
    for k in sorted({1, T // 4, T // 2, (3 * T) // 4, T - 1} - {0}):
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(gray[0], gray[k], pts, None, winSize=(21, 21), maxLevel=3)
        ok = st.ravel() == 1
        if ok.sum() < 0.5 * len(pts):
            return False
        if np.median(np.linalg.norm((nxt - pts).reshape(-1, 2)[ok], axis=1)) > thresh_px:
            return False
    return True


def _sample_colors(frames: np.ndarray, frame_idx: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Colours float32 [N,3] in [0,1] sampled (nearest pixel) at +0.5-convention pixels."""
    T, H, W, _ = frames.shape
    xi = np.clip(np.floor(xy[:, 0]).astype(int), 0, W - 1)
    yi = np.clip(np.floor(xy[:, 1]).astype(int), 0, H - 1)
    return frames[frame_idx, yi, xi].astype(np.float32) / 255.0


def unit_depth_points(frames: np.ndarray, K: np.ndarray, n: int = 4000, static: np.ndarray | None = None):
    """Points at depth 1 on a grid of frame 0's pixels (no parallax to do better): ([P,3], [P,3])."""
    _, H, W, _ = frames.shape
    step = max(1, int(np.sqrt(H * W / n)))
    ys, xs = np.mgrid[0:H:step, 0:W:step]
    xy = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], 1)
    if static is not None:
        xy = xy[static[0, ys.ravel(), xs.ravel()]]
    pts = np.concatenate([(xy - K[:2, 2]) / np.diag(K)[:2], np.ones((len(xy), 1))], 1)
    return pts, _sample_colors(frames, np.zeros(len(xy), int), xy)


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


def _polar(M: np.ndarray) -> np.ndarray:
    """Nearest rotation to a 3x3 matrix."""
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        R = U @ np.diag([1, 1, -1]) @ Vt
    return R


def _recover_pose(E, xa, xb, K, inl):
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


class Tracker:
    """One run of the built-in tracker on a clip; `solve()` returns a `Solution`.

    frames uint8 [T,H,W,3] RGB; masks bool [T,H,W] (True = moving) or None; focal px or None
    (estimated); progress callable(done, total) or None; K [3,3] to use instead of a centred
    square-pixel K built from the focal (known cameras).
    State while solving: poses as world-to-camera Rw [T,3,3], tw [T,3]; X [n_tracks,3] (nan
    until triangulated); obs_ok bool per track observation.
    """

    def __init__(self, frames, masks=None, focal=None, progress=None, max_corners=None, K=None):
        self.frames = frames
        self.K_given = None if K is None else np.asarray(K, dtype=np.float64)
        self.T, self.H, self.W = frames.shape[:3]
        self.masks = masks
        self.focal_given = focal is not None
        self.focal = float(focal) if focal is not None else 1.2 * max(self.W, self.H)
        self.progress = progress or (lambda done, total: None)
        self.max_corners = max_corners or int(np.clip(self.W * self.H / 150, 300, 1500))
        self.notes: list[str] = []
        self.timings: dict[str, float] = {}
        self.side = max(self.W, self.H)
        self.min_angle = 0.5  # degrees between rays for a new point; set from the first pair

    @property
    def K(self):
        return self.K_given if self.K_given is not None else intrinsics(self.focal, self.W, self.H)

    def _tick(self, name, t0):
        self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - t0
        return time.perf_counter()

    # ---- top level -----------------------------------------------------------------------------

    def solve(self) -> Solution:
        t0 = time.perf_counter()
        T = self.T
        gray = to_gray(self.frames)
        self.static = static_masks(self.masks, gray, self.notes)
        t0 = self._tick("masks", t0)
        if T == 1 or is_fixed_camera(gray, self.static):
            self.notes.append("single frame: identity pose" if T == 1 else
                              "fixed camera detected: identity poses, no poses solved")
            pts, cols = unit_depth_points(self.frames, self.K, static=self.static)
            self.progress(2 * T, 2 * T)
            return Solution(np.tile(np.eye(4), (T, 1, 1)), self.K, pts, cols, "fixed", float("nan"), self.notes,
                            self.timings)
        self.tracks = klt_tracks(gray, self.static, self.max_corners, progress=lambda k: self.progress(k + 1, 2 * T))
        t0 = self._tick("tracks", t0)
        j, general = self._init_pair()
        if not self.focal_given:
            self.focal = self._focal_search(j, general)
            if general:
                f = self._focal_trials(j)
                general = f is not None
                self.focal = f if general else self._focal_search(j, False)
            self.notes.append(f"focal search: {self.focal:.1f} px before the final adjustment")
        t0 = self._tick("focal", t0)
        sol = self._solve_general(j) if general else None
        if sol is None:
            if general:
                self.notes.append("two-view start failed: fell back to rotation-only cameras")
            sol = self._solve_rotation()
        self._tick("reconstruct", t0)
        self.progress(2 * T, 2 * T)
        return sol

    # ---- choosing how to start -----------------------------------------------------------------

    def _init_pair(self) -> tuple[int, bool]:
        """(j, general): frame paired with 0, and whether translation is observable.

        Parallax is what a homography cannot explain: the residuals of the tracks shared by
        frames 0 and j after a RANSAC homography. The first j with enough of it starts the
        reconstruction; if no frame gets there, the clip is treated as rotation-only.
        """
        need = max(1.5, 0.004 * self.side)
        best_j, best_par = 1, -1.0
        for j in range(1, self.T):
            _, xa, xb = self.tracks.common(0, j)
            if len(xa) < 30:
                break
            Hm, _ = robust_fit(cv2.findHomography, xa, xb, cv2.RANSAC, 1.0)
            if Hm is None:
                continue
            proj = cv2.perspectiveTransform(xa.reshape(-1, 1, 2), Hm).reshape(-1, 2)
            # upper quartile: a dominant plane (a wall) fits the homography whatever the motion
            par = float(np.percentile(np.linalg.norm(proj - xb, axis=1), 75))
            if par > best_par:
                best_j, best_par = j, par
            if par >= need:
                return j, True
        self.notes.append(f"parallax after a homography at most {max(best_par, 0):.2f} px (need {need:.2f})")
        return best_j, best_par >= 0.5 * need and best_par > 0.75

    def _pairs(self, gap: int, n: int = 8) -> list[tuple[int, int]]:
        """Up to n frame pairs (a, a + gap) spread over the clip."""
        gap = max(1, min(gap, self.T - 1))
        starts = np.unique(np.linspace(0, self.T - 1 - gap, min(n, self.T - gap)).round().astype(int))
        return [(int(a), int(a) + gap) for a in starts]

    def _focal_search(self, j: int, general: bool) -> float:
        """Focal on a log grid of 0.3..3 x the image side, scored by self-calibration residuals.

        General motion: the essential matrix K^T F K of each pair must have two equal singular
        values. Rotation: K^-1 H K must be a rotation. Refined later in bundle adjustment.
        """
        grid = self.side * np.exp(np.linspace(np.log(0.3), np.log(3.0), 161))
        mats = []
        for a, b in self._pairs(j):
            _, xa, xb = self.tracks.common(a, b)
            if len(xa) < 30:
                continue
            if general:
                M, inl = robust_fit(cv2.findFundamentalMat, xa, xb, cv2.USAC_MAGSAC, 1.0, 0.999)
            else:
                M, inl = robust_fit(cv2.findHomography, xa, xb, cv2.USAC_MAGSAC, 1.0)
            if M is not None and M.shape == (3, 3):
                mats.append(M)
        if not mats:
            self.notes.append("focal search found no usable pair: using 1.2 x image side")
            return 1.2 * self.side
        cost = np.zeros(len(grid))
        for g, f in enumerate(grid):
            K = intrinsics(f, self.W, self.H)
            Ki = np.linalg.inv(K)
            for M in mats:
                if general:
                    s = np.linalg.svd(K.T @ M @ K, compute_uv=False)
                    cost[g] += (s[0] - s[1]) / (s[0] + s[1])
                else:
                    Mr = Ki @ M @ K
                    Mr = Mr / np.cbrt(np.linalg.det(Mr))
                    cost[g] += np.linalg.norm(Mr.T @ Mr - np.eye(3))
        g = int(np.argmin(cost))
        if cost.max() - cost.min() < 1e-3 * len(mats):
            self.notes.append("focal poorly constrained by the first views: starting at 1.2 x image side")
            return 1.2 * self.side
        return float(grid[g])

    def _focal_trials(self, j: int) -> float:
        """Reconstruct the first frames from a few starting focals (the self-calibration guess
        and a log-spaced spread), each refined by bundle adjustment; keep the one with the lowest
        median reprojection error over all observations of its tracks, outliers included (a
        wrong focal bends the structure; counting inliers alone favours whichever hypothesis
        happened to triangulate more tracks)."""
        # about a dozen frames spread up to a little past j: enough views to pin the focal, cheap
        trial = np.unique(np.linspace(1, min(self.T - 1, j + 8), 12).round().astype(int))
        trial = sorted(set(trial.tolist()) | {j})
        starts = [self.focal] + [self.side * m for m in (0.5, 0.8, 1.25, 2.0)]
        best, seen = (np.inf, None), []
        for f in starts:
            self.focal = f
            sol = self._solve_general(j, frames=trial, report=False)
            if sol is not None:
                seen.append(f"{f:.0f}->{sol.K[0, 0]:.0f} ({sol.reproj_all_px:.3f} px)")
                if sol.reproj_all_px < best[0]:
                    best = (sol.reproj_all_px, float(sol.K[0, 0]))
        self.notes.append("focal trials, start -> refined (median error): " + ", ".join(seen))
        return best[1]  # None: no start could be reconstructed

    # ---- general motion ------------------------------------------------------------------------

    def _solve_general(self, j: int, frames=None, report: bool = True) -> Solution | None:
        """Incremental reconstruction of frame 0 and `frames` (all by default) from the pair (0, j)."""
        T, tr = self.T, self.tracks
        K = self.K
        self.reporting = report
        ids, x0, xj = tr.common(0, j)
        E, inl = robust_fit(cv2.findEssentialMat, x0, xj, K, cv2.USAC_MAGSAC, 0.999, 1.0)
        if E is None or E.shape != (3, 3):
            return None
        R, t, inl = _recover_pose(E, x0, xj, K, inl.ravel() > 0)
        if inl.sum() < 20:
            return None
        self.Rw = np.tile(np.eye(3), (T, 1, 1))
        self.tw = np.zeros((T, 3))
        self.reg = np.zeros(T, bool)
        self.reg[0] = True
        self.Rw[j], self.tw[j], self.reg[j] = R, t.ravel(), True
        self.X = np.full((tr.n_tracks, 3), np.nan)
        self.obs_ok = np.ones(len(tr.frame), bool)
        self.track_end = np.full(tr.n_tracks, T)
        keep = inl
        # slow or narrow-angle clips never reach a fixed triangulation angle: take half the
        # median angle of the first pair (within 0.05..1 degree) as the bar for new points
        _, ang = triangulate(self.Rw[[0]].repeat(keep.sum(), 0), self.tw[[0]].repeat(keep.sum(), 0),
                             self.Rw[[j]].repeat(keep.sum(), 0), self.tw[[j]].repeat(keep.sum(), 0),
                             x0[keep], xj[keep], K)
        self.min_angle = float(np.clip(0.5 * np.median(ang), 0.05, 1.0))
        self._triangulate_pairs(ids[keep], np.zeros(keep.sum(), int), np.full(keep.sum(), j), x0[keep], xj[keep])
        d = self._cam_depths(0, np.flatnonzero(self._has()))
        if len(d) < 15:
            return None
        s = np.median(d)  # scale: median depth of the first pair = 1
        self.tw[j] /= s
        self.X /= s
        order = [k for k in (range(1, T) if frames is None else frames) if k not in (0, j)]
        n_since = 0
        for count, k in enumerate(order):
            self._register(k)
            self._triangulate_frame(k)
            n_since += 1
            if n_since >= 8:
                self._local_ba()
                n_since = 0
            if report:
                self.progress(T + count + 2, 2 * T)
        return self._finish(quick=not report)

    def _reject(self, obs_idx):
        """Drop observations and everything later on their tracks: a track that stops agreeing
        has usually slid onto another surface (occlusion edge) and does not come back."""
        tr = self.tracks
        np.minimum.at(self.track_end, tr.track[obs_idx], tr.frame[obs_idx])
        self.obs_ok &= tr.frame < self.track_end[tr.track]

    def _has(self):
        return np.isfinite(self.X[:, 0])

    def _cam_depths(self, k, pids):
        return (self.X[pids] @ self.Rw[k].T + self.tw[k])[:, 2]

    def _triangulate_pairs(self, pids, fa, fb, xa, xb, max_err=2.0):
        """Triangulate tracks pids between frames fa[i] and fb[i]; keep well-conditioned points."""
        if len(pids) == 0:
            return
        X, ang = triangulate(self.Rw[fa], self.tw[fa], self.Rw[fb], self.tw[fb], xa, xb, self.K)
        ok = ang >= self.min_angle
        for f, x in ((fa, xa), (fb, xb)):
            e = reprojection_errors(self.Rw, self.tw, X, self.K, f, np.arange(len(X)), x)
            ok &= e < max_err
        self.X[pids[ok]] = X[ok]

    def _register(self, k):
        """Pose of frame k by PnP on its tracks with points; falls back to its neighbour's pose."""
        tr, K = self.tracks, self.K
        ids, xy = tr.in_frame(k)
        lo = np.searchsorted(tr.frame, k)
        okobs = self.obs_ok[lo:lo + len(ids)]
        sel = self._has()[ids] & okobs
        prev = max(i for i in range(k) if self.reg[i]) if k > 0 else 0
        rvec0 = cv2.Rodrigues(self.Rw[prev])[0]
        tvec0 = self.tw[prev].reshape(3, 1).copy()
        ok = False
        if sel.sum() >= 10:
            obj, img = self.X[ids[sel]], xy[sel]
            ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K, None, rvec0.copy(), tvec0.copy(), True, 200,
                                                     max(2.0, 0.003 * self.side), 0.999, flags=cv2.SOLVEPNP_ITERATIVE)
            if ok and inl is not None and len(inl) >= 8:
                inl = inl.ravel()
                rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, None, rvec, tvec)
                self._reject(lo + np.flatnonzero(sel)[np.setdiff1d(np.arange(sel.sum()), inl)])
            else:
                ok = False
        if not ok:
            rvec, tvec = rvec0, tvec0
            if self.reporting:
                self.notes.append(f"frame {k}: too few tracked points for PnP, pose copied from frame {prev}")
        self.Rw[k] = cv2.Rodrigues(rvec)[0]
        self.tw[k] = tvec.ravel()
        self.reg[k] = True

    def _triangulate_frame(self, k):
        """New points for tracks seen in frame k and in an earlier registered frame (widest baseline)."""
        tr = self.tracks
        ids, xy = tr.in_frame(k)
        new = ~self._has()[ids]
        if not new.any():
            return
        cand = ids[new]
        m = np.isin(tr.track, cand) & self.reg[tr.frame] & (tr.frame != k) & self.obs_ok
        first_t, first_i = np.unique(tr.track[m], return_index=True)  # observations sorted by frame
        first_i = np.flatnonzero(m)[first_i]
        pos = {t: i for i, t in enumerate(ids)}
        kb = np.array([pos[t] for t in first_t], int)
        self._triangulate_pairs(first_t, tr.frame[first_i], np.full(len(first_t), k), tr.xy[first_i], xy[kb])

    def _ba_problem(self, cams_free: np.ndarray, frames_used: np.ndarray | None = None):
        """Observations (in `frames_used`, default all) of points seen by free cameras:
        (cam_idx, pt_idx, obs, point ids, observation indices)."""
        tr = self.tracks
        has = self._has()
        used = self.reg if frames_used is None else self.reg & frames_used
        valid = self.obs_ok & used[tr.frame] & has[tr.track]
        pts = np.unique(tr.track[valid & cams_free[tr.frame]])
        m = valid & np.isin(tr.track, pts)
        # points observed once cannot be adjusted: drop them from the problem
        cnt = np.bincount(tr.track[m], minlength=tr.n_tracks)
        m &= cnt[tr.track] >= 2
        pts = np.flatnonzero(np.bincount(tr.track[m], minlength=tr.n_tracks))
        remap = np.full(tr.n_tracks, -1)
        remap[pts] = np.arange(len(pts))
        return tr.frame[m], remap[tr.track[m]], tr.xy[m], pts, np.flatnonzero(m)

    def _run_ba(self, cams_free, iters, opt_focal=False, fix_translation=False, max_points=1000, rest=False,
                frames_used=None):
        """Adjust free cameras with the `max_points` longest tracks (enough to pin the cameras;
        the cost grows with the observations), then with `rest` the other points with the
        cameras fixed; finally drop observations far above the median error."""
        ci, pi, obs, pts, oidx = self._ba_problem(cams_free, frames_used)
        if len(obs) == 0:
            return
        cnt = np.bincount(pi, minlength=len(pts))
        sub = np.zeros(len(pts), bool)
        sub[np.argsort(-cnt, kind="stable")[:max_points]] = True
        bounds = (0.25 * self.side, 4 * self.side)
        for part, free, it in ((sub, cams_free & self.reg, iters), (~sub, np.zeros(self.T, bool), 5)):
            if not part.any() or (part is not sub and not rest):
                continue
            m = part[pi]
            remap = np.cumsum(part) - 1
            R, t, X, K = bundle_adjust(self.Rw, self.tw, self.X[pts[part]], self.K, ci[m], remap[pi[m]], obs[m],
                                       free, opt_focal=opt_focal and free.any(), fix_translation=fix_translation,
                                       iters=it, focal_bounds=bounds)
            self.Rw, self.tw = R, t
            self.X[pts[part]] = X
            self.focal = float(K[0, 0])
        err = reprojection_errors(self.Rw, self.tw, self.X[pts], self.K, ci, pi, obs)
        thresh = max(0.5, 4 * float(np.median(err)))
        self._reject(oidx[err > thresh])

    def _local_ba(self):
        regd = np.flatnonzero(self.reg)
        free = np.zeros(self.T, bool)
        last = np.sort(regd)[-12:]
        free[last] = True
        free[0] = False
        # the window and as many fixed frames before it: older views barely move the window
        used = np.zeros(self.T, bool)
        used[np.sort(regd)[-24:]] = True
        self._run_ba(free, iters=10, opt_focal=not self.focal_given and self.reg.sum() >= 6, frames_used=used)

    def _finish(self, quick: bool = False) -> Solution:
        free = self.reg.copy()
        free[0] = False
        opt_f = not self.focal_given
        # a free focal moves along a shallow valley: give it more iterations
        self._run_ba(free, iters=10 if quick else 30 if opt_f else 20, opt_focal=opt_f)
        if not quick:
            self._run_ba(free, iters=15 if opt_f else 10, opt_focal=opt_f, rest=True)
        # gauge: frame 0 stays the identity; median depth of frame 0's points = 1
        ci, pi, obs, pts, _ = self._ba_problem(free | self.reg)
        in0 = np.unique(pi[ci == 0])
        d = self._cam_depths(0, pts[in0]) if len(in0) else self._cam_depths(0, pts)
        s = float(np.median(d[d > 0])) if (d > 0).any() else 1.0
        self.tw /= s
        self.X /= s
        err = reprojection_errors(self.Rw, self.tw, self.X[pts], self.K, ci, pi, obs)
        c2w = np.tile(np.eye(4), (self.T, 1, 1))
        c2w[:, :3, :3] = np.transpose(self.Rw, (0, 2, 1))
        c2w[:, :3, 3] = -np.einsum("nji,nj->ni", self.Rw, self.tw)
        sol = Solution(c2w, self.K, self.X[pts], self._point_colors(pts), "general",
                       float(np.median(err)) if len(err) else float("nan"), self.notes, self.timings,
                       point_frames=self._point_frames(pts))
        self._all_errors(sol, pts)
        return sol

    def _point_frames(self, pts: np.ndarray) -> np.ndarray:
        """int [len(pts),2]: the first and last frame of each track's observations kept."""
        tr = self.tracks
        kept = self.obs_ok & np.isin(tr.track, pts)
        first = np.full(tr.n_tracks, self.T - 1)
        last = np.zeros(tr.n_tracks, dtype=np.int64)
        np.minimum.at(first, tr.track[kept], tr.frame[kept])
        np.maximum.at(last, tr.track[kept], tr.frame[kept])
        return np.stack([first[pts], last[pts]], axis=1)

    def _all_errors(self, sol: Solution, pts: np.ndarray):
        """Median error over every observation of the solution's tracks, outliers included."""
        tr = self.tracks
        m = self.reg[tr.frame] & np.isin(tr.track, pts)
        if m.any():
            e = reprojection_errors(self.Rw, self.tw, self.X, self.K, tr.frame[m], tr.track[m], tr.xy[m])
            sol.reproj_all_px = float(np.median(e))
            sol.rejected = float(1 - self.obs_ok[m].mean())

    def _point_colors(self, pts):
        tr = self.tracks
        m = np.isin(tr.track, pts)
        t, first = np.unique(tr.track[m], return_index=True)
        idx = np.flatnonzero(m)[first]
        return _sample_colors(self.frames, tr.frame[idx], tr.xy[idx])

    # ---- rotation only -------------------------------------------------------------------------

    def _solve_rotation(self) -> Solution:
        """Cameras that only rotate (t = 0); points are directions placed at distance 1."""
        T, tr = self.T, self.tracks
        self.notes.append("rotation-only cameras: no parallax to recover translation")
        self.Rw = np.tile(np.eye(3), (T, 1, 1))
        self.tw = np.zeros((T, 3))
        self.reg = np.zeros(T, bool)
        self.reg[0] = True
        self.obs_ok = np.ones(len(tr.frame), bool)
        self.track_end = np.full(tr.n_tracks, T)
        K, Ki = self.K, np.linalg.inv(self.K)
        for k in range(1, T):
            _, xa, xb = tr.common(k - 1, k)
            Hm = None
            if len(xa) >= 8:
                Hm, _ = robust_fit(cv2.findHomography, xa, xb, cv2.USAC_MAGSAC, 1.0)
            if Hm is None:
                self.notes.append(f"frame {k}: no homography to frame {k - 1}, rotation copied")
                Rrel = np.eye(3)
            else:
                Rrel = _polar(Ki @ Hm @ K)
            self.Rw[k] = Rrel @ self.Rw[k - 1]
            self.reg[k] = True
            self.progress(T + k + 1, 2 * T)
        # each track becomes a point along its first ray (depth is unobservable without parallax)
        t, first = np.unique(tr.track, return_index=True)
        xy = tr.xy[first]
        rays = np.concatenate([xy, np.ones((len(xy), 1))], 1) @ Ki.T
        self.X = np.einsum("nji,nj->ni", self.Rw[tr.frame[first]], rays / rays[:, 2:3])
        free = np.ones(T, bool)
        free[0] = False
        for iters in (20, 10):
            self._run_ba(free, iters=iters, opt_focal=not self.focal_given, fix_translation=True, rest=iters == 10)
        ci, pi, obs, pts, _ = self._ba_problem(np.ones(T, bool))
        X = self.X[pts]
        X = X / np.linalg.norm(X, axis=1, keepdims=True)
        err = reprojection_errors(self.Rw, self.tw, X, self.K, ci, pi, obs)
        c2w = np.tile(np.eye(4), (T, 1, 1))
        c2w[:, :3, :3] = np.transpose(self.Rw, (0, 2, 1))
        sol = Solution(c2w, self.K, X, self._point_colors(pts), "rotation",
                       float(np.median(err)) if len(err) else float("nan"), self.notes, self.timings,
                       point_frames=self._point_frames(pts))
        self.X[pts] = X
        self._all_errors(sol, pts)
        return sol


def known_camera_points(frames: np.ndarray, masks: np.ndarray | None, cams):
    """Sparse points for given cameras: KLT tracks triangulated with the cameras' poses and
    refined with the poses fixed. Falls back to unit-depth points when the cameras have no
    baseline (e.g. identity poses). Returns (points [P,3], colors [P,3], median reprojection px)."""
    tr = Tracker(frames, masks, cams.focal, K=cams.K)
    gray = to_gray(frames)
    tr.static = static_masks(masks, gray, tr.notes)
    T = len(frames)
    if T >= 2:
        tr.tracks = klt_tracks(gray, tr.static, tr.max_corners)
        w2c = np.linalg.inv(cams.c2w)
        tr.Rw, tr.tw = w2c[:, :3, :3].copy(), w2c[:, :3, 3].copy()
        tr.reg = np.ones(T, bool)
        tr.X = np.full((tr.tracks.n_tracks, 3), np.nan)
        tr.obs_ok = np.ones(len(tr.tracks.frame), bool)
        tr.track_end = np.full(tr.tracks.n_tracks, T)
        for k in range(1, T):
            tr._triangulate_frame(k)
        if tr._has().sum() >= 50:
            tr._run_ba(np.zeros(T, bool), iters=10, rest=True)
            ci, pi, obs, pts, _ = tr._ba_problem(np.ones(T, bool))
            err = reprojection_errors(tr.Rw, tr.tw, tr.X[pts], tr.K, ci, pi, obs)
            return tr.X[pts], tr._point_colors(pts), float(np.median(err))
    pts, cols = unit_depth_points(frames, cams.K, static=tr.static)
    # frame 0's camera coordinates -> world
    return pts @ cams.c2w[0, :3, :3].T + cams.c2w[0, :3, 3], cols, float("nan")
