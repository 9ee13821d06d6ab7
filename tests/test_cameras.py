"""Cameras: JSON round trip, slicing, view matrices, and imports from AnyCam and COLMAP."""

import json

import cv2
import numpy as np
import pytest

from tomgs.cameras import Cameras, intrinsics
from tomgs.io import InputError


def _random_c2w(n, seed=0):
    rng = np.random.default_rng(seed)
    c2w = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        c2w[k, :3, :3] = cv2.Rodrigues(rng.normal(size=3) * 0.3)[0]
        c2w[k, :3, 3] = rng.normal(size=3)
    return c2w


def _rot_to_quat(R):
    """Rotation -> (w, x, y, z), w >= 0 (test helper; the library only needs the inverse)."""
    w = np.sqrt(max(0.0, 1 + np.trace(R))) / 2
    x = np.copysign(np.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2, R[2, 1] - R[1, 2])
    y = np.copysign(np.sqrt(max(0.0, 1 - R[0, 0] + R[1, 1] - R[2, 2])) / 2, R[0, 2] - R[2, 0])
    z = np.copysign(np.sqrt(max(0.0, 1 - R[0, 0] - R[1, 1] + R[2, 2])) / 2, R[1, 0] - R[0, 1])
    return np.array([w, x, y, z])


def test_json_round_trip_and_slicing(tmp_path):
    cams = Cameras.create(_random_c2w(5), intrinsics(400, 640, 360), 640, 360, frame_indices=[3, 5, 7, 9, 11])
    path = cams.save(tmp_path / "sub" / "cams.json")
    back = Cameras.load(path)
    assert np.array_equal(back.c2w, cams.c2w) and np.array_equal(back.K, cams.K)
    assert (back.width, back.height) == (640, 360)
    assert np.allclose(back.times, [0, 0.25, 0.5, 0.75, 1.0]) and list(back.frame_indices) == [3, 5, 7, 9, 11]
    d = json.loads(path.read_text())
    assert d["format"] == "tomgs-cameras" and d["version"] == 1 and len(d["frames"]) == 5
    assert not list(path.parent.glob("*.tmp"))  # atomic write left nothing behind

    sub = cams[1:4]
    assert len(sub) == 3 and np.allclose(sub.times, [0.25, 0.5, 0.75]) and list(sub.frame_indices) == [5, 7, 9]
    assert len(cams[2]) == 1 and len(cams[np.array([True, False, True, False, True])]) == 3

    vm = cams.viewmats()
    assert np.allclose(vm @ cams.c2w, np.eye(4), atol=1e-12)
    vt = cams.viewmats(device="cpu")
    assert vt.shape == (5, 4, 4) and str(vt.dtype) == "torch.float32"
    assert cams.Ks().shape == (5, 3, 3)

    half = cams.resized(320, 180)
    assert np.allclose(half.K, [[200, 0, 160], [0, 200, 90], [0, 0, 1]])
    reb = cams.rebased()
    assert np.allclose(reb.c2w[0], np.eye(4))
    assert np.allclose(np.linalg.inv(reb.c2w[1]) @ reb.c2w[2], np.linalg.inv(cams.c2w[1]) @ cams.c2w[2])


def test_bad_json(tmp_path):
    p = tmp_path / "x.json"
    p.write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        Cameras.load(p)
    p.write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(InputError, match="not a tomgs cameras file"):
        Cameras.load(p)
    p.write_text(json.dumps({"format": "tomgs-cameras", "version": 1, "width": 4, "height": 4,
                             "K": [[1, 0, 2], [0, 1, 2], [0, 0, 1]], "frames": [{"c2w": [[1]]}]}))
    with pytest.raises(InputError, match="schema"):
        Cameras.load(p)
    with pytest.raises(InputError, match="does not exist"):
        Cameras.load(tmp_path / "missing.json")


def test_anycam_import(tmp_path):
    c2w = _random_c2w(4, seed=1)
    np.save(tmp_path / "c2w.npy", c2w)
    K = intrinsics(300, 320, 240)
    np.save(tmp_path / "K.npy", np.stack([K] * 4))
    cams = Cameras.from_anycam(tmp_path / "c2w.npy", tmp_path / "K.npy", 320, 240)
    assert np.allclose(cams.c2w[0], np.eye(4))
    assert np.allclose(cams.c2w[3], np.linalg.inv(c2w[0]) @ c2w[3])
    assert np.allclose(cams.K, K)
    with pytest.raises(InputError, match=r"\[T,4,4\]"):
        Cameras.from_anycam(np.zeros((4, 3, 4)), K, 320, 240)


def test_colmap_import(tmp_path):
    c2w = _random_c2w(3, seed=2)
    lines_img = ["# Image list with two lines of data per image:", "#   IMAGE_ID, QW, ..."]
    order = [2, 0, 1]  # written out of order; names decide the frame order (natural sort)
    for k in order:
        w2c = np.linalg.inv(c2w[k])
        q, t = _rot_to_quat(w2c[:3, :3]), w2c[:3, 3]
        lines_img.append(f"{k + 1} {' '.join(map(str, q))} {' '.join(map(str, t))} 1 frame{k * 5}.png")
        lines_img.append("" if k == 0 else "10.0 20.0 -1 30.5 40.5 7")
    (tmp_path / "images.txt").write_text("\n".join(lines_img) + "\n")
    (tmp_path / "cameras.txt").write_text("# Camera list\n1 SIMPLE_RADIAL 640 480 500.5 320 240 0.01\n")
    cams = Cameras.from_colmap(tmp_path)
    assert (cams.width, cams.height) == (640, 480)
    assert np.allclose(cams.K, [[500.5, 0, 320], [0, 500.5, 240], [0, 0, 1]])
    expect = np.linalg.inv(c2w[0]) @ c2w
    assert np.allclose(cams.c2w, expect, atol=1e-9)
    (tmp_path / "cameras.txt").write_text("1 SIMPLE_RADIAL 640 480 not-a-number 320 240 0\n")
    with pytest.raises(InputError, match="cannot parse"):
        Cameras.from_colmap(tmp_path)
    (tmp_path / "cameras.txt").write_text("1 THIN_PRISM_FISHEYE 640 480 1 2 3 4 5 6 7 8 9 10 11 12\n")
    with pytest.raises(InputError, match="not supported"):
        Cameras.from_colmap(tmp_path)
    (tmp_path / "cameras.txt").unlink()
    with pytest.raises(InputError, match="cameras.txt is missing"):
        Cameras.from_colmap(tmp_path)
