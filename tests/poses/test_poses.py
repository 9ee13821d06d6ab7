"""The built-in tracker on synthetic clips with known cameras (rendered here, no data files).

Accuracy is measured after a similarity (Umeyama) alignment of the camera centres; rotations are
compared as rotations relative to frame 0, which both trajectories share as the identity.
"""

import numpy as np
import pytest

from tomgs.io import InputError
from tomgs.poses import estimate_cameras
from tomgs.cameras import intrinsics
from tomgs.poses.synthetic import Plane, RenderedClip, look_at, make_clip, orbit, pan, room, textured
from tomgs.poses.synthetic import trajectory_errors as errors


@pytest.fixture(scope="module")
def orbit_clip():
    return make_clip(orbit(24, strafe=2.4), mover=True, seed=0)


def test_auto_unknown_focal_with_masks(orbit_clip):
    clip = orbit_clip
    cams, pts, cols, rep = estimate_cameras(clip.frames, clip.masks)
    assert any("focal trials" in n for n in rep.notes)
    assert not any("weakly determined" in n for n in rep.notes), rep.notes  # the orbit pins it
    traj, rot = errors(cams.c2w, clip.c2w)
    assert rep.mode == "general" and rep.focal_estimated
    assert traj <= 0.02, traj
    assert rot <= 1.0, rot
    assert abs(cams.focal / clip.K[0, 0] - 1) <= 0.05, cams.focal
    assert np.allclose(cams.c2w[0], np.eye(4))
    assert rep.reproj_px < 0.5
    # points: world coordinates in front of frame 0, median depth of frame 0's points ~ 1
    assert pts.shape[1] == 3 and len(pts) > 200 and cols.shape == pts.shape
    assert 0 <= cols.min() and cols.max() <= 1 and np.median(pts[:, 2]) > 0
    assert np.allclose(cams.times, np.arange(24) / 23)


def test_auto_flow_masks_unknown_focal():
    """Neither masks nor focal: the card is found by flow residuals, the focal by the search."""
    clip = make_clip(orbit(24, strafe=2.4), mover=True, seed=1)
    cams, _, _, rep = estimate_cameras(clip.frames)
    traj, rot = errors(cams.c2w, clip.c2w)
    assert traj <= 0.02 and rot <= 1.0, (traj, rot)
    assert abs(cams.focal / 300 - 1) <= 0.05, cams.focal


def test_auto_flow_masks_known_focal(orbit_clip):
    """No masks given: the moving card must be found by flow residuals."""
    clip = orbit_clip
    cams, _, _, rep = estimate_cameras(clip.frames, focal=300.0)
    traj, rot = errors(cams.c2w, clip.c2w)
    assert not rep.focal_estimated and cams.focal == 300.0
    assert traj <= 0.02 and rot <= 1.0, (traj, rot)


def test_fixed_camera_gives_identity():
    clip = make_clip(np.tile(np.eye(4), (10, 1, 1)), width=160, height=120, focal=150.0, mover=True)
    cams, pts, _, rep = estimate_cameras(clip.frames)
    assert rep.mode == "fixed" and any("fixed camera" in n for n in rep.notes)
    assert np.array_equal(cams.c2w, np.tile(np.eye(4), (10, 1, 1)))
    assert len(pts) > 0


def test_fixed_camera_with_things_moved_in_front_of_it():
    """A fixed camera over faint walls while six bright cards, still in frame 0, are moved one after another
    (hands rearranging blocks on a table): most of frame 0's strong corners move, the background does not.
    The camera is fixed, not a rotation camera with a focal made up from nothing."""
    rng = np.random.default_rng(5)
    walls = [Plane(p.o, p.u, p.v, (96 + 0.25 * p.texture).astype(np.uint8)) for p in room(rng)]
    spots = [(-1.1, -0.7), (0.1, -0.7), (-1.1, 0.1), (0.1, 0.1), (-0.5, -0.3), (0.6, -0.3)]
    cards = [textured(rng, [x, y, 2.0], [0.5, 0, 0], [0, 0.5, 0]) for x, y in spots]
    ways = [np.array(w) for w in ([0.6, 0.2, 0], [-0.4, 0.5, 0], [0.3, -0.6, 0], [-0.6, -0.3, 0], [0.5, 0.5, 0],
                                  [-0.2, 0.7, 0])]

    def scene_at(k):
        return walls + [Plane(c.o + np.clip((k - 3 - i) / 6, 0, 1) * w, c.u, c.v, c.texture)
                        for i, (c, w) in enumerate(zip(cards, ways))]

    T = 16
    clip = RenderedClip(scene_at, np.tile(np.eye(4), (T, 1, 1)), intrinsics(150.0, 160, 120), 160, 120, len(walls))
    cams, pts, _, rep = estimate_cameras(np.stack([clip.render(k)[1] for k in range(T)]), device="cpu")
    assert rep.mode == "fixed" and any("fixed camera found by solving" in n for n in rep.notes), rep.notes
    assert not any("rotation cameras" in n for n in rep.notes)
    assert np.array_equal(cams.c2w, np.tile(np.eye(4), (T, 1, 1))) and cams.focal == 1.2 * 160 and len(pts) > 0


def test_weakly_determined_focal_is_said():
    """A camera that only moves forward leaves the focal in a flat valley (trials from 0.5 to 2 x the side
    fit within a few percent): the notes say so rather than give the pick as measured."""
    T = 24
    c2w = np.stack([look_at([0, 0, 0.8 * k / (T - 1)], [0, 0, 5 + 0.8 * k / (T - 1)]) for k in range(T)])
    clip = make_clip(c2w, width=160, height=120, focal=125.0, mover=True, seed=4)
    _, _, _, rep = estimate_cameras(clip.frames, device="cpu")
    assert rep.mode == "general" and any("focal length is weakly determined" in n for n in rep.notes), rep.notes


def test_pure_rotation_unknown_focal():
    clip = make_clip(pan(16, yaw_deg=20, pitch_deg=6), mover=True, seed=1)
    cams, _, _, rep = estimate_cameras(clip.frames, clip.masks)
    assert rep.mode == "rotation"
    _, rot = errors(cams.c2w, clip.c2w)
    assert rot <= 1.0, rot
    assert np.abs(cams.c2w[:, :3, 3]).max() < 1e-9
    assert abs(cams.focal / 300 - 1) <= 0.05, cams.focal


def test_two_frames():
    c2w = orbit(9, strafe=1.0)[[0, 8]]
    clip = make_clip(c2w, mover=False, seed=2)
    cams, _, _, rep = estimate_cameras(clip.frames, focal=300.0)
    assert len(cams) == 2 and rep.mode == "general"
    _, rot = errors(cams.c2w, clip.c2w)
    assert rot <= 1.0
    t_est, t_gt = cams.c2w[1, :3, 3], clip.c2w[1, :3, 3]
    angle = np.degrees(np.arccos(t_est @ t_gt / np.linalg.norm(t_est) / np.linalg.norm(t_gt)))
    assert angle <= 3.0, angle


def test_identity_method_and_bad_inputs(orbit_clip):
    frames = orbit_clip.frames[:3]
    cams, pts, cols, rep = estimate_cameras(frames, method="identity", focal=250)
    assert np.array_equal(cams.c2w, np.tile(np.eye(4), (3, 1, 1))) and cams.focal == 250
    assert np.allclose(pts[:, 2], 1.0)
    with pytest.raises(InputError, match="unknown method"):
        estimate_cameras(frames, method="colmap-please")
    with pytest.raises(InputError, match="masks must be"):
        estimate_cameras(frames, masks=np.zeros((2, 5, 5), bool))
    with pytest.raises(InputError, match="frames must be"):
        estimate_cameras(frames.astype(np.float32))
    with pytest.raises(InputError, match="focal"):
        estimate_cameras(frames, focal=-3)


def test_pose_file_methods(orbit_clip, tmp_path):
    """Cameras from a JSON / npy file come back unchanged, with points triangulated from them."""
    from tomgs.cameras import Cameras

    clip = orbit_clip
    gt = Cameras.create(clip.c2w, clip.K, 320, 240)
    gt.save(tmp_path / "gt.json")
    cams, pts, _, rep = estimate_cameras(clip.frames, clip.masks, method=tmp_path / "gt.json")
    assert rep.method == "file" and np.allclose(cams.c2w, clip.c2w)
    assert len(pts) > 100 and rep.reproj_px < 0.5
    np.save(tmp_path / "c2w.npy", clip.c2w)
    cams, _, _, _ = estimate_cameras(clip.frames, method=str(tmp_path / "c2w.npy"), focal=300.0)
    assert np.allclose(cams.c2w, clip.c2w) and cams.focal == 300.0
    with pytest.raises(InputError, match="gives 24 cameras for 3 frames"):
        estimate_cameras(clip.frames[:3], method=tmp_path / "gt.json")


def test_points_carry_the_frames_that_tracked_them(orbit_clip):
    """Each point's first..last tracked frame: inside the clip, and the point projects into the
    image (in front of the camera) at both ends."""
    clip = orbit_clip
    cams, pts, _, rep = estimate_cameras(clip.frames, clip.masks)
    spans = rep.point_frames
    assert spans.shape == (len(pts), 2) and (0 <= spans[:, 0]).all() and (spans[:, 0] <= spans[:, 1]).all()
    assert spans[:, 1].max() == len(cams) - 1 and (spans[:, 1] - spans[:, 0] < len(cams) - 1).any()
    w2c = cams.viewmats()
    for end in (0, 1):
        m = w2c[spans[:, end]]
        cam = np.einsum("nij,nj->ni", m[:, :3, :3], pts) + m[:, :3, 3]
        uv = cam[:, :2] / cam[:, 2:3] @ cams.K[:2, :2].T + cams.K[:2, 2]
        inside = (cam[:, 2] > 0) & (uv >= -2).all(1) & (uv[:, 0] <= cams.width + 2) & (uv[:, 1] <= cams.height + 2)
        assert inside.mean() > 0.98, inside.mean()


def test_fixed_camera_points_have_no_spans():
    clip = make_clip(np.repeat(np.eye(4)[None], 4, 0), mover=False, seed=2)
    _, _, _, rep = estimate_cameras(clip.frames)
    assert rep.mode == "fixed" and rep.point_frames is None
