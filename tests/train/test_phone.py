"""Phone videos: frames decoded only where selected and kept as uint8, a plan line and a
progress bar per phase, a default that ends on a CPU, and a full-clip PSNR measured away from
densification."""

from __future__ import annotations

import csv
import json
import re

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from tomgs.cli import main
from tomgs.train.loop import RunHooks

CPU = torch.device("cpu")
GOP = 10


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


@pytest.fixture(scope="module")
def long_clip(tmp_path_factory):
    """300 frames of 64x48 H.264 with a keyframe every GOP frames and B-frames (as phone encoders
    write them); frame k's red channel is 10 (k % 25) on its left half."""
    import av

    path = tmp_path_factory.mktemp("long") / "long.mp4"
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=30)
        stream.width, stream.height, stream.pix_fmt = 64, 48, "yuv420p"
        stream.codec_context.gop_size = GOP
        stream.options = {"bf": "2", "sc_threshold": "0"}
        for k in range(300):
            image = np.zeros((48, 64, 3), np.uint8)
            image[:, :32, 0] = 10 * (k % 25)
            image[:, :, 1] = np.arange(64, dtype=np.uint8)[None] * 3
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


def test_a_range_of_a_long_clip_decodes_only_from_the_keyframe_before_it(long_clip):
    """--frames 200:210 of 300 decodes the frames from the keyframe at 200 up to 209 (and the few
    B-frames the decoder holds back), not the 200 before them; so does the end of the clip by a
    negative range, which needs the count (from the index, not decoding)."""
    from tomgs.io import read_video

    clip = read_video(long_clip, frames="200:210")
    assert clip.indices.tolist() == list(range(200, 210))
    assert clip.frames.dtype == np.uint8 and clip.frames.shape == (10, 48, 64, 3)
    assert np.abs(clip.frames[:, 10, 10, 0].astype(int) - 10 * (np.arange(200, 210) % 25)).max() <= 4  # the right ones
    assert clip.decoded <= 10 + 4
    clip = read_video(long_clip, frames="205:215:5")  # from the keyframe at 200
    assert clip.indices.tolist() == [205, 210] and clip.decoded <= 11 + 4
    clip = read_video(long_clip, frames="-5:", max_side=32)
    assert clip.indices.tolist() == list(range(295, 300)) and clip.frames.shape == (5, 24, 32, 3)
    assert clip.decoded <= 5 + GOP + 4
    everything = read_video(long_clip)
    assert everything.decoded == 300 and len(everything) == 300
    assert np.array_equal(everything.frames[200:210], read_video(long_clip, frames="200:210").frames)


def test_probe_reads_the_count_and_size_without_decoding(long_clip):
    from tomgs.io.video import probe_clip

    assert probe_clip(long_clip, "10:20", max_side=32) == (10, 24, 32, 48 * 64)
    assert probe_clip(long_clip)[0] == 300


def test_frames_weights_and_alpha_targets_stay_uint8(long_clip):
    """The trainer and the background layer hold the clip as uint8, never as float32 copies."""
    from tomgs.cameras import Cameras, intrinsics
    from tomgs.io import read_video
    from tomgs.render.layers import background_inputs
    from tomgs.train import Trainer, preset

    clip = read_video(long_clip, frames="0:6")
    clip.masks = np.zeros(clip.frames.shape[:3], bool)
    clip.masks[:, 10:20, 10:20] = True
    inputs = background_inputs(clip, 1)
    assert inputs.hooks["weights"].dtype == np.uint8 and inputs.hooks["alpha_targets"].dtype == np.uint8
    cams = Cameras.identity(6, intrinsics(60.0, 64, 48), 64, 48)
    trainer = Trainer(inputs.frames, cams, np.zeros((0, 3)), np.zeros((0, 3)),
                      preset("quick", init_points_per_frame=20), CPU, **inputs.hooks)
    assert trainer.frames.dtype == trainer.weights.dtype == trainer.alpha_targets.dtype == torch.uint8
    assert trainer.frames.data_ptr() == torch.from_numpy(inputs.frames).data_ptr()  # on a CPU: shared, no copy
    trainer.step()


PHASES = ("loading", "reading", "poses", "initialising", "training", "saving")
PROGRESS_LINE = re.compile(r"\s*\[\s*\S+ (?:s|min)\] (\S+) \d+%")  # a phase's line where stderr is a log


def test_fit_prints_its_plan_first_and_a_bar_for_every_phase(long_clip, tmp_path):
    result = run("fit", long_clip, "-o", tmp_path / "s.ply", "--frames", "0:8", "--max-side", "32", "--preset",
                 "quick", "--iterations", "12", "--device", "cpu", "--poses", "identity")
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    # not a terminal here: a line as each phase starts, "[  1 s] reading 0%" (tomgs.cli.common.ProgressLines),
    # from the imports ("loading") on; the plan comes before the clip is read
    said = [line for line in lines if not PROGRESS_LINE.match(line)]
    assert PROGRESS_LINE.match(lines[0]).group(1) == "loading"
    assert said[0].startswith("plan: 8 frames of 32x24 (30 fps) on cpu, 12 iterations") and "ETA" in said[0]
    started = [m.group(1) for m in map(PROGRESS_LINE.match, lines) if m]
    assert [p for p in dict.fromkeys(started) if p in PHASES] == list(PHASES)  # each phase, in order
    assert "peak memory" in result.output and "s in all (read" in result.output
    quiet = run("fit", long_clip, "-o", tmp_path / "q.ply", "--frames", "0:4", "--max-side", "32", "--preset",
                "quick", "--iterations", "3", "--device", "cpu", "--poses", "identity", "-q", "--json",
                tmp_path / "q.json")
    assert quiet.exit_code == 0 and "plan:" not in quiet.output
    assert not any(map(PROGRESS_LINE.match, quiet.output.splitlines()))
    # where the memory went: the peak so far at the end of each phase (it only rises), as --json reports it
    report = json.loads((tmp_path / "q.json").read_text())
    peaks = report["peak_host_mb_by_phase"]
    assert list(peaks) == ["read", "poses", "init", "train", "save"]
    assert 0 < peaks["read"] <= peaks["poses"] <= peaks["init"] <= peaks["train"] <= peaks["save"] == \
        report["peak_host_mb"]


def test_the_default_fit_ends_at_a_budget_it_chooses_on_a_cpu(long_clip, tmp_path, monkeypatch):
    """Without --budget or --iterations a CPU fit whose iterations would outrun DEFAULT_BUDGET stops at
    it and says so (the budget shrunk to seconds here, so the test is quick)."""
    from tomgs.train import plan

    monkeypatch.setitem(plan.DEFAULT_BUDGET, "cpu", 6.0)
    result = run("fit", long_clip, "-o", tmp_path / "s.ply", "--frames", "0:4", "--max-side", "32", "--device",
                 "cpu", "--poses", "identity")
    assert result.exit_code == 0, result.output
    assert "12,000 iterations or 6 s, whichever comes first (budget chosen" in result.output
    assert "budget 6 s: 12,000 iterations would take about" in result.output
    rows = list(csv.DictReader(open(tmp_path / "s.csv")))
    assert 0 < int(rows[-1]["iteration"]) < 12_000 and rows[-1]["clip_psnr"] != ""
    assert "chosen budget 6 s for the whole fit" in result.output
    asked = run("fit", long_clip, "-o", tmp_path / "n.ply", "--frames", "0:4", "--max-side", "32", "--device",
                "cpu", "--poses", "identity", "--iterations", "5")  # a count asked for is kept
    assert asked.exit_code == 0 and "budget chosen" not in asked.output
    assert list(csv.DictReader(open(tmp_path / "n.csv")))[-1]["iteration"] == "5"


def test_plan_scales_capacity_with_the_clip_and_the_cpu_time():
    from tomgs.train import preset
    from tomgs.train.plan import make_plan

    short, _ = make_plan(preset("default"), 30, 480, 854, 480 * 854, "cuda")
    long, _ = make_plan(preset("default"), 900, 1080, 1920, 1080 * 1920, "cuda")
    assert long.cap > 5 * short.cap and long.budget == 0  # a 1080p, 900-frame clip is not held to 10M
    asked, config = make_plan(preset("default", max_gaussians=123_456), 900, 1080, 1920, 1080 * 1920, "cuda")
    assert asked.cap == config.max_gaussians == 123_456
    cpu, config = make_plan(preset("default", max_seconds=180), 141, 240, 184, 368 * 480, "cpu")
    assert cpu.points_per_frame * 141 <= 60_000 < 2000 * 141  # a phone's portrait clip started from 282,950
    assert config.init_points_per_frame == cpu.points_per_frame and config.max_gaussians == cpu.cap
    assert any("fewer than 500 steps" in r for r in cpu.reasons) and cpu.eta == 180


def test_full_clip_psnr_is_not_measured_right_after_a_densification():
    """Rows with a full-clip PSNR (but the last) come at least densify_interval / 2 steps after the last
    densification, prune or reset; before, every row at a densification step measured the dip."""
    from tomgs.train import Trainer

    from tests.train.test_train import small_config, synthetic_clip

    images, cams, points, colors = synthetic_clip(3, 32, 18)
    config = small_config(300).replace(eval_interval_s=0.0)
    trainer = Trainer(images, cams, points, colors, config, CPU)
    changed = {}
    observe = trainer.densifier.step_post_backward

    def record(model, optimizer, meta, visible, iteration, progress):
        observe(model, optimizer, meta, visible, iteration, progress)
        changed[iteration] = trainer.densifier.changed_at
    trainer.densifier.step_post_backward = record
    result = trainer.run()
    measured = [r["iteration"] for r in result.history if r["clip_psnr"] != ""]
    assert len(measured) >= 4 and measured[-1] == 300
    assert max(changed.values()) > 0  # it densified
    for iteration in measured[:-1]:
        assert iteration - changed[iteration] >= config.densify_interval // 2, (iteration, changed[iteration])


def test_the_eta_is_when_the_iterations_end_when_that_comes_before_the_budget():
    """With stop_at_iterations (`--iterations` beside `--budget`) a budget caps the ETA; it is not the ETA:
    on the H100 a 132-frame 720p fit with --budget 300 ended its 12,000 iterations after 129 s while the plan
    said 300 s. Without it (`--budget` alone) the fit trains for the whole budget."""
    from tomgs.train import preset
    from tomgs.train.plan import UNTIL_BUDGET, make_plan

    plenty, config = make_plan(preset("default", max_seconds=3000, stop_at_iterations=True), 132, 720, 1280,
                               720 * 1280, "cuda")
    assert 60 < plenty.eta < 0.5 * plenty.budget and plenty.phases["train"] < 3000 and config.iterations == 12_000
    tight, _ = make_plan(preset("default", max_seconds=30, stop_at_iterations=True), 132, 720, 1280, 720 * 1280,
                         "cuda")
    assert tight.eta == 30
    longer, config = make_plan(preset("default", max_seconds=3000), 132, 720, 1280, 720 * 1280, "cuda")
    assert longer.eta == 3000 and config.iterations == longer.iterations == UNTIL_BUDGET
    assert "training for 50.0 min in all" in longer.summary()


def test_a_long_clip_has_a_clip_psnr_early_over_evenly_spaced_frames(monkeypatch, tmp_path):
    """A full-clip PSNR was taken only once it cost at most 10% of the run, so a long clip's
    curve began late (900 frames at 1080p on the H100: none in the first 1.5 minutes). Before the
    last, a measurement covers evenly spaced frames, as many as 10% of the run so far pays for or as
    take a second; the CSV says how many (clip_frames); the last covers every frame. On a fake clock a
    step takes 0.1 s and a frame's render 0.05 s: all 300 frames take 15 s, which the old rule first
    measured at 150 s."""
    import time

    from tomgs.cameras import Cameras, intrinsics
    from tomgs.train import Trainer
    from tomgs.train.log import write_plot

    from tests.train.test_train import small_config

    T, clock, asked = 300, [0.0], []

    def step(self):
        clock[0] += 0.1
        self.iteration += 1

    def clip_psnr(self, tick=None, frames=None):
        frames = list(range(self.num_frames)) if frames is None else [int(k) for k in frames]
        asked.append((self.iteration, frames))
        clock[0] += 0.05 * len(frames)
        return [20.0 + self.iteration / 1000] * len(frames)

    cams = Cameras.identity(T, intrinsics(20.0, 16, 9), 16, 9)
    # quality max: the schedule of measurements alone (the quality rule's rounds measure every frame too)
    config = small_config(3000).replace(eval_interval_s=5.0, init_points_per_frame=2, quality="max")
    trainer = Trainer(np.zeros((T, 9, 16, 3), np.uint8), cams, np.zeros((0, 3)), np.zeros((0, 3)), config, CPU)
    monkeypatch.setattr(time, "perf_counter", lambda: clock[0])
    monkeypatch.setattr(Trainer, "step", step)
    monkeypatch.setattr(Trainer, "clip_psnr", clip_psnr)
    result = trainer.run(hooks=RunHooks(log_csv=tmp_path / "log.csv"))
    monkeypatch.undo()

    rows = [r for r in result.history if r["clip_psnr"] != ""]
    assert rows[0]["wall_s"] < 5 and 8 <= rows[0]["clip_frames"] < T, rows[0]
    early = [r for r in rows if r["wall_s"] < 150]
    assert len(early) >= 3 and all(r["clip_frames"] < T for r in early), early
    assert [r["iteration"] for r in rows] == [i for i, _ in asked]
    for row, (_, frames) in zip(rows, asked):
        assert row["clip_frames"] == len(frames) and frames[0] == 0 and frames[-1] == T - 1
        assert np.ptp(np.diff(frames)) <= 1  # evenly spaced
    assert rows[-1]["iteration"] == 3000 and rows[-1]["clip_frames"] == T and result.clip_psnr == rows[-1]["clip_psnr"]
    spent = sum(0.05 * len(frames) for _, frames in asked[:-1])
    assert spent <= 0.12 * rows[-1]["wall_s"], (spent, rows[-1]["wall_s"])
    with open(tmp_path / "log.csv") as f:
        logged = list(csv.DictReader(f))
    assert {r["clip_frames"] for r in logged if r["clip_psnr"] == ""} == {""}
    assert [int(r["clip_frames"]) for r in logged if r["clip_psnr"] != ""] == [r["clip_frames"] for r in rows]
    write_plot(tmp_path / "log.psnr.png", logged)  # the plot reads the log's rows (strings) as they are written
    assert (tmp_path / "log.psnr.png").stat().st_size > 1000


def test_a_clip_psnr_of_some_frames_is_theirs_of_every_frame():
    from tomgs.train import Trainer

    from tests.train.test_train import small_config, synthetic_clip

    images, cams, points, colors = synthetic_clip(6, 32, 18)
    trainer = Trainer(images, cams, points, colors, small_config(10), CPU)
    every = trainer.clip_psnr()
    assert trainer.clip_psnr(frames=[0, 2, 5]) == pytest.approx([every[0], every[2], every[5]], abs=1e-9)
    with pytest.raises(ValueError, match="frame 6 is not one of the clip's 6"):
        trainer.clip_psnr(frames=[1, 6])


def test_the_hosts_frames_go_once_the_trainer_has_its_own_copy(tmp_path, monkeypatch):
    """On a GPU the trainer keeps the clip on the device, and the fit let go of the host's
    copy only when it returned (1.7 GiB of 4.1 for 300 frames of 1080p on the H100). Here the trainer
    is given its own copy as a GPU's would be: the decoded frames are freed before training starts;
    on a CPU, where the trainer's frames are the decoded ones, they stay."""
    import weakref

    import tomgs.io
    from tomgs.train import Trainer, fit

    from tests.train.test_train import small_config

    video = tmp_path / "clip.mp4"
    assert run("demo", "--frames", 6, "--size", "64x36", "-o", video, "-q", "--device", "cpu").exit_code == 0
    refs, seen = [], []
    read = tomgs.io.read_video

    def read_video(*a, **k):
        clip = read(*a, **k)
        refs.append(weakref.ref(clip.frames.base if clip.frames.base is not None else clip.frames))
        return clip

    monkeypatch.setattr(tomgs.io, "read_video", read_video)
    for copy in (True, False):
        if copy:
            own = Trainer.__init__

            def init(self, *a, **k):
                own(self, *a, **k)
                self.frames = self.frames.clone()  # as on a GPU: the trainer's own copy

            monkeypatch.setattr(Trainer, "__init__", init)
        fit(video, tmp_path / f"{copy}.ply", small_config(4), poses="identity", device="cpu",
            progress=lambda row: seen.append(refs[-1]() is None))
        if copy:
            monkeypatch.setattr(Trainer, "__init__", own)
        assert seen and seen == [copy] * len(seen), (copy, seen)
        seen.clear()
