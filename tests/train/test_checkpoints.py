"""Checkpoints and durable fits: a checkpoint is tensors and plain data, read without running code;
temporaries are private and never followed through links; a fit refuses to replace outputs it
was not asked to; it saves on a schedule and on SIGINT / SIGTERM at a step boundary, never a torn
state; `resume` refuses options that change the frames; an all-black clip fits."""

from __future__ import annotations

import csv
import json
import os
import pickle
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from tests.train.test_train import CPU, small_config, synthetic_clip
from tomgs.errors import InputError
from tomgs.train import Trainer, fit, preset
from tomgs.train.checkpoint import read_checkpoint
from tomgs.train.sampler import FrameSampler
from tomgs.train.loop import RunHooks

# what a subprocess puts on its sys.path to import the tests' helpers: the repository root and tests/
TESTS = os.pathsep.join(str(Path(__file__).resolve().parents[i]) for i in (2, 1))


def write_frames(folder: Path, count: int = 5, width: int = 32, height: int = 18, black: bool = False,
                 flipped: bool = False) -> Path:
    """A folder of PNG frames of the demo scene (or black ones)."""
    folder.mkdir()
    images = synthetic_clip(count, width, height)[0]
    if black:
        images = np.zeros_like(images)
    if flipped:
        images = images[:, ::-1]
    for i, image in enumerate(images):
        cv2.imwrite(str(folder / f"{i:03d}.png"), np.ascontiguousarray(image[..., ::-1]))
    return folder


def trainer_for(iterations: int, frames: int = 3, **kw) -> Trainer:
    images, cams, points, colors = synthetic_clip(frames, 32, 18)
    return Trainer(images, cams, points, colors, small_config(iterations, **kw), CPU)


def read_state(path) -> dict:
    """A checkpoint as the trainer reads it: tensors and plain data only."""
    return torch.load(path, map_location="cpu", weights_only=True)


def fit_clip(video, out, iterations: int = 60, interrupt_at: int | None = None, **kw):
    """`fit` with identity poses; `interrupt_at`: Ctrl-C from the progress callback at that iteration."""
    def progress(row):
        if row["iteration"] == interrupt_at:
            raise KeyboardInterrupt

    config = kw.pop("config", None) or small_config(iterations)
    kw.setdefault("poses", "identity")
    return fit(video, out, config, device="cpu", progress=progress, **kw)


def interrupted_fit(tmp_path, **kw) -> tuple[Path, Path]:
    """A frames folder and the scene path of a fit stopped at iteration 25 (its checkpoint kept)."""
    video = write_frames(tmp_path / "frames")
    out = tmp_path / "scene.ply"
    with pytest.raises(KeyboardInterrupt):
        fit_clip(video, out, interrupt_at=25, **kw)
    assert (tmp_path / "scene.ckpt").is_file()
    return video, out


def assert_consistent(state: dict) -> None:
    """Every parameter, its Adam moments and the densifier's statistics have the same rows."""
    rows = {name: t.shape[0] for name, t in state["params"].items()}
    assert len(set(rows.values())) == 1, rows
    n = next(iter(rows.values()))
    for index, moments in state["optimizer"]["state"].items():
        for key in ("exp_avg", "exp_avg_sq"):
            assert moments[key].shape[0] == n, (index, key, moments[key].shape, n)
    assert state["densifier"]["grad_sum"].shape[0] == n and state["densifier"]["seen"].shape[0] == n


# -- a checkpoint is data, never code ---------------------------------------------------------------


class Payload:
    """Unpickling this runs os.mkdir(marker): the stand-in for any code a crafted file could run."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return os.mkdir, (self.marker,)


def craft(kind: str, checkpoint: Path, marker: Path) -> None:
    """Replace the genuine `checkpoint` with a bad one of `kind`."""
    genuine = torch.load(checkpoint, map_location="cpu", weights_only=False)  # the attacker's tool: our own file
    if kind == "payload only":
        torch.save({"state": Payload(marker)}, checkpoint)
    elif kind == "payload added to a genuine checkpoint":
        genuine["notes"].append(Payload(marker))
        torch.save(genuine, checkpoint)
    elif kind == "payload in torch's legacy format":
        torch.save(Payload(marker), checkpoint, _use_new_zipfile_serialization=False)
    elif kind == "payload as a plain pickle":
        checkpoint.write_bytes(pickle.dumps([1, Payload(marker)]))
    elif kind == "garbage":
        checkpoint.write_bytes(b"\x00not a checkpoint" * 50)
    elif kind == "truncated":
        data = checkpoint.read_bytes()
        checkpoint.write_bytes(data[:len(data) // 2])
    elif kind == "empty":
        checkpoint.write_bytes(b"")
    elif kind == "plain data of another shape":
        torch.save({"iteration": 3, "params": [1, 2]}, checkpoint)
    elif kind == "rows that disagree":
        genuine["params"]["means"] = genuine["params"]["means"][:-1]
        torch.save(genuine, checkpoint)
    elif kind == "a log row of another layout":
        genuine["history"].append({"iteration": 26, "evil": 1})
        torch.save(genuine, checkpoint)
    elif kind == "a pending measurement of no frame":
        genuine["sampler"]["pending"] = [[10 ** 6, 30.0]]
        torch.save(genuine, checkpoint)
    elif kind == "a growth state of another layout":
        genuine["growth"]["stages"] = [["evil"]]
        torch.save(genuine, checkpoint)
    elif kind == "a densifier limit that is no count":
        genuine["densifier"]["limit"] = "evil"
        torch.save(genuine, checkpoint)
    elif kind == "unknown setting":
        config = genuine["config"] if isinstance(genuine["config"], dict) else vars(genuine["config"])
        genuine["config"] = dict(config, evil=1)
        torch.save(genuine, checkpoint)
    elif kind == "a setting of no allowed value":
        genuine["config"] = dict(genuine["config"], init_depth="evil")
        torch.save(genuine, checkpoint)
    else:
        raise AssertionError(kind)


BAD_CHECKPOINTS = ["payload only", "payload added to a genuine checkpoint", "payload in torch's legacy format",
                   "payload as a plain pickle", "garbage", "truncated", "empty", "plain data of another shape",
                   "rows that disagree", "a log row of another layout", "a pending measurement of no frame",
                   "a growth state of another layout", "a densifier limit that is no count", "unknown setting",
                   "a setting of no allowed value"]


@pytest.mark.parametrize("kind", BAD_CHECKPOINTS)
def test_a_crafted_or_damaged_checkpoint_is_refused_and_runs_nothing(tmp_path, kind):
    video, out = interrupted_fit(tmp_path)
    checkpoint = tmp_path / "scene.ckpt"
    marker = tmp_path / "payload-ran"
    craft(kind, checkpoint, marker)
    before = checkpoint.read_bytes()
    with pytest.raises(Exception) as caught:
        fit_clip(video, out, resume=True)
    assert not marker.exists(), "the checkpoint ran code"
    assert isinstance(caught.value, InputError), repr(caught.value)
    message = str(caught.value)
    assert str(checkpoint) in message and "--overwrite" in message, message
    assert checkpoint.read_bytes() == before  # kept for the user to look at
    assert not out.exists()


def test_trainer_load_checkpoint_runs_no_code(tmp_path):
    checkpoint, marker = tmp_path / "run.ckpt", tmp_path / "payload-ran"
    torch.save({"state": Payload(marker)}, checkpoint)
    with pytest.raises(InputError, match="run.ckpt"):
        trainer_for(10).load_checkpoint(checkpoint)
    assert not marker.exists()


def test_a_checkpoint_is_tensors_and_plain_data(tmp_path):
    interrupted_fit(tmp_path)
    state = read_state(tmp_path / "scene.ckpt")  # weights_only: raises on anything else
    assert state["iteration"] == 25 and isinstance(state["config"], dict)
    assert_consistent(state)


# -- temporaries and existing outputs ---------------------------------------------------------------


def test_checkpoint_temporaries_never_follow_a_planted_link(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    checkpoint = tmp_path / "scene.ckpt"
    for planted in ("scene.ckpt.tmp", f".scene.ckpt.{os.getpid()}.tmp", ".scene.ckpt.tmp"):
        (tmp_path / planted).symlink_to(victim)
    trainer = trainer_for(30)
    trainer.config.checkpoint_interval_s = 0.0
    with pytest.raises(KeyboardInterrupt):
        trainer.run(hooks=RunHooks(checkpoint=checkpoint, progress=lambda row: (_ for _ in ()).throw(KeyboardInterrupt)))
    assert victim.read_bytes() == b"precious"
    assert checkpoint.is_file() and not checkpoint.is_symlink()
    assert read_state(checkpoint)["iteration"] == 25


def test_the_log_never_follows_a_link_planted_during_the_run(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    video = write_frames(tmp_path / "frames")
    csv_path = tmp_path / "scene.csv"

    def plant(row):
        if row["iteration"] == 25:
            csv_path.unlink()
            csv_path.symlink_to(victim)

    fit(video, tmp_path / "scene.ply", small_config(60), poses="identity", device="cpu", progress=plant)
    assert victim.read_bytes() == b"precious"
    assert not csv_path.is_symlink() and csv_path.read_text().startswith("iteration,")


@pytest.mark.parametrize("which", ["scene.ply", "scene.csv", "scene.psnr.png", "scene.ckpt"])
def test_an_existing_output_is_refused_before_any_work(tmp_path, monkeypatch, which):
    video = write_frames(tmp_path / "frames")
    existing = tmp_path / which
    existing.write_bytes(b"the user's file")
    import tomgs.io

    def no_work(*a, **k):
        raise AssertionError("the video was read before the outputs were checked")

    monkeypatch.setattr(tomgs.io, "read_video", no_work)
    with pytest.raises(InputError) as caught:
        fit_clip(video, tmp_path / "scene.ply")
    message = str(caught.value)
    assert str(existing) in message and "--overwrite" in message, message
    if which == "scene.ckpt":
        assert "--resume" in message, message  # an interrupted run: continue it, or start over
    assert existing.read_bytes() == b"the user's file"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["frames", which])


def test_overwrite_replaces_every_output_and_starts_over(tmp_path):
    video, out = interrupted_fit(tmp_path)
    for name in ("scene.ply", "scene.psnr.png"):
        (tmp_path / name).write_bytes(b"old")
    result = fit_clip(video, out, iterations=40, overwrite=True)
    assert result.iterations == 40
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames", "scene.csv", "scene.ply", "scene.psnr.png"]
    assert (tmp_path / "scene.ply").read_bytes() != b"old" and (tmp_path / "scene.psnr.png").read_bytes() != b"old"
    rows = (tmp_path / "scene.csv").read_text().splitlines()
    assert rows[0].startswith("iteration,") and [r.split(",")[0] for r in rows[1:]] == ["25", "40"]


def test_resume_expects_the_log_and_checkpoint_but_refuses_a_scene(tmp_path):
    video, out = interrupted_fit(tmp_path)
    out.write_bytes(b"the user's scene")
    with pytest.raises(InputError, match="--overwrite"):
        fit_clip(video, out, resume=True)
    assert out.read_bytes() == b"the user's scene"
    out.unlink()
    result = fit_clip(video, out, resume=True)
    assert result.iterations == 60 and not (tmp_path / "scene.ckpt").exists()
    rows = list(csv.DictReader(open(tmp_path / "scene.csv")))
    logged = [r["iteration"] for r in rows if int(r["iteration"]) % 25 == 0 or r is rows[-1]]
    assert logged == ["25", "50", "60"]  # and between them the quality rule's rounds, each with its clip PSNR
    assert all(r["clip_psnr"] != "" for r in rows if r["iteration"] not in logged)


def test_stale_temporaries_are_cleaned_and_fresh_ones_kept(tmp_path):
    video = write_frames(tmp_path / "frames")
    stale = [tmp_path / ".scene.ckpt.k1l2m3.tmp", tmp_path / ".scene.csv.a1b2c3.tmp", tmp_path / ".scene.ply.x9.tmp"]
    for path in stale:
        path.write_bytes(b"left by a killed fit")
        os.utime(path, (time.time() - 3600, time.time() - 3600))
    fresh = tmp_path / ".scene.ckpt.z9y8x7.tmp"  # another process writing right now
    fresh.write_bytes(b"being written")
    fit_clip(video, tmp_path / "scene.ply", iterations=10)
    assert not any(p.exists() for p in stale)
    assert fresh.exists()


def test_a_failed_save_keeps_the_last_good_checkpoint_and_leaves_no_temporary(tmp_path, monkeypatch):
    checkpoint = tmp_path / "run.ckpt"
    trainer = trainer_for(30)
    trainer.save_checkpoint(checkpoint)
    good = checkpoint.read_bytes()
    real_save = torch.save

    def disk_full(obj, f, *a, **k):
        real_save({"partial": torch.zeros(10)}, f)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", disk_full)
    trainer.step()
    with pytest.raises(OSError):
        trainer.save_checkpoint(checkpoint)
    assert checkpoint.read_bytes() == good
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.ckpt"]


# -- durable fits: schedule and signals -------------------------------------------------------------


def scheduled_saves(monkeypatch, iterations: int, save_seconds: float = 0.0) -> list[tuple[int, float]]:
    """(iteration, clock) of every checkpoint of a run whose steps take one (fake) second each, and whose
    checkpoints keep training waiting `save_seconds`."""
    clock = [0.0]
    saves = []

    def step(self):
        clock[0] += 1.0
        self.iteration += 1

    def save(self, path, *a, **k):
        saves.append((self.iteration, clock[0]))
        clock[0] += save_seconds

    trainer = trainer_for(iterations)
    trainer.config = preset("quick", iterations=iterations, log_interval=25, eval_interval_s=1e9)
    monkeypatch.setattr(time, "perf_counter", lambda: clock[0])
    monkeypatch.setattr(Trainer, "step", step)
    monkeypatch.setattr(Trainer, "checkpoint_in_background", save)  # the periodic checkpoints
    monkeypatch.setattr(Trainer, "clip_psnr",
                        lambda self, tick=None, frames=None, hidden=None: [20.0] * len(
                            range(self.num_frames) if frames is None else frames))
    trainer.run(hooks=RunHooks(checkpoint=Path("unused.ckpt")))
    monkeypatch.undo()
    return saves


def test_a_crash_loses_at_most_30_seconds_of_training(monkeypatch):
    saves = scheduled_saves(monkeypatch, 200)
    times = [0.0] + [t for _, t in saves] + [200.0]
    assert max(np.diff(times)) <= 30.0, saves
    assert saves[0][0] > 1  # no checkpoint of a first step: nothing to lose yet


def test_slow_checkpoints_are_spaced_so_saving_costs_at_most_5_percent(monkeypatch):
    saves = scheduled_saves(monkeypatch, 400, save_seconds=5.0)
    gaps = np.diff([t for _, t in saves])
    assert len(saves) >= 2 and gaps.min() >= 100.0, saves


def test_sigint_saves_the_step_it_reached_and_restores_the_handlers(tmp_path):
    checkpoint = tmp_path / "run.ckpt"
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)

    def progress(row):
        if row["iteration"] == 50:
            os.kill(os.getpid(), signal.SIGINT)

    with pytest.raises(KeyboardInterrupt) as caught:
        trainer_for(100).run(hooks=RunHooks(checkpoint=checkpoint, progress=progress))
    assert getattr(caught.value, "checkpoint", "missing") == checkpoint
    assert getattr(caught.value, "signum", None) == signal.SIGINT
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
    state = read_state(checkpoint)
    assert state["iteration"] == 50
    assert_consistent(state)


def test_a_checkpoint_from_before_clip_frames_loads_and_resumes(tmp_path):
    """Rows of a checkpoint written before the log said how many frames a clip PSNR covers load (they
    covered every frame) and the run resumes from them; a row with another key is still refused."""
    checkpoint = tmp_path / "run.ckpt"

    def progress(row):
        if row["iteration"] == 50:
            os.kill(os.getpid(), signal.SIGINT)

    trainer = trainer_for(100)
    trainer.config = trainer.config.replace(eval_interval_s=0.0)
    with pytest.raises(KeyboardInterrupt):
        trainer.run(hooks=RunHooks(checkpoint=checkpoint, progress=progress))
    state = read_state(checkpoint)
    assert any(row["clip_psnr"] != "" for row in state["history"]), state["history"]
    for row in state["history"]:
        del row["clip_frames"]  # as an older tomgs wrote it
    torch.save(state, checkpoint)
    loaded = read_checkpoint(checkpoint)
    assert all(row["clip_frames"] == (3 if row["clip_psnr"] != "" else "") for row in loaded["history"])
    resumed = trainer_for(100)
    resumed.config = resumed.config.replace(eval_interval_s=0.0)
    resumed.load_checkpoint(checkpoint)
    result = resumed.run(hooks=RunHooks(log_csv=tmp_path / "run.csv"))
    assert result.iterations == 100 and result.history[-1]["clip_frames"] == 3
    with open(tmp_path / "run.csv") as f:
        rows = list(csv.DictReader(f))
    assert rows[0]["clip_frames"] in ("", "3") and rows[-1]["clip_frames"] == "3"
    state["history"].append(dict(state["history"][-1], evil=1))
    torch.save(state, checkpoint)
    with pytest.raises(InputError, match="history rows"):
        read_checkpoint(checkpoint)


def test_a_run_outside_the_main_thread_trains_without_signal_handlers(tmp_path):
    import threading

    outcome = []
    thread = threading.Thread(target=lambda: outcome.append(trainer_for(10).run(hooks=RunHooks(checkpoint=tmp_path / "run.ckpt"))))
    thread.start()
    thread.join(timeout=300)
    assert outcome and outcome[0].iterations == 10


SIGTERM_SCRIPT = textwrap.dedent("""
    import json, os, signal, sys
    from pathlib import Path
    sys.path[:0] = sys.argv[2].split(os.pathsep)
    from tests.train.test_train import CPU, small_config, synthetic_clip
    from tomgs.train import Trainer
    from tomgs.train.loop import RunHooks

    images, cams, points, colors = synthetic_clip(3, 32, 18)
    trainer = Trainer(images, cams, points, colors, small_config(100), CPU)

    def progress(row):
        if row["iteration"] == 50:
            os.kill(os.getpid(), signal.SIGTERM)

    try:
        trainer.run(hooks=RunHooks(checkpoint=Path(sys.argv[1]), progress=progress))
    except KeyboardInterrupt as e:
        print(json.dumps(dict(signum=getattr(e, "signum", None), checkpoint=str(getattr(e, "checkpoint", None)))))
""")


def test_sigterm_saves_a_checkpoint_and_stops_cleanly(tmp_path):
    checkpoint = tmp_path / "run.ckpt"
    done = subprocess.run([sys.executable, "-c", SIGTERM_SCRIPT, str(checkpoint), str(TESTS)], capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, (done.returncode, done.stderr[-2000:])
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report == dict(signum=signal.SIGTERM, checkpoint=str(checkpoint))
    assert read_state(checkpoint)["iteration"] == 50
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.ckpt"]


def test_an_interrupt_inside_densification_never_saves_a_torn_state(tmp_path, monkeypatch):
    """SIGINT between the parameter swap and the optimiser update: the densification finishes, then
    the step is saved; the checkpoint resumes to the end."""
    from tomgs.model import GaussianModel

    checkpoint = tmp_path / "run.ckpt"
    original = GaussianModel.replace
    fired = []

    def replace(self, tensors):
        original(self, tensors)
        if not fired:
            fired.append(True)
            os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(GaussianModel, "replace", replace)
    with pytest.raises(KeyboardInterrupt):
        trainer_for(200).run(hooks=RunHooks(checkpoint=checkpoint))  # densifies at 100 and 150
    monkeypatch.undo()
    assert fired
    state = read_state(checkpoint)
    assert state["iteration"] == 100
    assert_consistent(state)
    resumed = trainer_for(200)
    resumed.load_checkpoint(checkpoint)
    assert resumed.run(hooks=RunHooks(checkpoint=checkpoint)).iterations == 200
    assert_consistent(read_state(checkpoint))


def test_an_exception_inside_densification_keeps_the_last_good_checkpoint(tmp_path, monkeypatch):
    """An interrupt that is not a signal (raised in the middle of the swap) saves nothing: the
    checkpoint on disk stays the last complete one."""
    from tomgs.model import GaussianModel

    checkpoint = tmp_path / "run.ckpt"
    # densifies at 100; no periodic checkpoint before it, however slow a loaded machine steps
    trainer = trainer_for(200, checkpoint_interval_s=1e9)
    trainer.save_checkpoint(checkpoint)
    good = checkpoint.read_bytes()
    original = GaussianModel.replace

    def replace(self, tensors):
        original(self, tensors)
        raise KeyboardInterrupt

    monkeypatch.setattr(GaussianModel, "replace", replace)
    with pytest.raises(KeyboardInterrupt):
        trainer.run(hooks=RunHooks(checkpoint=checkpoint))
    assert checkpoint.read_bytes() == good


@pytest.mark.parametrize("resume", [False, True])
def test_an_interrupt_while_decoding_reports_the_checkpoint_there_is(tmp_path, monkeypatch, resume):
    import tomgs.io

    if resume:
        video, out = interrupted_fit(tmp_path)
    else:
        video, out = write_frames(tmp_path / "frames"), tmp_path / "scene.ply"
    real_read = tomgs.io.read_video

    def read_then_ctrl_c(*a, **k):
        clip = real_read(*a, **k)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.5)
        return clip

    monkeypatch.setattr(tomgs.io, "read_video", read_then_ctrl_c)
    with pytest.raises(KeyboardInterrupt) as caught:
        fit_clip(video, out, resume=resume)
    expected = tmp_path / "scene.ckpt" if resume else None
    assert getattr(caught.value, "checkpoint", "missing") == expected
    assert (tmp_path / "scene.ckpt").exists() == resume


# -- resume: same clip, same sizes ----------------------------------------------------------------------


@pytest.mark.parametrize("change, option", [
    (dict(frames="0:3"), "--frames"),
    (dict(frames="1:5"), "--frames"),
    (dict(max_side=16), "--max-side"),
    (dict(config=small_config(60, sh_degree=1)), "--sh-degree"),
    (dict(config=small_config(60, temporal=False)), "--static"),
    (dict(poses="auto"), "--poses"),
    (dict(video="flipped"), "video"),
])
def test_resume_refuses_options_that_change_the_frames(tmp_path, change, option):
    video, out = interrupted_fit(tmp_path, frames="0:4")
    checkpoint = tmp_path / "scene.ckpt"
    before = checkpoint.read_bytes()
    if change.get("video") == "flipped":
        change = dict(video=write_frames(tmp_path / "other", flipped=True))
    kw = dict(dict(video=video, frames="0:4"), **change)
    with pytest.raises(InputError) as caught:
        fit_clip(kw.pop("video"), out, resume=True, **kw)
    assert option in str(caught.value) and "--overwrite" in str(caught.value), str(caught.value)
    assert checkpoint.read_bytes() == before and not out.exists()
    result = fit_clip(video, out, resume=True, frames="0:4")  # the same options still resume
    assert result.iterations == 60 and not checkpoint.exists()


def test_resume_uses_the_checkpoints_cameras_and_repeats_the_uninterrupted_run(tmp_path, monkeypatch):
    import tomgs.poses

    video, out = interrupted_fit(tmp_path)
    real_estimate = tomgs.poses.estimate_cameras

    def no_estimate(*a, **k):
        raise AssertionError("resume estimated the cameras again")

    monkeypatch.setattr(tomgs.poses, "estimate_cameras", no_estimate)
    resumed = fit_clip(video, out, resume=True)
    monkeypatch.setattr(tomgs.poses, "estimate_cameras", real_estimate)
    straight = fit_clip(video, tmp_path / "straight.ply")
    assert resumed.iterations == straight.iterations == 60
    assert np.allclose(resumed.cameras.c2w, straight.cameras.c2w)
    assert abs(resumed.clip_psnr - straight.clip_psnr) <= 0.1


# -- an all-black clip ------------------------------------------------------------------------------------


def test_an_all_black_clip_fits_and_leaves_no_checkpoint(tmp_path):
    video = write_frames(tmp_path / "frames", black=True)
    result = fit_clip(video, tmp_path / "scene.ply", iterations=30)
    assert result.iterations == 30
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames", "scene.csv", "scene.ply", "scene.psnr.png"]


def test_the_sampler_takes_perfect_and_undefined_psnrs():
    sampler = FrameSampler(4, seed=0)
    for frame, value in enumerate([float("inf"), float("nan"), 30.0, float("inf")]):
        sampler.update(frame, value)
    p = sampler.probabilities()
    assert torch.isfinite(p).all() and float(p.sum()) == pytest.approx(1.0) and (p > 0).all()
    assert p[1] >= p[2] >= p[0]  # unmeasured (nan) counts as the worst, a perfect frame as the best
    assert 0 <= sampler.sample() < 4


def test_a_warm_up_beside_the_poses_changes_no_result(tmp_path, monkeypatch, capsys):
    """On a GPU a fit pays its first steps' one-off costs in a thread while the CPU reads the clip and
    estimates its cameras (tomgs.train.warm). Forced on here on the CPU: the thread runs a throwaway
    Trainer, and the fitted scene is bit-identical to the fit without it."""
    from tomgs.io.scene import load_scene
    from tomgs.train import warm

    assert warm.pays_on(torch.device("cuda")) and not warm.pays_on(CPU)
    video = write_frames(tmp_path / "frames")
    fit_clip(video, tmp_path / "plain.ply", iterations=30)
    warmed = []
    real_warm_up = warm.warm_up
    monkeypatch.setattr(warm, "pays_on", lambda device: True)
    monkeypatch.setattr(warm, "warm_up", lambda config, device: warmed.append(real_warm_up(config, device)))
    fit_clip(video, tmp_path / "warmed.ply", iterations=30)
    assert warmed == [None] and "warm-up skipped" not in capsys.readouterr().err
    plain, warmed_scene = load_scene(tmp_path / "plain.ply").model, load_scene(tmp_path / "warmed.ply").model
    for name, value in plain.parameters_by_name().items():
        assert torch.equal(value, warmed_scene.parameters_by_name()[name]), name
