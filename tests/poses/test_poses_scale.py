"""The tracker at scale: keyframes, registration of the frames between them, portrait clips, and
what it keeps in memory (small synthetic clips, CPU)."""

import tracemalloc

import numpy as np
import pytest

from tomgs.poses import estimate_cameras
from tomgs.poses.ba import refine_poses
from tomgs.poses.synthetic import make_clip, noise_texture, orbit, trajectory_errors, umeyama
from tomgs.poses.tracks import WorkingFrames


def frame_errors(est, gt):
    """Per frame (position error / path length, rotation error in degrees) of c2w [T,4,4] after
    a similarity alignment of all camera centres."""
    s, R, t = umeyama(est[:, :3, 3], gt[:, :3, 3])
    pos = np.linalg.norm(s * est[:, :3, 3] @ R.T + t - gt[:, :3, 3], axis=1)
    path = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum()
    cos = (np.einsum("kij,kij->k", gt[:, :3, :3], est[:, :3, :3]) - 1) / 2
    return pos / path, np.degrees(np.arccos(np.clip(cos, -1, 1)))


@pytest.fixture(scope="module")
def slow_clip():
    """A slow sideways camera: 40 frames over a short path."""
    clip = make_clip(orbit(40, strafe=1.0), width=240, height=180, focal=225.0, mover=True, seed=4)
    return clip, estimate_cameras(clip.frames, clip.masks)


def test_slow_clip_solves_few_keyframes_and_poses_every_frame(slow_clip):
    clip, (cams, pts, _, rep) = slow_clip
    keys = rep.keyframes
    assert keys[0] == 0 and keys[-1] == 39 and len(keys) <= 20, keys
    assert len(cams) == 40 and rep.mode == "general"
    traj, rot = trajectory_errors(cams.c2w, clip.c2w)
    assert traj <= 0.02 and rot <= 1.0, (traj, rot)
    assert abs(cams.focal / 225 - 1) <= 0.05, cams.focal
    assert any("of 40 frames solved together as keyframes" in n for n in rep.notes)


def test_registered_frames_match_ground_truth(slow_clip):
    """The frames between keyframes (registered, not in the bundle) are as good as the keyframes."""
    clip, (cams, _, _, rep) = slow_clip
    rest = np.setdiff1d(np.arange(40), rep.keyframes)
    assert len(rest) >= 20
    pos, rot = frame_errors(cams.c2w, clip.c2w)
    assert pos[rest].max() <= 0.02 and rot[rest].max() <= 1.0, (pos[rest].max(), rot[rest].max())
    # the median error covers the registered frames' observations too
    assert rep.reproj_px < 0.5 and rep.point_frames[:, 1].max() == 39


def test_refine_poses_recovers_perturbed_cameras():
    """Pose-only refinement of many cameras at once from perturbed starts, with 10% outliers."""
    rng = np.random.default_rng(0)
    C, P = 12, 300
    X = rng.uniform([-2, -1.5, 4], [2, 1.5, 8], (P, 3))
    c2w = orbit(C, strafe=1.5)
    w2c = np.linalg.inv(c2w)
    K = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
    cam = np.repeat(np.arange(C), P)
    pt = np.tile(np.arange(P), C)
    Xc = np.einsum("nij,nj->ni", w2c[cam, :3, :3], X[pt]) + w2c[cam, :3, 3]
    obs = Xc[:, :2] / Xc[:, 2:] @ K[:2, :2].T + K[:2, 2] + rng.normal(0, 0.2, (len(cam), 2))
    bad = rng.random(len(cam)) < 0.1
    obs[bad] += rng.uniform(-40, 40, (bad.sum(), 2))
    import cv2

    R0 = np.stack([cv2.Rodrigues(rng.normal(0, 0.02, 3))[0] for _ in range(C)]) @ w2c[:, :3, :3]
    t0 = w2c[:, :3, 3] + rng.normal(0, 0.05, (C, 3))
    R, t, err = refine_poses(R0, t0, X[pt], K, cam, obs, iters=20, device="cpu")
    assert np.abs(R - w2c[:, :3, :3]).max() < 2e-3 and np.abs(t - w2c[:, :3, 3]).max() < 5e-3
    assert np.median(err[~bad]) < 0.3 and np.median(err[bad]) > 5


def test_portrait_clip():
    clip = make_clip(orbit(24, strafe=2.4), width=180, height=320, focal=300.0, mover=True, seed=5)
    cams, pts, _, rep = estimate_cameras(clip.frames, clip.masks)
    assert (cams.width, cams.height) == (180, 320) and rep.mode == "general"
    traj, rot = trajectory_errors(cams.c2w, clip.c2w)
    assert traj <= 0.02 and rot <= 1.0, (traj, rot)
    assert abs(cams.focal / 300 - 1) <= 0.05, cams.focal
    assert np.allclose(cams.K[:2, 2], [90, 160])


class SlidingFrames:
    """A sequence of uint8 [H,W,3] frames cut from a larger texture (a sideways pan of `step` pixels a
    frame; 0: a fixed camera), made when read, so the clip never exists as one array; counts the reads."""

    def __init__(self, T, W, H, step=4):
        self.T, self.W, self.H, self.step = T, W, H, step
        self.texture = noise_texture(np.random.default_rng(0), H + 8, W + step * T)
        self.reads = 0

    def __len__(self):
        return self.T

    def __getitem__(self, k):
        if not 0 <= k < self.T:
            raise IndexError(k)
        self.reads += 1
        return self.texture[4:4 + self.H, self.step * k:self.step * k + self.W].copy()


def test_frames_are_read_once_and_kept_small():
    """1080p frames read one at a time: each once, and the peak of Python-side allocations a fraction
    of the clip's uint8 size: two frames, one pair's flow and the tracks (0.18 of 24 frames; 0.33
    with a gray, colour and mask copy of every frame; >= 1.33 holding the clip and its gray copy)."""
    frames = SlidingFrames(24, 1920, 1080)
    clip_bytes = 24 * 1920 * 1080 * 3
    tracemalloc.start()
    try:
        cams, _, _, rep = estimate_cameras(frames, focal=1500.0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert frames.reads == 25  # each frame once, and frame 0 once more to check it up front
    assert peak < 0.25 * clip_bytes, (peak / 1e6, clip_bytes / 1e6)
    assert (cams.width, cams.height) == (1920, 1080) and len(cams) == 24
    work = WorkingFrames(SlidingFrames(3, 1920, 1080))
    gray, colour, moving = work.first
    assert gray.shape == (540, 960) and colour.shape == (270, 480, 3) and moving is None and work.scale == 0.5
    assert [g.shape for g, _, _ in work] == [(540, 960)] * 3 and work.frames.reads == 3


@pytest.mark.parametrize("W, H, step, T", [(320, 180, 0, 12), (192, 108, 3, 12)], ids=["fixed", "pan"])
def test_tracker_keeps_no_copy_of_each_frame(W, H, step, T):
    """What the tracker keeps per frame is its tracks (32 bytes an observation: at most 0.15
    of a frame at these sizes), never copies of the frames. Growing the clip from T to 4T frames may
    add at most 0.3 of a frame's uint8 size per frame to the peak of Python-side allocations; the
    tracker that kept a gray, a colour and a mask copy of every frame added 1.4-1.8 (a fixed camera
    and a pan)."""
    def peak(frames):
        tracemalloc.start()
        try:
            estimate_cameras(SlidingFrames(frames, W, H, step), focal=0.8 * W, device="cpu")
            return tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()

    per_frame = (peak(4 * T) - peak(T)) / (3 * T)
    assert per_frame < 0.3 * W * H * 3, per_frame / (W * H * 3)


def test_runs_of_observations_change_no_result(monkeypatch):
    """The bundle adjustment sums its normal equations, the registration refines its cameras and the
    errors are measured a run of observations at a time (the memory is a run's, not the clip's): the
    cameras and points are exactly those of one piece."""
    import tomgs.poses.auto as auto
    import tomgs.poses.ba as ba

    clip = make_clip(orbit(24, strafe=1.0), width=200, height=150, focal=190.0, seed=4)
    whole = estimate_cameras(clip.frames, focal=190.0, device="cpu")
    calls = []
    refine = auto.refine_poses
    monkeypatch.setattr(auto, "refine_poses", lambda *a, **k: calls.append(len(a[4])) or refine(*a, **k))
    monkeypatch.setattr(ba, "BA_RUN", 701)
    monkeypatch.setattr(ba, "ERROR_RUN", 997)
    monkeypatch.setattr(auto, "REGISTER_RUN", 600)
    runs = estimate_cameras(clip.frames, focal=190.0, device="cpu")
    assert len(calls) >= 6, calls  # two passes, each in runs
    assert whole[3].mode == runs[3].mode == "general" and len(whole[3].keyframes) < 24
    assert np.array_equal(whole[0].c2w, runs[0].c2w) and np.array_equal(whole[0].K, runs[0].K)
    assert np.array_equal(whole[1], runs[1]) and np.array_equal(whole[2], runs[2])


def test_progress_is_reported_often(slow_clip):
    clip, _ = slow_clip
    calls = []
    estimate_cameras(clip.frames, clip.masks, focal=225.0, progress=lambda d, t: calls.append((d, t)))
    done = [d for d, _ in calls]
    # once per frame as it is read and tracked (one pass), then between the solver's steps
    assert done[:40] == list(range(1, 41)) and len(calls) >= 40 + 20
    assert done == sorted(done) and calls[-1] == (80, 80)
