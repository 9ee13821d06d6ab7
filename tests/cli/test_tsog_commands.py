"""Every command that reads a scene reads a compressed one (.tsog), `fit -o scene.tsog` writes one,
`tomgs compress` and `tomgs info` report its size, and `export -o f.sog` writes PlayCanvas's SOG."""

from __future__ import annotations

import io
import json
import re
import zipfile

import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image

from tests.io.test_tsog import wall_cameras, wall_model
from tomgs.cli import main
from tomgs.edit.export import pick_moment, static_moment
from tomgs.io import tsog
from tomgs.io.scene import load_scene, save_scene


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """(the wall as a PLY scene, the same compressed by `tomgs compress`, its frames rendered from the PLY)."""
    folder = tmp_path_factory.mktemp("commands")
    ply = save_scene(folder / "wall.ply", wall_model(400, max_sh_degree=1), wall_cameras(first=0),
                     {"fps": 12.0, "background": [0.0, 0.0, 0.0]})
    compressed = folder / "wall.tsog"
    result = run("compress", ply, "-o", compressed)
    assert result.exit_code == 0, result.output
    assert re.search(r"wall\.tsog: 400 Gaussians, [\d,]+ bytes \([\d.]+x smaller than wall\.ply\), [\d.]+ bytes a "
                     r"Gaussian, [\d.]+ bits per pixel of the clip \(6 frames of 64x36\)", result.output), result.output
    frames = folder / "frames"
    assert run("render", ply, "-o", frames, "--device", "cpu").exit_code == 0
    return ply, compressed, frames


def test_compress_writes_a_smaller_scene_that_loads(scenes):
    ply, compressed, _ = scenes
    assert compressed.read_bytes().startswith(tsog.MAGIC)
    assert compressed.stat().st_size < ply.stat().st_size / 1.5  # 400 Gaussians: codebooks and WebP headers weigh
    back = load_scene(compressed)
    assert len(back.model) == 400 and back.model.max_sh_degree == 1 and back.info["fps"] == 12.0


def test_compress_refuses_what_it_cannot_write(scenes, tmp_path):
    ply, compressed, _ = scenes
    result = run("compress", ply, "-o", tmp_path / "x.mp4")
    assert result.exit_code == 2 and "a compressed scene is a .tsog" in result.output
    result = run("compress", ply, "-o", compressed)
    assert result.exit_code == 2 and "--overwrite" in result.output
    back = tmp_path / "back.ply"  # and a .ply writes a PLY scene again
    assert run("compress", compressed, "-o", back).exit_code == 0 and back.read_bytes().startswith(b"ply\n")


def test_render_and_eval_read_it(scenes, tmp_path):
    _, compressed, frames = scenes
    out = tmp_path / "out"
    result = run("render", compressed, "-o", out, "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert len(list(out.glob("*.png"))) == 6
    report = tmp_path / "metrics.json"
    result = run("eval", compressed, frames, "--device", "cpu", "--json", report)
    assert result.exit_code == 0, result.output
    assert json.loads(report.read_text())["psnr"] > 35.0  # against the PLY's own 8-bit frames


def test_info_reports_bytes_bits_per_pixel_and_alive_counts(scenes):
    _, compressed, _ = scenes
    result = run("info", compressed)
    assert result.exit_code == 0, result.output
    size = compressed.stat().st_size
    assert f"file: {size:,} bytes (tsog), {8 * size / (64 * 36 * 6):.3f} bits per pixel of the clip" in result.output
    assert re.search(r"alive per frame: min [\d,]+ \(frame \d+\), mean [\d,]+, median", result.output)
    data = json.loads(run("info", compressed, "--json").output)
    assert data["file_format"] == "tsog" and data["file_bytes"] == size
    assert data["bits_per_pixel"] == pytest.approx(8 * size / (64 * 36 * 6))
    assert data["bytes_per_gaussian"] == pytest.approx(size / 400)
    counts = data["alive_per_frame"]["counts"]
    assert data["alive_per_frame"]["mean"] == pytest.approx(np.mean(counts)) and len(counts) == 6


def test_export_edit_and_tets_read_it(scenes, tmp_path):
    _, compressed, _ = scenes
    assert run("export", compressed, "--frame", 2, "-o", tmp_path / "f.ply").exit_code == 0
    result = run("edit", compressed, "-o", tmp_path / "moved.tsog", "--select", "box:-2,-2,0,0,2,5",
                 "--translate", "0.1,0,0")
    assert result.exit_code == 0, result.output
    moved = load_scene(tmp_path / "moved.tsog")
    assert len(moved.model) == 400 and moved.info["edits"][-1]["selected"] > 0
    result = run("tets", "export", compressed, "-o", tmp_path / "tets.ply", "--select", "box:-2,-2,0,0,2,5")
    assert result.exit_code == 0, result.output
    result = run("tets", "export", compressed, "-o", tmp_path / "tets.tsog")
    assert result.exit_code == 2 and "a tets file is a .ply" in result.output


def test_the_viewer_loads_it(scenes):
    pytest.importorskip("viser", reason="the viewer is the optional extra [view]")
    from tomgs.viewer.server import open_viewer

    _, compressed, _ = scenes
    viewer = open_viewer(compressed, port=0, device="cpu", echo=lambda *a: None)
    try:
        assert len(viewer.view.scene.model) == 400
    finally:
        viewer.stop()


def test_fit_writes_a_compressed_scene(tmp_path):
    clip = tmp_path / "clip.mp4"
    assert run("demo", "-o", clip, "--frames", "5", "--size", "48x27", "--device", "cpu").exit_code == 0
    scene = tmp_path / "scene.tsog"
    result = run("fit", clip, "-o", scene, "--preset", "quick", "--iterations", "20", "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.mp4", "scene.csv", "scene.psnr.png", "scene.tsog"]
    loaded = load_scene(scene)
    assert loaded.info["iterations"] == 20 and len(loaded.cameras) == 5
    size, w, h = scene.stat().st_size, loaded.cameras.width, loaded.cameras.height
    assert f"  {size:,} bytes, {8 * size / (w * h * 5):.3f} bits per pixel of the clip (5 frames of {w}x{h})" \
        in result.output
    result = run("fit", clip, "-o", tmp_path / "scene.npz", "--preset", "quick", "--iterations", "5")
    assert result.exit_code == 2 and "scene.ply or scene.tsog" in result.output


# ---- SOG --------------------------------------------------------------------------------------------

def _read_sog(path) -> dict:
    """The Gaussians of a SOG version 2 file, decoded as PlayCanvas's format page states (not by
    tomgs's writer): positions, rotations (w x y z), log scales, DC, opacity, SH rest."""
    archive = zipfile.ZipFile(path)
    meta = json.loads(archive.read("meta.json"))

    def image(name):
        return np.asarray(Image.open(io.BytesIO(archive.read(name))).convert("RGBA")).reshape(-1, 4)

    n = meta["count"]
    lo, hi = image(meta["means"]["files"][0])[:n], image(meta["means"]["files"][1])[:n]
    q = (hi[:, :3].astype(np.int64) << 8) | lo[:, :3]
    mins, maxs = np.array(meta["means"]["mins"]), np.array(meta["means"]["maxs"])
    v = mins + (maxs - mins) * q / 65535
    quats = image(meta["quats"]["files"][0])[:n]
    abc = (quats[:, :3] / 255.0 - 0.5) * 2 / np.sqrt(2)
    rot = np.zeros((n, 4))
    for k in range(n):
        largest = quats[k, 3] - 252
        rest = [i for i in range(4) if i != largest]
        rot[k, rest] = abc[k]
        rot[k, largest] = np.sqrt(max(0.0, 1 - (abc[k] ** 2).sum()))
    sh0 = image(meta["sh0"]["files"][0])[:n]
    out = dict(means=np.sign(v) * np.expm1(np.abs(v)), quats=rot,
               log_scales=np.array(meta["scales"]["codebook"])[image(meta["scales"]["files"][0])[:n, :3]],
               sh_dc=np.array(meta["sh0"]["codebook"])[sh0[:, :3]], opacity=sh0[:, 3] / 255.0)
    if "shN" in meta:
        coefficients = [0, 3, 8, 15][meta["shN"]["bands"]]
        centroids = image(meta["shN"]["files"][0])
        labels = image(meta["shN"]["files"][1])[:n]
        label = labels[:, 0].astype(np.int64) | (labels[:, 1].astype(np.int64) << 8)
        width = 64 * coefficients
        pixel = (label // 64)[:, None] * width + (label % 64)[:, None] * coefficients + np.arange(coefficients)
        out["sh_rest"] = np.array(meta["shN"]["codebook"])[centroids[pixel][..., :3]]  # [N, coefficients, 3]
    return out


def test_export_sog_is_playcanvas_sog_version_2(scenes, tmp_path):
    ply, compressed, _ = scenes
    out = tmp_path / "f.sog"
    result = run("export", compressed, "--frame", 2, "-o", out)
    assert result.exit_code == 0, result.output
    archive = zipfile.ZipFile(out)
    assert all(info.compress_type == zipfile.ZIP_STORED for info in archive.infolist())
    meta = json.loads(archive.read("meta.json"))
    assert meta["version"] == 2 and meta["shN"]["bands"] == 1
    assert sorted(archive.namelist()) == sorted(["meta.json", "means_l.webp", "means_u.webp", "quats.webp",
                                                  "scales.webp", "sh0.webp", "shN_centroids.webp", "shN_labels.webp"])
    for name in archive.namelist()[1:]:
        assert Image.open(io.BytesIO(archive.read(name))).format == "WEBP"
    got = _read_sog(out)
    scene = load_scene(compressed)
    want = static_moment(scene.model, pick_moment(scene.cameras, frame=2).time)
    assert meta["count"] == len(want) > 0
    # SOG keeps Morton order: each wanted Gaussian's match is the decoded one nearest it
    match = np.argmin(np.abs(got["means"][:, None] - want.means[None]).sum(-1), axis=0)
    assert len(np.unique(match)) == len(want)
    np.testing.assert_allclose(got["means"][match], want.means, atol=1e-4, rtol=1e-4)
    unit = want.quats / np.linalg.norm(want.quats, axis=1, keepdims=True)
    assert np.abs(np.abs((got["quats"][match] * unit).sum(1)) - 1).max() < 1e-3
    assert np.abs(got["opacity"][match] - 1 / (1 + np.exp(-want.opacity_logits.astype(np.float64)))).max() <= 0.5 / 255
    for name, book in (("log_scales", meta["scales"]["codebook"]), ("sh_dc", meta["sh0"]["codebook"])):
        nearest = np.array(book)[np.abs(getattr(want, name)[..., None] - np.array(book)).argmin(-1)]
        np.testing.assert_allclose(got[name][match], nearest, atol=1e-6)
    assert np.abs(got["sh_rest"][match] - want.sh_rest).max() < 0.02  # palette of every vector, codebook steps


def test_compress_reports_the_loss_and_refuses_more_than_asked(tmp_path):
    """The far scene (tests/io/test_tsog.py): kept at 16 bits with the loss in its line; at 8 bits a
    position it loses dB, and nothing is written."""
    from tests.io.test_tsog import far_scene

    model, cams = far_scene()
    ply = save_scene(tmp_path / "far.ply", model, cams, {"clip_psnr": 38.0})
    result = run("compress", ply, "-o", tmp_path / "far.tsog", "--device", "cpu")
    assert result.exit_code == 0, result.output
    found = re.search(r"renders ([\d.]+) dB against the scene's over 4 frames: ([\d.]+) dB of the scene's 38\.00 dB",
                      result.output)
    assert found and float(found.group(2)) <= 0.2, result.output
    result = run("compress", ply, "-o", tmp_path / "coarse.tsog", "--means-bits", "8", "--device", "cpu")
    lines = [line for line in result.output.splitlines() if line.startswith("Error:")]
    assert result.exit_code == 2 and len(lines) == 1 and "would lose" in lines[0] and "--max-loss 0.2" in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["far.ply", "far.tsog"]  # no .tsog, no temporary left
    assert run("compress", ply, "-o", tmp_path / "coarse.tsog", "--means-bits", "8", "--max-loss", "30",
               "--device", "cpu").exit_code == 0
