"""`tomgs fit` and `tomgs eval` end to end on a tiny clip, and their answers to bad input."""

from __future__ import annotations

import csv
import json

import pytest
from click.testing import CliRunner

from tomgs.cli import main


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    folder = tmp_path_factory.mktemp("clip")
    path = folder / "clip.mp4"
    assert run("demo", "-o", path, "--frames", "5", "--size", "48x27", "--device", "cpu").exit_code == 0
    return path


def test_fit_then_eval_then_render(clip, tmp_path):
    scene = tmp_path / "scene.ply"
    result = run("fit", clip, "-o", scene, "--preset", "quick", "--iterations", "40", "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert "full-clip PSNR" in result.output and "note: poses:" in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.csv", "scene.ply", "scene.psnr.png"]
    rows = list(csv.DictReader(open(tmp_path / "scene.csv")))
    assert int(rows[-1]["iteration"]) == 40 and float(rows[-1]["wall_s"]) > 0
    assert rows[-1]["clip_psnr"] != ""

    metrics = tmp_path / "metrics.json"
    result = run("eval", scene, clip, "--device", "cpu", "--json", metrics)
    assert result.exit_code == 0, result.output
    data = json.load(open(metrics))
    assert data["frames"] == 5 and len(data["per_frame"]) == 5
    assert abs(data["psnr"] - float(rows[-1]["clip_psnr"])) < 1e-2  # the fit's own measure agrees
    assert run("render", scene, "--frames", "0:5", "-o", tmp_path / "out", "--device", "cpu").exit_code == 0


def test_fit_on_every_kth_frame_records_their_rate(clip, tmp_path):
    """The demo clip plays at 24 fps; every second frame of it, at 12, so its video plays in real time."""
    from tomgs.io.scene import load_scene

    scene = tmp_path / "scene.ply"
    result = run("fit", clip, "-o", scene, "--frames", "0:5:2", "--preset", "quick", "--iterations", "5",
                 "--device", "cpu", "--poses", "identity")
    assert result.exit_code == 0, result.output
    loaded = load_scene(scene)
    assert loaded.cameras.frame_indices.tolist() == [0, 2, 4] and loaded.info["fps"] == pytest.approx(12.0)


def test_fit_leaves_out_what_no_frame_shows_unless_asked_to_keep_all(clip, tmp_path):
    from tomgs.io.scene import load_scene

    counts = {}
    for compact in ("0", "0.2"):
        scene = tmp_path / f"scene{compact}.ply"
        result = run("fit", clip, "-o", scene, "--preset", "quick", "--iterations", "30", "--device", "cpu",
                     "--poses", "identity", "--compact", compact, "--seed", "3")
        assert result.exit_code == 0, result.output
        assert ("Gaussians that gave no frame 0.2 of a pixel's colour" in result.output) == (compact != "0")
        counts[compact] = len(load_scene(scene).model)
    assert 0 < counts["0.2"] < counts["0"]
    result = CliRunner().invoke(main, ["fit", str(clip), "-o", str(tmp_path / "s.ply"), "--compact", "-1"])
    assert result.exit_code == 2 and "--compact" in result.output


@pytest.mark.parametrize("setup, args, message", [
    ("corrupt", ["{video}", "-o", "{tmp}/s.ply"], "cannot open video"),
    ("clip", ["{clip}", "-o", "{tmp}/s.ply", "--device", "tpu"], "device"),
    ("clip", ["{clip}", "-o", "{tmp}/s.ply", "--frames", "10:20"], "frame"),
    ("clip", ["{clip}", "-o", "{tmp}/missing/s.ply"], "does not exist"),
    ("clip", ["{clip}", "-o", "{tmp}/s.txt"], ".ply"),
    ("clip", ["{clip}", "-o", "{tmp}/s.ply", "--resume"], "no checkpoint"),
])
def test_fit_bad_input(clip, tmp_path, setup, args, message):
    video = tmp_path / "broken.mp4"
    if setup == "corrupt":
        video.write_bytes(b"\x00not a video" * 100)
    args = [a.replace("{video}", str(video)).replace("{clip}", str(clip)).replace("{tmp}", str(tmp_path))
            for a in args]
    before = set(tmp_path.iterdir())
    result = CliRunner().invoke(main, ["fit", *args, "--preset", "quick", "--iterations", "5"])
    assert result.exit_code == 2, result.output
    assert message in result.output
    assert set(tmp_path.iterdir()) == before  # nothing written


def test_eval_bad_input(clip, tmp_path):
    not_a_scene = tmp_path / "scene.ply"
    not_a_scene.write_text("hello")
    result = CliRunner().invoke(main, ["eval", str(not_a_scene), str(clip)])
    assert result.exit_code == 2 and "scene.ply" in result.output


def test_the_fit_s_clock_starts_with_tomgs_not_with_its_process(clip, tmp_path):
    """`bash -c "sleep 15 && tomgs fit ..."` hands tomgs a process 15 s old: its budget and its time in
    all count from tomgs's own start, not the process's."""
    import os
    import subprocess
    import sys
    import time
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    code = ("import sys, time; time.sleep(4); sys.argv[0] = 'tomgs'; from tomgs.cli import main; main()")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (str(root), os.environ.get("PYTHONPATH"))))}
    began = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", code, "-q", "fit", str(clip), "-o", str(tmp_path / "s.ply"),
                           "--iterations", "3", "--device", "cpu", "--poses", "identity", "--json", "-"],
                          env=env, capture_output=True, text=True, timeout=600)
    took = time.perf_counter() - began
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["wall_seconds"] < took - 3.5, (json.loads(done.stdout)["wall_seconds"], took)
