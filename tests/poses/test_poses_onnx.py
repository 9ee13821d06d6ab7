"""The ONNX door: a tiny pose model exported from torch here, run through onnxruntime."""

import numpy as np
import pytest
import torch

from tomgs.io import InputError
from tomgs.poses import estimate_cameras
from tomgs.poses.onnx_model import run_onnx

# the legacy (TorchScript) exporter needs no onnxscript, which the test extras do not install
pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


class TinyPoses(torch.nn.Module):
    """Frames [T,3,H,W] -> c2w [T,4,4] (frame k moved by 0.1 k along x, and by the frame's mean
    colour along y, so the output depends on the input) and a fixed K [3,3]."""

    def __init__(self):
        super().__init__()
        self.register_buffer("K", torch.tensor([[48.0, 0, 16], [0, 48, 12], [0, 0, 1]]))

    def forward(self, frames):
        mean = frames.mean(dim=(1, 2, 3))  # [T]
        step = torch.cumsum(torch.ones_like(mean), 0) - 1  # 0, 1, ..., T-1
        c2w = torch.eye(4).repeat(mean.shape[0], 1, 1)
        c2w[:, 0, 3] = 0.1 * step
        c2w[:, 1, 3] = mean
        return c2w, self.K


class WrongPoses(torch.nn.Module):
    def forward(self, frames):
        return frames.mean(dim=(2, 3))  # [T,3]: not a pose


def _export(model, path, outputs):
    torch.onnx.export(model, (torch.rand(2, 3, 24, 32),), str(path), input_names=["frames"],
                      output_names=outputs, dynamic_axes={"frames": {0: "T", 2: "H", 3: "W"}}, dynamo=False)
    return path


@pytest.fixture(scope="module")
def frames():
    rng = np.random.default_rng(0)
    return rng.integers(0, 255, (5, 24, 32, 3), dtype=np.uint8)


def test_onnx_model_contract(tmp_path, frames):
    path = _export(TinyPoses(), tmp_path / "poses.onnx", ["c2w", "K"])
    cams, pts, cols, rep = estimate_cameras(frames, method=str(path))
    assert rep.method == "onnx" and len(cams) == 5
    assert np.allclose(cams.c2w[:, 0, 3], 0.1 * np.arange(5), atol=1e-6)
    means = frames.astype(np.float32).mean(axis=(1, 2, 3)) / 255
    assert np.allclose(cams.c2w[:, 1, 3], means - means[0], atol=1e-5)  # re-anchored to frame 0
    assert np.allclose(cams.K, [[48, 0, 16], [0, 48, 12], [0, 0, 1]], atol=1e-5)
    assert len(pts) > 0 and cols.shape == pts.shape


def test_onnx_wrong_outputs(tmp_path, frames):
    path = _export(WrongPoses(), tmp_path / "wrong.onnx", ["pose"])
    with pytest.raises(InputError, match=r"outputs pose \[5, 3\]"):
        run_onnx(path, frames)
    with pytest.raises(InputError, match="does not exist"):
        run_onnx(tmp_path / "missing.onnx", frames)
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    with pytest.raises(InputError, match="cannot load ONNX model"):
        run_onnx(junk, frames)


def test_cli_wrong_outputs_exit_2(tmp_path, frames):
    import cv2
    from click.testing import CliRunner

    from tomgs.cli import main

    d = tmp_path / "frames"
    d.mkdir()
    for k, f in enumerate(frames):
        cv2.imwrite(str(d / f"{k}.png"), f)
    model = _export(WrongPoses(), tmp_path / "wrong.onnx", ["pose"])
    out = tmp_path / "cams.json"
    res = CliRunner().invoke(main, ["poses", str(d), "--method", str(model), "-o", str(out)])
    assert res.exit_code == 2 and "pose contract" in res.output and not out.exists()
    good = _export(TinyPoses(), tmp_path / "good.onnx", ["c2w", "K"])
    res = CliRunner().invoke(main, ["poses", str(d), "--method", str(good), "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert out.exists() and "onnx" in res.output
