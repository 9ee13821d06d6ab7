"""The built-in, weight-free camera tracker.

frames (+ moving masks), read once, one at a time, into small copies at a working resolution
(tracks.WorkingFrames) -> static-region masks -> KLT tracks, in one pass that keeps the tracks and
no copy of any frame -> [fixed camera? -> identity] -> keyframes (track survival and image motion)
-> on the keyframes: init pair (0, j) chosen by parallax left after a homography -> focal, when
unknown, by self-calibration on a log grid and trial reconstructions -> essential matrix
(USAC_MAGSAC) + a chirality vote + triangulation -> PnP (RANSAC + LM) per new keyframe,
triangulating new tracks, windowed bundle adjustment -> final robust bundle adjustment (focal
refined) -> frame 0 = identity, median depth of frame 0's points = 1 -> the other frames registered
to the keyframes' points (start between their two keyframes, one batched pose-only refinement, a
run of frames at a time), so the cost grows linearly with the frames and the memory with the tracks.
A clip whose views are all related by homographies (pure rotation, or a very distant scene)
is solved with rotation-only cameras. Pixel thresholds inside are in working pixels; the
Solution is in the input frames' pixels.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from tomgs.cameras import intrinsics
from tomgs.poses.ba import bundle_adjust, pick_device, refine_poses, reprojection_errors, so3_exp
from tomgs.poses.tracks import KLT, WORK_SIDE, FlowMotion, Tracks, WorkingFrames, robust_fit, select_keyframes
from tomgs.poses.twoview import nearest_rotation, recover_pose, scale_K, triangulate, unit_depth_points
from tomgs.runtime import one_cpu_thread

REGISTER_RUN = 1 << 16  # observations refined at once when the frames between keyframes are registered
FLAT_ERROR = 1.1  # focal trials within this factor of the best error fit the views about as well
FIXED_PX = 0.3  # working pixels: a camera that moves the background less than this in every frame is fixed


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
    keyframes: np.ndarray | None = None  # int [K]: the frames solved in the bundle (None: no keyframes)


def static_frames(clip: WorkingFrames, notes: list):
    """Each frame of `clip` with its static mask, in order: (k, gray, colour, static bool [h,w], True
    where pixels may be used). The mask is the given moving mask dilated or, without masks, flow
    residuals (then a frame comes out when the next one has been read: its mask needs both pairs)."""
    T, (w, h) = len(clip), clip.work
    r = max(1, round(0.01 * max(h, w)))
    kern = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    flow = FlowMotion(h, w) if clip.masks is None and T >= 2 else None
    bad, waiting = 0, None  # the frame whose flow mask needs the next one

    def static_of(moving):
        nonlocal bad
        static = np.ones((h, w), bool) if moving is None else ~moving
        if static.mean() < 0.15:  # a mask that leaves almost nothing is more likely wrong than the scene
            static[:] = True
            bad += 1
        return static

    for k, (gray, colour, moving) in enumerate(clip):
        if moving is not None:
            yield k, gray, colour, static_of(cv2.dilate(moving.astype(np.uint8), kern) > 0)
        elif flow is None:
            yield k, gray, colour, static_of(None)
        else:
            done = flow.push(gray)
            if waiting is not None:
                yield (*waiting, static_of(done))
            waiting = (k, gray, colour)
    if waiting is not None:
        yield (*waiting, static_of(flow.finish()))
    if bad:
        notes.append(f"{bad} frame{'s' if bad != 1 else ''} masked over 85%: their masks were ignored")


def is_fixed_camera(gray: dict, static0: np.ndarray, thresh_px: float = FIXED_PX) -> bool:
    """True if static corners of frame 0 stay within `thresh_px` in a handful of later frames.
    gray: {frame: uint8 [h,w]} holding frame 0 and the later frames to compare (fixed_probes);
    static0: bool [h,w], frame 0's static mask."""
    pts = cv2.goodFeaturesToTrack(gray[0], 400, 0.01, 8, mask=static0.astype(np.uint8) * 255)
    if pts is None or len(pts) < 20:
        return False
    for k in sorted(set(gray) - {0}):
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(gray[0], gray[k], pts, None, winSize=(21, 21), maxLevel=3)
        ok = st.ravel() == 1
        if ok.sum() < 0.5 * len(pts):
            return False
        if np.median(np.linalg.norm((nxt - pts).reshape(-1, 2)[ok], axis=1)) > thresh_px:
            return False
    return True


def fixed_probes(T: int) -> set:
    """The frames is_fixed_camera compares: 0, 1 and the clip's quarters."""
    return {0, 1, T // 4, T // 2, (3 * T) // 4, T - 1} & set(range(T))


class Tracker:
    """One run of the built-in tracker on a clip; `solve()` returns a `Solution`.

    frames uint8 [T,H,W,3] RGB or a sequence of uint8 [H,W,3]; masks bool [T,H,W] (or a sequence
    of [H,W]; True = moving) or None; focal px or None (estimated); progress callable(done,
    total) or None; K [3,3] to use instead of a centred square-pixel K built from the focal
    (known cameras); work_side: long side of the working resolution; device: where the bundle
    adjustment and the registration run (default: CUDA when torch sees it).
    State while solving, in working pixels: poses as world-to-camera Rw [T,3,3], tw [T,3];
    X [n_tracks,3] (nan until triangulated); obs_ok bool per track observation. While the
    keyframes are solved, T, tracks and frame numbers are the keyframes' (self.keys maps them back).
    """

    def __init__(self, frames, masks=None, focal=None, progress=None, max_corners=None, K=None,
                 work_side: int = WORK_SIDE, device=None):
        self.T_all = self.T = len(frames)
        self._progress_fn = progress or (lambda done, total: None)
        self._done = 0
        self.clip = WorkingFrames(frames, masks, work_side)  # reads frame 0; the rest when tracked
        self.timings: dict[str, float] = {}
        self.W, self.H = self.clip.work
        self.scale = self.clip.scale
        self.K_full = None if K is None else np.asarray(K, dtype=np.float64)
        self.K_given = None if K is None else scale_K(self.K_full, self.scale)
        self.focal_given = focal is not None
        self.focal = float(focal) * self.scale if focal is not None else 1.2 * max(self.W, self.H)
        self.focal_first = self.focal  # a fixed camera's: its focal cannot be measured
        self.max_corners = max_corners or int(np.clip(self.W * self.H / 150, 300, 1500))
        self.device = pick_device(device)
        self.notes: list[str] = []
        self.side = max(self.W, self.H)
        self.min_angle = 0.5  # degrees between rays for a new point; set from the first pair
        self.keys = np.arange(self.T)
        self.keyframes = None  # the keyframes once solved: int [K]

    @property
    def K(self):
        return self.K_given if self.K_given is not None else intrinsics(self.focal, self.W, self.H)

    def _progress(self, units: float):
        """Report progress out of 2 T_all: reading and tracking [0, T], keyframes [T, 1.8 T],
        registration [1.8 T, 2 T]; never backwards, and repeated as a heartbeat during long steps."""
        self._done = max(self._done, min(int(units), 2 * self.T_all))
        self._progress_fn(self._done, 2 * self.T_all)

    def _tick(self, name, t0):
        self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - t0
        return time.perf_counter()

    def _frame_no(self, k: int) -> int:
        """The clip's frame number of solver frame k (a keyframe while keyframes are solved)."""
        return int(self.keys[k])

    # ---- top level -----------------------------------------------------------------------------

    def track(self, probes=()) -> tuple[Tracks | None, np.ndarray, dict]:
        """One pass over the frames, each read once: static masks and KLT tracks (none for a single
        frame). Returns (the tracks, frame 0's static mask bool [h,w], {k: gray} of the frames in
        `probes`); no other copy of a frame outlives its turn."""
        klt = KLT(self.max_corners) if self.T_all > 1 else None
        static0, grays = None, {}
        for k, gray, colour, static in static_frames(self.clip, self.notes):
            static0 = static if k == 0 else static0
            if k in probes:
                grays[k] = gray
            if klt is not None:
                klt.add(gray, static, colour)
            self._progress(k + 1)
        return None if klt is None else klt.tracks(), static0, grays

    def solve(self) -> Solution:
        """The cameras and points of the clip (on a CPU with torch in one thread: tomgs.runtime.one_cpu_thread)."""
        with one_cpu_thread(self.device):
            return self._solve()

    def _solve(self) -> Solution:
        t0 = time.perf_counter()
        T = self.T_all
        # the fixed-camera check comes after the pass: deciding first would mean reading twice
        all_tracks, static0, grays = self.track(fixed_probes(T))
        if T == 1 or is_fixed_camera(grays, static0):
            self._tick("tracks", t0)
            return self._fixed(static0, "single frame: identity pose" if T == 1 else
                               "fixed camera detected: identity poses, no poses solved")
        del grays
        tracked_notes = len(self.notes)  # what solving notes is moot if the camera turns out fixed
        self.keys = select_keyframes(all_tracks, T, self.side)
        self.tracks, self.key_obs = all_tracks.subset(self.keys)
        self.T = len(self.keys)
        self.notes.append(f"{self.T} of {T} frames solved together as keyframes, the others placed against them")
        t0 = self._tick("tracks", t0)
        j, general = self._init_pair()
        if not self.focal_given:
            self.focal = self._focal_search(j, general)
            if general:
                f = self._focal_trials(j)
                general = f is not None
                self.focal = f if general else self._focal_search(j, False)
            self.notes.append(f"focal length first guessed at {self.focal / self.scale:.1f} px from the first frames, "
                              "then solved with the cameras")
        t0 = self._tick("focal", t0)
        pts = self._solve_general(j) if general else None
        mode = "general"
        if pts is None:
            if general:
                self.notes.append("two-view start failed: fell back to rotation-only cameras")
            pts, mode = self._solve_rotation(), "rotation"
        t0 = self._tick("keyframes", t0)
        self._register_rest(all_tracks, mode == "rotation")
        self._tick("register", t0)
        shift = self._camera_shift(pts)
        if shift < FIXED_PX:  # what moved in front of it hid the fixed camera from is_fixed_camera
            del self.notes[tracked_notes:]
            return self._fixed(static0, f"fixed camera found by solving: the cameras move the background by at most "
                                        f"{shift / self.scale:.2f} px, identity poses")
        sol = self._solution(mode, pts)
        if len(sol.points) == 0:  # nothing trackable (blank frames): still give the trainer something
            sol.points, sol.colors = self._unit_depth(None)
            sol.point_frames = None
            self.notes.append("no trackable texture: points placed at depth 1 in front of frame 0")
        self._progress(2 * T)
        return sol

    def _fixed(self, static0: np.ndarray, note: str) -> Solution:
        """The Solution of a fixed camera: identity poses, points at depth 1 in front of frame 0."""
        self.notes.append(note)
        if not self.focal_given and self.T_all > 1:
            self.focal = self.focal_first
            self.notes.append("a fixed camera's focal length cannot be measured: 1.2 x the image side assumed "
                              "(give --focal if known)")
        pts, cols = self._unit_depth(static0)
        self._progress(2 * self.T_all)
        return Solution(np.tile(np.eye(4), (self.T_all, 1, 1)), self._full_K(), pts, cols, "fixed", float("nan"),
                        self.notes, self.timings)

    def _camera_shift(self, pts: np.ndarray, n: int = 500) -> float:
        """The largest, over the frames, 90th percentile of how far (working px) frame k's camera moves up to
        `n` of the points `pts` from where frame 0's camera sees them: the image motion that the cameras
        themselves make, whatever moved in front of them."""
        if len(pts) == 0:
            return np.inf
        X = self.X[pts[np.linspace(0, len(pts) - 1, min(n, len(pts))).astype(int)]]
        cam = np.einsum("tij,pj->tpi", self.Rw, X) + self.tw[:, None]  # [T,P,3]
        ok = (cam[..., 2] > 1e-9) & (cam[:1, :, 2] > 1e-9)
        uv = cam[..., :2] / np.where(ok, cam[..., 2], 1.0)[..., None] * np.diag(self.K)[:2]
        d = np.linalg.norm(uv - uv[:1], axis=-1)
        return float(max(np.percentile(dk[okk], 90) if okk.any() else np.inf for dk, okk in zip(d, ok)))

    def _full_K(self) -> np.ndarray:
        """K [3,3] in the input frames' pixels."""
        if self.K_full is not None:
            return self.K_full
        W, H = self.clip.size
        return intrinsics(self.focal / self.scale, W, H)

    def _unit_depth(self, static0: np.ndarray | None):
        """Points at depth 1 in front of frame 0 and their colours (frame 0's colour copy); static0:
        frame 0's static mask bool [h,w] or None."""
        img = self.clip.first[1]
        return unit_depth_points(img, scale_K(self._full_K(), img.shape[1] / self.clip.size[0]), static=static0)

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
        self.notes.append(f"little parallax: near and far points shift apart by at most {max(best_par, 0):.2f} px "
                          f"between frames ({need:.2f} px tells a camera's movement from its turning)")
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
        best, seen, fits = (np.inf, None), [], []
        for f in starts:
            self.focal = f
            pts = self._solve_general(j, frames=trial, report=False)
            self._progress(self._done)  # heartbeat: a trial takes a few seconds on a CPU
            if pts is not None:
                err = self._all_errors(pts)[0]
                seen.append(f"{f / self.scale:.0f}->{self.focal / self.scale:.0f} ({err / self.scale:.3f} px)")
                fits.append((err, self.focal))
                if err < best[0]:
                    best = (err, self.focal)
        self.notes.append("focal trials, start -> refined (median error): " + ", ".join(seen))
        # a flat valley (forward motion, a small orbit): focals far apart fit the views about as well
        close = [f for err, f in fits if err <= FLAT_ERROR * best[0]]
        if close and max(close) > 1.5 * min(close):
            self.notes.append(f"the focal length is weakly determined by this clip: trials refined to "
                              f"{min(close) / self.scale:.0f}-{max(close) / self.scale:.0f} px fit within "
                              f"{100 * (FLAT_ERROR - 1):.0f}% of the best error (give --focal if known)")
        return best[1]  # None: no start could be reconstructed

    # ---- general motion ------------------------------------------------------------------------

    def _solve_general(self, j: int, frames=None, report: bool = True) -> np.ndarray | None:
        """Incremental reconstruction of frame 0 and `frames` (all by default) from the pair (0, j)."""
        T, tr = self.T, self.tracks
        K = self.K
        self.reporting = report
        ids, x0, xj = tr.common(0, j)
        E, inl = robust_fit(cv2.findEssentialMat, x0, xj, K, cv2.USAC_MAGSAC, 0.999, 1.0)
        if E is None or E.shape != (3, 3):
            return None
        R, t, inl = recover_pose(E, x0, xj, K, inl.ravel() > 0)
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
                self._progress(self.T_all * (1 + 0.8 * (count + 2) / T))
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
                self.notes.append(f"frame {self._frame_no(k)}: too few tracked points for PnP, pose copied from "
                                  f"frame {self._frame_no(prev)}")
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
                                       iters=it, focal_bounds=bounds, device=self.device,
                                       tick=lambda: self._progress(self._done))
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

    def _finish(self, quick: bool = False) -> np.ndarray:
        """Final adjustment of every solved frame, then the gauge; returns the track ids with points."""
        free = self.reg.copy()
        free[0] = False
        opt_f = not self.focal_given
        # a free focal moves along a shallow valley: give it more iterations
        self._run_ba(free, iters=10 if quick else 30 if opt_f else 20, opt_focal=opt_f)
        if not quick:
            self._progress(self._done)
            self._run_ba(free, iters=15 if opt_f else 10, opt_focal=opt_f, rest=True)
        # gauge: frame 0 stays the identity; median depth of frame 0's points = 1
        ci, pi, obs, pts, _ = self._ba_problem(free | self.reg)
        in0 = np.unique(pi[ci == 0])
        d = self._cam_depths(0, pts[in0]) if len(in0) else self._cam_depths(0, pts)
        s = float(np.median(d[d > 0])) if (d > 0).any() else 1.0
        self.tw /= s
        self.X /= s
        return pts

    # ---- the frames between keyframes ----------------------------------------------------------

    def _register_rest(self, all_tracks: Tracks, rotation: bool):
        """Pose every frame from the solved keyframes and switch the state to all frames.

        A frame between keyframes a and b starts from their poses interpolated (rotation along
        the geodesic, translation linearly), then all such frames are refined at once against
        the points (pose only, Huber), observations far off are dropped, and refined again.
        Observations of a track after the keyframe solve ended it stay rejected."""
        T, keys, nK = self.T_all, self.keys, self.T
        is_key = np.zeros(T, bool)
        is_key[keys] = True
        a = np.searchsorted(keys, np.arange(T), side="right") - 1
        b = np.minimum(a + 1, nK - 1)
        w = np.where(b > a, (np.arange(T) - keys[a]) / np.maximum(keys[b] - keys[a], 1), 0.0)
        rel = self.Rw[b] @ np.transpose(self.Rw[a], (0, 2, 1))
        rotvec = np.stack([cv2.Rodrigues(r)[0].ravel() for r in rel])
        Rw = so3_exp(torch.as_tensor(w[:, None] * rotvec)).numpy() @ self.Rw[a]
        tw = (1 - w)[:, None] * self.tw[a] + w[:, None] * self.tw[b]
        Rw[keys], tw[keys] = self.Rw, self.tw
        # track ends found while solving keyframes, as clip frame numbers
        end = np.where(self.track_end < nK, keys[np.minimum(self.track_end, nK - 1)], T)
        ok = np.zeros(len(all_tracks.frame), bool)
        ok[self.key_obs] = self.obs_ok
        tr = all_tracks
        m = ~is_key[tr.frame] & self._has()[tr.track] & (tr.frame < end[tr.track])
        rest = np.flatnonzero(~is_key)
        if len(rest) and m.any():
            slot = np.cumsum(~is_key) - 1
            idx = np.flatnonzero(m)
            R, t = Rw[rest], tw[rest]
            inliers = lambda err: err <= max(0.5, 4 * float(np.median(err[np.isfinite(err)])))  # as _run_ba
            for iters in (8, 5):  # refine, drop what is far off, refine again
                self._progress(1.8 * T if iters == 8 else 1.9 * T)
                R, t, err = self._refine_runs(R, t, tr, idx, slot[tr.frame[idx]], rotation, iters)
                idx = idx[inliers(err)]
            ok[idx] = True
            count = np.bincount(slot[tr.frame[idx]], minlength=len(rest))
            good = count >= 10
            Rw[rest[good]], tw[rest[good]] = R[good], t[good]
            if not good.all():
                self.notes.append(f"{int((~good).sum())} frame(s) with under 10 tracked points: pose interpolated "
                                  "between their keyframes")
        self.tracks, self.T, self.keys = all_tracks, T, np.arange(T)
        self.Rw, self.tw, self.obs_ok = Rw, tw, ok
        self.reg = np.ones(T, bool)
        self.keyframes = keys

    def _refine_runs(self, R: np.ndarray, t: np.ndarray, tr: Tracks, idx: np.ndarray, cam: np.ndarray, rotation: bool,
                     iters: int):
        """refine_poses of cameras R [C,3,3], t [C,3] on observations idx [N] of tracks `tr` (cam [N]:
        their camera, nondecreasing), a run of cameras with at most REGISTER_RUN observations at a
        time: each camera's refinement is its own, so the result is the same, and the memory of the
        refinement (~1 kB an observation) and of the host's copies is one run's, not the clip's.
        Returns (R, t, error per observation [N])."""
        C = len(R)
        R, t, err = R.copy(), t.copy(), np.empty(len(idx))
        first = np.searchsorted(cam, np.arange(C + 1))  # camera c's observations: first[c]:first[c + 1]
        c0 = 0
        while c0 < C:
            c1 = min(C, max(c0 + 1, int(np.searchsorted(first, first[c0] + REGISTER_RUN, side="right")) - 1))
            o0, o1 = first[c0], first[c1]
            sel = idx[o0:o1]
            R[c0:c1], t[c0:c1], err[o0:o1] = refine_poses(R[c0:c1], t[c0:c1], self.X[tr.track[sel]], self.K,
                                                           cam[o0:o1] - c0, tr.xy[sel], fix_translation=rotation,
                                                           iters=iters, device=self.device)
            c0 = c1
        return R, t, err

    def _solution(self, mode: str, pts: np.ndarray) -> Solution:
        """The Solution of the current state for points `pts`, in the input frames' pixels."""
        tr = self.tracks
        m = self.obs_ok & np.isin(tr.track, pts)
        err = reprojection_errors(self.Rw, self.tw, self.X, self.K, tr.frame[m], tr.track[m], tr.xy[m])
        c2w = np.tile(np.eye(4), (self.T, 1, 1))
        c2w[:, :3, :3] = np.transpose(self.Rw, (0, 2, 1))
        c2w[:, :3, 3] = -np.einsum("nji,nj->ni", self.Rw, self.tw)
        all_px, rejected = self._all_errors(pts)
        return Solution(c2w, self._full_K(), self.X[pts], self._point_colors(pts), mode,
                        float(np.median(err)) / self.scale if len(err) else float("nan"), self.notes, self.timings,
                        all_px / self.scale, rejected, self._point_frames(pts), self.keyframes)

    def _point_frames(self, pts: np.ndarray) -> np.ndarray:
        """int [len(pts),2]: the first and last frame of each track's observations kept."""
        tr = self.tracks
        kept = self.obs_ok & np.isin(tr.track, pts)
        first = np.full(tr.n_tracks, self.T - 1)
        last = np.zeros(tr.n_tracks, dtype=np.int64)
        np.minimum.at(first, tr.track[kept], tr.frame[kept])
        np.maximum.at(last, tr.track[kept], tr.frame[kept])
        return np.stack([first[pts], last[pts]], axis=1)

    def _all_errors(self, pts: np.ndarray) -> tuple[float, float]:
        """(median error in working px over every observation of the tracks `pts`, outliers
        included; the fraction rejected). nan, nan without observations."""
        tr = self.tracks
        m = self.reg[tr.frame] & np.isin(tr.track, pts)
        if not m.any():
            return float("nan"), float("nan")
        e = reprojection_errors(self.Rw, self.tw, self.X, self.K, tr.frame[m], tr.track[m], tr.xy[m])
        return float(np.median(e)), float(1 - self.obs_ok[m].mean())

    def _point_colors(self, pts):
        """float32 [len(pts),3]: each track's colour where it was first seen (sampled while tracking)."""
        return self.tracks.colors[pts].astype(np.float32) / 255.0

    # ---- rotation only -------------------------------------------------------------------------

    def _solve_rotation(self) -> np.ndarray:
        """Cameras that only rotate (t = 0); points are directions placed at distance 1. Returns
        the track ids with points."""
        T, tr = self.T, self.tracks
        self.notes.append("the cameras only turn (rotation cameras): without parallax neither their movement nor "
                          "the scene's depth can be measured, so depth is a guess (a 3D box picks by direction, "
                          "not by distance)")
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
                self.notes.append(f"frame {self._frame_no(k)}: no homography to frame {self._frame_no(k - 1)}, "
                                  "rotation copied")
                Rrel = np.eye(3)
            else:
                Rrel = nearest_rotation(Ki @ Hm @ K)
            self.Rw[k] = Rrel @ self.Rw[k - 1]
            self.reg[k] = True
            self._progress(self.T_all * (1 + 0.4 * (k + 1) / T))
        # each track becomes a point along its first ray (depth is unobservable without parallax)
        t, first = np.unique(tr.track, return_index=True)
        xy = tr.xy[first]
        rays = np.concatenate([xy, np.ones((len(xy), 1))], 1) @ Ki.T
        self.X = np.full((tr.n_tracks, 3), np.nan)  # tracks seen only between keyframes get none
        self.X[t] = np.einsum("nji,nj->ni", self.Rw[tr.frame[first]], rays / rays[:, 2:3])
        free = np.ones(T, bool)
        free[0] = False
        for iters in (20, 10):
            self._run_ba(free, iters=iters, opt_focal=not self.focal_given, fix_translation=True, rest=iters == 10)
            self._progress(self._done)
        pts = self._ba_problem(np.ones(T, bool))[3]
        self.X[pts] /= np.linalg.norm(self.X[pts], axis=1, keepdims=True)
        return pts


def known_camera_points(frames, masks, cams):
    """Sparse points for given cameras: KLT tracks (at the working resolution) triangulated with
    the cameras' poses and refined with the poses fixed. Falls back to unit-depth points when the
    cameras have no baseline (e.g. identity poses). frames, masks: as `Tracker` takes them.
    Returns (points [P,3], colors [P,3], median reprojection px of the input frames)."""
    tr = Tracker(frames, masks, cams.focal, K=cams.K)
    tracks, static0, _ = tr.track()
    T = tr.T
    if T >= 2:
        tr.tracks = tracks
        w2c = np.linalg.inv(cams.c2w)
        tr.Rw, tr.tw = w2c[:, :3, :3].copy(), w2c[:, :3, 3].copy()
        tr.reg = np.ones(T, bool)
        tr.X = np.full((tr.tracks.n_tracks, 3), np.nan)
        tr.obs_ok = np.ones(len(tr.tracks.frame), bool)
        tr.track_end = np.full(tr.tracks.n_tracks, T)
        for k in range(1, T):
            tr._triangulate_frame(k)
        if tr._has().sum() >= 50:
            with one_cpu_thread(tr.device):
                tr._run_ba(np.zeros(T, bool), iters=10, rest=True)
            ci, pi, obs, pts, _ = tr._ba_problem(np.ones(T, bool))
            err = reprojection_errors(tr.Rw, tr.tw, tr.X[pts], tr.K, ci, pi, obs)
            return tr.X[pts], tr._point_colors(pts), float(np.median(err)) / tr.scale
    pts, cols = tr._unit_depth(static0)
    # frame 0's camera coordinates -> world
    return pts @ cams.c2w[0, :3, :3].T + cams.c2w[0, :3, 3], cols, float("nan")
