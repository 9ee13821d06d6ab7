"""Stiff clips stay finite and converge: a hard scene cut, a static clip, a single frame."""

from __future__ import annotations

import numpy as np
import torch

from tomgs.cameras import Cameras, intrinsics
from tomgs.train import Trainer, preset
from tests.train.test_train import synthetic_clip


def fit(frames, cams, iterations=120, **settings):
    config = preset("quick", iterations=iterations, log_interval=20, eval_interval_s=0.0, init_points_per_frame=300,
                    max_gaussians=3000, densify_start_fraction=35 / iterations,
                    densify_stop_fraction=0.75, densify_interval=20, **settings)
    result = Trainer(frames, cams, np.zeros((0, 3)), np.zeros((0, 3), np.float32), config, torch.device("cpu")).run()
    for name, value in result.model.parameters_by_name().items():
        assert torch.isfinite(value).all(), name
    clip = [r["clip_psnr"] for r in result.history if r["clip_psnr"] != ""]  # rows right after a densification: none
    assert all(np.isfinite(clip))
    return clip


def fixed_cameras(n, width, height):
    return Cameras.create(np.repeat(np.eye(4)[None], n, 0), intrinsics(width, width, height), width, height)


def test_hard_scene_cut():
    """Two unrelated shots back to back: the windows of the first must close at the cut."""
    first, _, _, _ = synthetic_clip(3, 32, 18)
    second = np.ascontiguousarray(255 - first[:, ::-1])  # another picture entirely
    frames = np.concatenate([first, second])
    clip = fit(frames, fixed_cameras(6, 32, 18), iterations=300)
    assert clip[-1] > clip[0] + 5 and clip[-1] > 24


def test_static_clip():
    frame, _, _, _ = synthetic_clip(1, 32, 18)
    clip = fit(np.repeat(frame, 5, axis=0), fixed_cameras(5, 32, 18))
    assert clip[-1] > clip[0] + 5 and clip[-1] > 24


def test_flat_static_clip_keeps_its_depth_order():
    """A flat picture seen by a still camera: its Gaussians start on one plane, and which of them is in
    front is settled by depth differences of a few float32 ulps. A sort that read 21 bits of depth (ties
    below 2^-12 relative, drawn in index order) ended this fit at 41.2 dB; 25 bits, every bit and the 29
    it reads (tomgs.constants.DEPTH_SORT_BITS) at 43.4 (the run repeats exactly, at any thread count). Those
    figures are at the depth jitter they were measured with, 0.1: at the default 0.3 the same fit starts
    slower and ends at 40.0 dB with the same 29 bits (53.6 against 55.2 at 600 steps), which says nothing of
    the sort."""
    frame, _, _, _ = synthetic_clip(1, 32, 18)
    clip = fit(np.repeat(frame, 5, axis=0), fixed_cameras(5, 32, 18), iterations=300, init_depth_jitter=0.1)
    assert clip[-1] > 42.5


def test_single_frame():
    frame, _, _, _ = synthetic_clip(1, 32, 18)
    clip = fit(frame, fixed_cameras(1, 32, 18), iterations=60)
    assert clip[-1] > clip[0] + 3
