"""`tomgs render` and `tomgs info` end to end on a tiny scene, and their bad input (exit 2, nothing written)."""

from __future__ import annotations

import json
import re

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from tests.scenes import rewrite_vertex
from tomgs.cameras import Cameras, intrinsics, look_at
from tomgs.cli import main
from tomgs.io.scene import save_scene
from tomgs.model import GaussianModel
from tomgs.render.sequence import render_sequence

W, H, T = 64, 36, 6


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def tiny_model(n: int = 240) -> GaussianModel:
    """A textured wall of Gaussians at depth ~3 whose halves live in the first and last part of the clip."""
    g = torch.Generator().manual_seed(7)
    xy = torch.rand(n, 2, generator=g) * torch.tensor([2.6, 1.6]) - torch.tensor([1.3, 0.8])
    means = torch.cat([xy, 3.0 + 0.2 * torch.rand(n, 1, generator=g)], 1)
    colors = torch.rand(n, 3, generator=g)
    t_means = (xy[:, 0] > 0).float() * 0.8 + 0.1
    model = GaussianModel.from_points(means, colors, t_means, t_scale=0.15, max_sh_degree=1, opacity=0.8)
    with torch.no_grad():
        model.log_scales.fill_(np.log(0.12))
    return model


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    c2w = np.stack([look_at([0.05 * k, 0.0, 0.0], [0.0, 0.0, 3.0]) for k in range(T)])
    cams = Cameras.create(c2w, intrinsics(50.0, W, H), W, H, frame_indices=np.arange(20, 20 + T))
    path = tmp_path_factory.mktemp("scene") / "tiny.ply"
    save_scene(path, tiny_model(), cams, {"fps": 12.0, "background": [0.0, 0.0, 0.2]})
    return path


def test_help_lists_render_and_info():
    help_text = run("--help").output
    assert "render" in help_text and "info" in help_text


def test_render_writes_a_video(tmp_path, scene):
    out = tmp_path / "out.mp4"
    result = run("render", scene, "-o", out, "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert re.search(rf"{T} frames \(20\.\.25\) at {W}x{H} on cpu in [\d.]+ s \([\d.]+ fps\)", result.output)
    assert "240 Gaussians; alive per frame" in result.output
    video = cv2.VideoCapture(str(out))
    assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == T
    assert video.get(cv2.CAP_PROP_FPS) == pytest.approx(12.0)  # the scene's fps from its info
    ok, frame = video.read()
    assert ok and frame.shape == (H, W, 3) and frame.std() > 10
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mp4"]


def test_render_png_frames_match_the_renderer(tmp_path, scene):
    from tomgs.io.scene import load_scene

    out = tmp_path / "frames"
    result = run("render", scene, "--frames", "22:25", "-o", out, "--device", "cpu", "--background", "1,1,1")
    assert result.exit_code == 0, result.output
    assert "3 frames (22..24)" in result.output and "fps)" in result.output
    names = sorted(p.name for p in out.iterdir())
    assert names == ["00022.png", "00023.png", "00024.png"]  # the scene's frame numbers
    loaded = load_scene(scene)
    expected = [(img.numpy() * 255 + 0.5).astype(np.uint8)
                for _, img, _ in render_sequence(loaded.model.render_inputs(), loaded.cameras, [2, 3, 4],
                                                 background=(1.0, 1.0, 1.0))]
    for name, want in zip(names, expected):
        got = cv2.imread(str(out / name))[..., ::-1]
        np.testing.assert_array_equal(got, want)
    first, last = (cv2.imread(str(out / n)).astype(float) for n in (names[0], names[-1]))
    assert abs(first - last).mean() > 2.0  # the Gaussians' windows differ over time


def test_render_a_stepped_range_past_the_end(tmp_path, scene):
    """A stop past the last frame is clamped like a Python slice; PNGs are named by frame number."""
    out = tmp_path / "frames"
    result = run("render", scene, "--frames", "20:90:2", "-o", out, "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert "3 frames (20..24)" in result.output
    assert sorted(p.name for p in out.iterdir()) == ["00020.png", "00022.png", "00024.png"]


def test_info_text_json_and_plot(tmp_path, scene):
    result = run("info", scene)
    assert result.exit_code == 0, result.output
    out = result.output
    assert f"240 Gaussians, {T} frames (numbers 20..25) at {W}x{H}" in out
    assert "SH degree 0 of 1" in out and "alive per frame: min" in out and "opacity (base)" in out
    assert "temporal sigma in frames" in out and "#" in out

    result = run("info", scene, "--json")
    assert result.exit_code == 0, result.output
    s = json.loads(result.output)
    assert s["gaussians"] == 240 and s["frames"] == T and s["info"]["fps"] == 12.0
    assert len(s["alive_per_frame"]["counts"]) == T and sum(s["temporal_sigma_frames"]["counts"]) == 240
    assert s["temporal_sigma_frames"]["median"] == pytest.approx(0.15 * (T - 1), rel=1e-6)

    plot = tmp_path / "sigma.png"
    result = run("info", scene, "--plot", plot)
    assert result.exit_code == 0, result.output
    image = cv2.imread(str(plot))
    assert image is not None and image.shape[0] > 100 and image.std() > 10
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sigma.png"]


def _missing_property(tmp_path, scene):
    def drop_scale_1(rows):
        keep = [n for n in rows.dtype.names if n != "scale_1"]
        out = np.empty(len(rows), dtype=[(n, rows.dtype[n]) for n in keep])
        for n in keep:
            out[n] = rows[n]
        return out
    return rewrite_vertex(scene, tmp_path / "inputs" / "noscale.ply", drop_scale_1)


@pytest.mark.parametrize("case, args, message", [
    ("missing", ["render", "{inputs}/nope.ply", "-o", "{out}/x.mp4"], "does not exist"),
    ("not ply", ["render", "{inputs}/text.ply", "-o", "{out}/x.mp4"], "not a PLY file"),
    ("property", ["render", "{noscale}", "-o", "{out}/x.mp4"], "lacks properties scale_1"),
    ("past end", ["render", "{scene}", "--frames", "26:40", "-o", "{out}/x.mp4"], "outside the scene's frames"),
    ("empty", ["render", "{scene}", "--frames", "24:22", "-o", "{out}/x.mp4"], "holds none of the scene's frames"),
    ("before", ["render", "{scene}", "--frames", "0:22", "-o", "{out}/frames"], "outside the scene's frames"),
    ("malformed", ["render", "{scene}", "--frames", "a:b", "-o", "{out}/x.mp4"], "bad frame range"),
    ("device", ["render", "{scene}", "--device", "tpu", "-o", "{out}/x.mp4"], "device"),
    ("background", ["render", "{scene}", "--background", "2,0", "-o", "{out}/x.mp4"], "--background"),
    ("output type", ["render", "{scene}", "-o", "{out}/x.gif"], "unknown output type"),
    ("info missing", ["info", "{inputs}/nope.ply"], "does not exist"),
    ("info not ply", ["info", "{inputs}/text.ply", "--plot", "{out}/p.png"], "not a PLY file"),
    ("info property", ["info", "{noscale}"], "lacks properties scale_1"),
    ("plot type", ["info", "{scene}", "--plot", "{out}/p.jpg"], "PNG"),
])
def test_bad_input_exits_2_and_writes_nothing(tmp_path, scene, case, args, message):
    (tmp_path / "inputs").mkdir()
    (tmp_path / "out").mkdir()
    (tmp_path / "inputs" / "text.ply").write_text("this is not a PLY file\n")
    noscale = _missing_property(tmp_path, scene)
    fill = dict(inputs=tmp_path / "inputs", out=tmp_path / "out", scene=scene, noscale=noscale)
    result = run(*[a.format(**fill) for a in args])
    assert result.exit_code == 2, (case, result.output)
    assert message in result.output, (case, result.output)
    assert list((tmp_path / "out").iterdir()) == []
