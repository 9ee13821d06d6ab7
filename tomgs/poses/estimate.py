"""`estimate_cameras`: one entry point for every way of getting cameras for a clip."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tomgs.cameras import Cameras, intrinsics
from tomgs.errors import InputError, counted

METHODS = ("auto", "identity", "a .json/.npy pose file, a COLMAP text folder, or an .onnx model")


@dataclass
class PoseReport:
    """What estimate_cameras did.

    method: "auto", "identity", "file" or "onnx"; mode: "fixed", "rotation", "general" (auto) or
    the method; frames: T; focal: px; focal_estimated: True if it was not given;
    reproj_px: median reprojection error of the background track observations kept by the final
    adjustment (nan if not measured); reproj_all_px: the same over all observations of those
    tracks, rejected outliers included; rejected: the fraction rejected;
    seconds: wall time; points: P; notes: what was detected, skipped or assumed;
    point_frames: int [P,2], the first and last frame each point was tracked in (None: points not
    from tracks, such as a fixed camera's or known cameras', taken as seen throughout);
    keyframes: int [K], the frames solved in the bundle adjustment (the others were registered
    to them), or None.
    """

    method: str
    mode: str
    frames: int
    focal: float
    focal_estimated: bool
    reproj_px: float
    seconds: float
    points: int
    notes: list = field(default_factory=list)
    timings: dict = field(default_factory=dict)
    reproj_all_px: float = float("nan")
    rejected: float = float("nan")
    point_frames: np.ndarray | None = None
    keyframes: np.ndarray | None = None

    def summary(self) -> str:
        err = "n/a" if not np.isfinite(self.reproj_px) else f"{self.reproj_px:.2f} px"
        f = f"{self.focal:.1f} px" + (" (estimated)" if self.focal_estimated else "")
        return (f"{counted(self.frames, 'frame')}, {self.mode} cameras ({self.method}), focal {f}, "
                f"reprojection error {err}, {self.points} points, {self.seconds:.1f} s")


def estimate_cameras(frames, masks=None, method="auto", focal=None, progress=None, device=None):
    """Cameras and a sparse coloured point cloud for a clip.

    frames: uint8 [T,H,W,3] RGB, or any sequence of uint8 [H,W,3] frames (the tracker reads each
            once, in order, and keeps its tracks, no copy of a frame), or a `tomgs.io.Video`, whose
            masks are then used by default.
    masks:  bool [T,H,W] (or a sequence of bool [H,W]), True on moving content (ignored for pose
            estimation), or None.
    method: "auto" (the built-in tracker), "identity" (a fixed camera), a path to a cameras
            .json (Cameras.save), an AnyCam c2w .npy (K from `focal` or 1.2 x max(W, H)), a COLMAP
            text model folder, or an .onnx model (contract in tomgs.poses.onnx_model).
    focal:  focal length in pixels if known; None lets `auto` estimate it.
    progress: optional callable(done, total), called at least once per frame read and tracked
            and between the solver's steps.
    device: where the tracker's bundle adjustment and registration run ("cuda", "cpu"); None:
            CUDA when torch sees it.
    Returns (Cameras, points float64 [P,3] (world), colors float32 [P,3] in [0,1], PoseReport).
    Raises InputError for bad frames, masks or methods.
    """
    t0 = time.perf_counter()
    from tomgs.io import Video

    indices = None
    if isinstance(frames, Video):
        masks = frames.masks if masks is None else masks
        indices = frames.indices
        frames = frames.frames
    if isinstance(frames, np.ndarray) and (frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8):
        raise InputError(f"frames must be uint8 [T,H,W,3] with T >= 1, got {frames.dtype} {frames.shape}")
    if len(frames) == 0:
        raise InputError("frames must be uint8 [T,H,W,3] with T >= 1, got no frames")
    T = len(frames)
    first = np.asarray(frames[0])  # the rest are checked as they are read
    if first.ndim != 3 or first.shape[-1] != 3 or first.dtype != np.uint8:
        raise InputError(f"frames must be uint8 [T,H,W,3] with T >= 1, got frame 0 as {first.dtype} {first.shape}")
    H, W = first.shape[:2]
    if isinstance(masks, np.ndarray) and masks.shape != (T, H, W):
        raise InputError(f"masks must be bool [T,H,W] = {(T, H, W)} like the frames, got {masks.shape}")
    if focal is not None and not (np.isfinite(focal) and focal > 0):
        raise InputError(f"focal must be a positive number of pixels, got {focal}")

    if isinstance(method, (str, Path)) and str(method) == "auto":
        from tomgs.poses.auto import Tracker

        sol = Tracker(frames, masks, focal, progress, device=device).solve()
        cams = Cameras.create(sol.c2w, sol.K, W, H, indices)
        rep = PoseReport("auto", sol.mode, T, cams.focal, focal is None and sol.mode != "fixed", sol.reproj_px,
                         0.0, len(sol.points), list(sol.notes), dict(sol.timings), sol.reproj_all_px, sol.rejected,
                         sol.point_frames, sol.keyframes)
        pts, cols = sol.points, sol.colors
    elif isinstance(method, (str, Path)) and str(method) == "identity":
        from tomgs.poses.twoview import unit_depth_points

        K = intrinsics(focal if focal is not None else 1.2 * max(W, H), W, H)
        cams = Cameras.identity(T, K, W, H, indices)
        static = None if masks is None else ~np.asarray(masks[0], dtype=bool)  # moving content left out
        pts, cols = unit_depth_points(first, K, static=static)
        rep = PoseReport("identity", "identity", T, cams.focal, False, float("nan"), 0.0, len(pts),
                         ["identity poses requested" + ("" if focal is not None else "; focal assumed 1.2 x image side")])
    else:
        path = Path(method)
        if path.suffix.lower() == ".onnx":
            from tomgs.poses.onnx_model import run_onnx

            try:
                cams = run_onnx(path, np.asarray(frames), indices)
            except InputError as e:  # Cameras' own checks do not know the file
                raise InputError(str(e) if str(path) in str(e) else f"{path}: {str(e).removeprefix('Cameras: ')}") \
                    from None
            kind = "onnx"
        else:
            cams = load_cameras(path, W, H, focal, indices)
            kind = "file"
        if len(cams) != T:
            raise InputError(f"{path} gives {len(cams)} cameras for {T} frames: poses must match the frames "
                             "(same --frames range)")
        if (cams.width, cams.height) != (W, H):
            cams = cams.resized(W, H)
        from tomgs.poses.auto import known_camera_points

        pts, cols, err = known_camera_points(frames, masks, cams)
        rep = PoseReport(kind, kind, T, cams.focal, False, err, 0.0, len(pts), [f"cameras from {path}"])
    rep.seconds = time.perf_counter() - t0
    return cams, pts, cols, rep


def load_cameras(path: Path, width: int, height: int, focal=None, indices=None) -> Cameras:
    """Cameras from a file: tomgs .json, AnyCam c2w .npy (with K from `focal`, or an npy/txt K
    file next to it named K.npy / K.txt / intrinsics.npy), or a COLMAP text model folder."""
    if not path.exists():
        text = str(path)
        if path.suffix or "/" in text or "\\" in text:  # names a file or folder: say which is missing
            raise InputError(f"pose file {path} does not exist: give the path of a cameras .json, an AnyCam "
                             "c2w .npy, a COLMAP text folder or an .onnx model, or --poses auto")
        raise InputError(f"unknown method {text!r}: use {', '.join(METHODS)}")
    if path.is_dir():
        return Cameras.from_colmap(path)
    suffix = path.suffix.lower()
    if suffix == ".json":
        return Cameras.load(path)
    if suffix == ".npy":
        K = None
        for name in ("K.npy", "K.txt", "intrinsics.npy", "intrinsics.txt"):
            if (path.parent / name).is_file():
                K = path.parent / name
                break
        if focal is not None or K is None:
            K = intrinsics(focal if focal is not None else 1.2 * max(width, height), width, height)
        return Cameras.from_anycam(path, K, width, height)
    raise InputError(f"{path}: unsupported pose file; use {', '.join(METHODS)}")
