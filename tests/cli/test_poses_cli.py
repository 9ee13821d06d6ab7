"""`tomgs poses`: writes cameras on success; bad input gets exit code 2 and writes nothing."""

import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from tomgs.cli import main
from tomgs.poses.synthetic import make_clip, orbit


@pytest.fixture(scope="module")
def clip_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("clip")
    clip = make_clip(orbit(10, strafe=1.0), width=192, height=144, focal=180.0, mover=True, seed=3)
    (d / "images").mkdir()
    (d / "masks").mkdir()
    for k, (img, m) in enumerate(zip(clip.frames, clip.masks)):
        cv2.imwrite(str(d / "images" / f"{k:03d}.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(d / "masks" / f"{k:03d}.png"), m.astype(np.uint8) * 255)
    return d


def test_poses_command_writes_cameras(clip_dir, tmp_path):
    out = tmp_path / "cams.json"
    res = CliRunner().invoke(main, ["poses", str(clip_dir / "images"), "-o", str(out), "--masks",
                                    str(clip_dir / "masks"), "--frames", "0:10:1", "--focal", "180"])
    assert res.exit_code == 0, res.output
    d = json.loads(out.read_text())
    assert d["format"] == "tomgs-cameras" and len(d["frames"]) == 10 and d["width"] == 192
    assert "10 frames" in res.output and "focal 180.0 px" in res.output and "reprojection error" in res.output
    assert np.allclose(d["frames"][0]["c2w"], np.eye(4))


def test_poses_command_resize_and_identity(clip_dir, tmp_path):
    out = tmp_path / "id.json"
    res = CliRunner().invoke(main, ["poses", str(clip_dir / "images"), "-o", str(out), "--method", "identity",
                                    "--max-side", "96", "--frames", "::3"])
    assert res.exit_code == 0, res.output
    d = json.loads(out.read_text())
    assert (d["width"], d["height"]) == (96, 72) and [f["index"] for f in d["frames"]] == [0, 3, 6, 9]


@pytest.mark.parametrize("args, message", [
    (["{missing}"], "does not exist"),
    (["{corrupt}"], "corrupt"),
    (["{empty}"], "no jpg/png"),
    (["{images}", "--masks", "{few_masks}"], "masks but the clip has"),
    (["{images}", "--frames", "5:x"], "bad frame range"),
    (["{images}", "--method", "superglue"], "unknown method"),
    (["{images}", "--method", "{bad_onnx}"], "cannot load ONNX model"),
])
def test_bad_input_exit_2_nothing_written(clip_dir, tmp_path, args, message):
    (tmp_path / "empty").mkdir()
    (tmp_path / "broken.mp4").write_bytes(b"\x00\x01garbage" * 50)
    few = tmp_path / "few"
    few.mkdir()
    cv2.imwrite(str(few / "0.png"), np.zeros((144, 192), np.uint8))
    (tmp_path / "bad.onnx").write_bytes(b"nope")
    paths = {"missing": tmp_path / "nope.mp4", "corrupt": tmp_path / "broken.mp4", "empty": tmp_path / "empty",
             "images": clip_dir / "images", "few_masks": few, "bad_onnx": tmp_path / "bad.onnx"}
    out = tmp_path / "out" / "cams.json"
    out.parent.mkdir()  # outputs go into existing folders (tests/test_outputs.py covers a missing one)
    res = CliRunner().invoke(main, ["poses", *[a.format(**paths) for a in args], "-o", str(out)])
    assert res.exit_code == 2, res.output
    assert message in res.output
    assert not out.exists() and not (out.parent.exists() and any(out.parent.iterdir()))
