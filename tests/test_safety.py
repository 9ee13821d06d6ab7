"""The "safe by default" promises at their edges, one test per defect an adversarial audit found:
outputs that collide, full disks, signals, crafted sizes and extreme option values. Each test's name
says which defect it holds to (docs/notes/safety.md lists them)."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from benchmarks.declared_sizes import declare_jpeg, views_declaring
from tomgs.cameras import Cameras, intrinsics, look_at
from tomgs.cli import main
from tomgs.io.scene import load_scene, save_scene
from tomgs.model import GaussianModel
from tomgs.train.budget import Budget

W, H, T = 32, 24, 3


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def one_line_refusal(result, code: int = 2) -> str:
    """The error line of a refused command: exit `code`, one line, no traceback."""
    assert result.exit_code == code, result.output
    assert isinstance(result.exception, SystemExit), result.exception
    lines = [line for line in result.output.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: "), result.output
    return lines[0]


def tiny_model(n: int = 60, seed: int = 3) -> GaussianModel:
    g = torch.Generator().manual_seed(seed)
    xy = torch.rand(n, 2, generator=g) * 2.0 - 1.0
    means = torch.cat([xy, 3.0 + 0.2 * torch.rand(n, 1, generator=g)], 1)
    model = GaussianModel.from_points(means, torch.rand(n, 3, generator=g), torch.rand(n, generator=g), t_scale=0.4,
                                      max_sh_degree=0, opacity=0.8)
    with torch.no_grad():
        model.log_scales.fill_(np.log(0.15))
    return model


def tiny_cameras(frames: int = T) -> Cameras:
    c2w = np.stack([look_at([0.05 * k, 0.0, 0.0], [0.0, 0.0, 3.0]) for k in range(frames)])
    return Cameras.create(c2w, intrinsics(30.0, W, H), W, H, frame_indices=np.arange(frames))


def write_scene(path, info=None, model=None) -> Path:
    save_scene(path, tiny_model() if model is None else model, tiny_cameras(), {"fps": 12.0, **(info or {})})
    return Path(path)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_scene(tmp_path_factory.mktemp("scene") / "tiny.ply")


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    path = tmp_path_factory.mktemp("clip") / "clip.mp4"
    assert run("demo", "-o", path, "--frames", "4", "--size", "48x27", "--device", "cpu").exit_code == 0
    return path


def listing(folder: Path) -> dict:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


# -- 1. a finished result overwritten -----------------------------------------------------------------


@pytest.mark.parametrize("case", ["json over scene", "json over log", "poses json over cameras", "render over scene",
                                  "edit over its scene", "export over its cameras", "json through a link",
                                  "frames folder holding a mask"])
def test_defect01_outputs_never_overwrite_each_other_or_an_input(case, clip, scene, tmp_path):
    """`fit -o g.ply --json g.ply` wrote the JSON over the scene (exit 0); `--json g.csv` over the log;
    `poses -o c.json --json c.json` over the cameras. Every such collision is refused before any work."""
    (tmp_path / "given").mkdir()
    scene_copy = tmp_path / "given" / "s.ply"
    scene_copy.write_bytes(scene.read_bytes())
    (tmp_path / "masks").mkdir()
    (tmp_path / "masks" / "00000.png").write_bytes(b"a mask")
    os.symlink(tmp_path / "given" / "s.ply", tmp_path / "link.json")
    o = tmp_path
    args = {
        "json over scene": ["fit", clip, "-o", o / "g.ply", "--json", o / "g.ply", "--iterations", "3"],
        "json over log": ["fit", clip, "-o", o / "g.ply", "--json", o / "g.csv", "--iterations", "3"],
        "poses json over cameras": ["poses", clip, "-o", o / "c.json", "--json", o / "c.json"],
        "render over scene": ["render", scene_copy, "-o", o / "given" / "s.ply"],
        "edit over its scene": ["edit", scene_copy, "-o", o / "given" / "s.ply", "--translate", "1,0,0", "-y"],
        "export over its cameras": ["export", scene_copy, "-o", o / "cams" / "cameras.json", "--cameras-out",
                                    o / "cams", "--frame", "0"],
        "json through a link": ["eval", scene_copy, clip, "--json", o / "link.json", "-y"],
        "frames folder holding a mask": ["edit", scene_copy, "-o", o / "e.ply", "--translate", "1,0,0", "--select",
                                         f"mask:{o / 'masks'}", "--render", o / "masks", "-y"],
    }[case]
    before = {p: p.read_bytes() for p in o.rglob("*") if p.is_file()}
    line = one_line_refusal(run(*args))
    assert "is also" in line or "the input" in line, line
    after = {p: p.read_bytes() for p in o.rglob("*") if p.is_file()}
    assert after == before  # nothing written, nothing replaced


# -- 2. a full disk while writing a video ---------------------------------------------------------------


class FullDisk:
    """`open` for tomgs.io.writer whose files take `room` bytes in all, then raise ENOSPC (a small
    disk, deterministically; `code`: another errno, EIO for a failing disk). Once full, a seek fails
    too, as a buffered file's does when it flushes bytes that no longer fit; `buffered`: the write that
    overflows seems to succeed (its bytes wait in the buffer) and only the seeks after it fail."""

    def __init__(self, room: int, buffered: bool = False, code: int = errno.ENOSPC):
        self.room, self.buffered, self.code = room, buffered, code

    def __call__(self, path, mode="r", *args, **kwargs):
        real = open(path, mode, *args, **kwargs)  # noqa: SIM115 - handed to the caller
        if "r" in mode and "+" not in mode:
            return real
        disk = self

        class Limited:
            def __getattr__(self, name):
                return getattr(real, name)

            def __enter__(self):
                return self

            def __exit__(self, *exc):
                real.close()

            def write(self, data):
                if len(data) > disk.room:
                    disk.room = 0
                    if disk.buffered:
                        return len(data)
                    raise OSError(disk.code, os.strerror(disk.code))
                disk.room -= len(data)
                return real.write(data)

            def seek(self, offset, whence=0):
                if disk.room == 0:
                    raise OSError(disk.code, os.strerror(disk.code))
                return real.seek(offset, whence)
        return Limited()


@pytest.mark.parametrize("name", ["d.mp4", "d.mkv", "d.avi", "frames"])
@pytest.mark.parametrize("room", [0, 3000])
def test_defect02_full_disk_while_writing_a_video_is_one_line_and_leaves_nothing(name, room, monkeypatch, tmp_path):
    """`demo -o full/d.mp4` ended in a segmentation fault (the PyAV writer closed again after its close
    failed) and `render -o full/r.mp4` in "Aborted!", each leaving a hidden .d.mp4.XXXX.tmp/ folder."""
    import tomgs.io.writer as writer

    monkeypatch.setattr(writer, "open", FullDisk(room), raising=False)
    if name == "d.avi":  # OpenCV writes .avi itself: its file is short of frames, which the writer reads back
        monkeypatch.setattr(writer._MJPGWriter, "write", lambda self, rgb: setattr(self, "count", self.count + 1))
    result = run("demo", "-o", tmp_path / name, "--frames", "6", "--size", "48x27", "--device", "cpu", "-q")
    line = one_line_refusal(result, code=1)
    assert str(tmp_path / name) in line and "nothing was written" in line, line
    assert "No space left on device" in line or "holds 0 of its 6 frames" in line, line
    assert list(tmp_path.iterdir()) == []  # no output, no temporary


@pytest.mark.parametrize("name", ["d.mp4", "frames"])
def test_a_failing_disk_while_writing_a_video_is_one_line_and_leaves_nothing(name, monkeypatch, tmp_path):
    """EIO, a disk that fails rather than fills, takes the same way out as ENOSPC: one line naming the
    file and its error, nothing left."""
    import tomgs.io.writer as writer

    monkeypatch.setattr(writer, "open", FullDisk(3000, code=errno.EIO), raising=False)
    result = run("demo", "-o", tmp_path / name, "--frames", "6", "--size", "48x27", "--device", "cpu", "-q")
    line = one_line_refusal(result, code=1)
    assert str(tmp_path / name) in line and "Input/output error; nothing was written" in line, line
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("room", [0, 3000])
def test_defect02_a_seek_that_fails_on_a_full_disk_is_no_traceback(room, monkeypatch, tmp_path):
    """A full disk met first by a seek (a buffered file flushing): FFmpeg seeks again after the first
    failure, and PyAV printed each earlier failure's traceback ("PyAV library exception being
    dropped") above the one line; the safety trials' `render` on a tmpfs found it."""
    import tomgs.io.writer as writer

    monkeypatch.setattr(writer, "open", FullDisk(room, buffered=True), raising=False)
    result = run("demo", "-o", tmp_path / "d.mp4", "--frames", "6", "--size", "48x27", "--device", "cpu", "-q")
    line = one_line_refusal(result, code=1)
    assert "No space left on device; nothing was written" in line, line
    assert list(tmp_path.iterdir()) == []


def test_defect02_a_video_writer_is_closed_once_even_when_its_close_fails(monkeypatch, tmp_path):
    from tomgs.io import write_frames
    from tomgs.io import writer

    closes = []

    class Failing:
        def __init__(self, *args):
            pass

        def write(self, rgb):
            pass

        def close(self):
            closes.append(1)
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(writer, "_H264Writer", Failing)
    frames = [np.zeros((8, 8, 3), np.uint8)] * 3
    with pytest.raises(OSError, match="No space left on device; nothing was written") as caught:
        write_frames(frames, tmp_path / "v.mp4")
    assert caught.value.filename == str(tmp_path / "v.mp4") and closes == [1]
    assert list(tmp_path.iterdir()) == []


def test_defect02_a_failed_write_keeps_the_previous_video(monkeypatch, tmp_path):
    import tomgs.io.writer as writer

    old = tmp_path / "d.mp4"
    old.write_bytes(b"the earlier render")
    monkeypatch.setattr(writer, "open", FullDisk(2000), raising=False)
    line = one_line_refusal(run("demo", "-o", old, "--frames", "4", "--size", "48x27", "--device", "cpu", "-y", "-q"), 1)
    assert "the existing d.mp4 is kept" in line
    assert listing(tmp_path) == {"d.mp4": b"the earlier render"}


# -- 10. tracebacks for extreme option values ---------------------------------------------------------------


@pytest.mark.parametrize("args, option", [
    (["fit", "{clip}", "-o", "{tmp}/s.ply", "--budget", "inf"], "--budget"),
    (["fit", "{clip}", "-o", "{tmp}/s.ply", "--budget", "1e308"], "--budget"),
    (["fit", "{clip}", "-o", "{tmp}/s.ply", "--focal", "1e-300"], "--focal"),
    (["fit", "{clip}", "-o", "{tmp}/s.ply", "--focal", "1e300"], "--focal"),
    (["poses", "{clip}", "-o", "{tmp}/c.json", "--focal", "1e300"], "--focal"),
    (["fit", "{clip}", "-o", "{tmp}/s.ply", "--seed", str(2**70)], "--seed"),
    (["render", "{scene}", "-o", "{tmp}/r.mp4", "--fps", "1e300"], "--fps"),
    (["edit", "{scene}", "-o", "{tmp}/e.ply", "--translate", "1e308,0,0"], "--translate"),
    (["edit", "{scene}", "-o", "{tmp}/e.ply", "--scale", "1e300"], "--scale"),
])
def test_defect10_extreme_option_values_are_refused_at_the_door(args, option, clip, scene, tmp_path):
    args = [a.replace("{clip}", str(clip)).replace("{scene}", str(scene)).replace("{tmp}", str(tmp_path))
            for a in args]
    line = one_line_refusal(run(*args))
    assert option in line and "give" in line, line
    assert list(tmp_path.iterdir()) == []


def test_defect10_a_scene_whose_stored_rate_is_absurd_renders_at_the_default(tmp_path):
    path = write_scene(tmp_path / "s.ply", {"fps": 1e300})
    result = run("render", path, "-o", tmp_path / "r.mp4", "--device", "cpu")
    assert result.exit_code == 0, result.output
    import av

    with av.open(str(tmp_path / "r.mp4")) as container:
        assert float(container.streams.video[0].average_rate) == pytest.approx(25.0)


def test_defect10_the_ends_of_every_range_run(scene, tmp_path):
    """The largest and smallest accepted values do their work: no traceback at a range's end."""
    for k, (extra, out) in enumerate([(["--translate", "1e6,-1e6,1e6"], "a.ply"), (["--scale", "1e6"], "b.ply"),
                                      (["--scale", "1e-6", "--rotate", "1e6,-1e6,0"], "c.ply")]):
        result = run("edit", scene, "-o", tmp_path / out, *extra)
        assert result.exit_code == 0, result.output
        assert np.isfinite(load_scene(tmp_path / out).model.means.detach().numpy()).all()
    for fps in ("0.1", "1000"):
        result = run("render", scene, "-o", tmp_path / f"r{fps}.mp4", "--fps", fps, "--device", "cpu")
        assert result.exit_code == 0, result.output


# -- 3. a full disk at a checkpoint ---------------------------------------------------------------------


def test_defect03_a_checkpoint_that_cannot_be_written_lets_training_go_on(tmp_path, monkeypatch):
    """A fit died at 64.6 s with a multi-page traceback when a checkpoint met a full disk. The run goes
    on, notes it, and the last complete checkpoint stays the one to resume."""
    from tests.train.test_train import background_writes, run_clip

    background_writes(monkeypatch, {}, error=OSError(errno.ENOSPC, "No space left on device", "run.ckpt"))
    rows = []
    result = run_clip(30, checkpoint=tmp_path / "run.ckpt", checkpoint_interval_s=0.0, log_interval=1,
                      on_row=rows.append)
    assert result.iterations == 30 and len(rows) == 30
    said = [n for n in result.notes if "checkpoint could not be written" in n]
    assert len(said) == 1 and "No space left on device" in said[0] and "training went on" in said[0], result.notes


def test_defect03_torch_zip_writer_on_a_full_disk_is_an_os_error_naming_the_checkpoint(tmp_path, monkeypatch):
    import tomgs.train.checkpoint as checkpoint
    from tests.train.test_train import CPU, small_config, synthetic_clip
    from tomgs.train import Trainer

    images, cams, points, colors = synthetic_clip(2, 24, 14)
    state = Trainer(images, cams, points, colors, small_config(5), CPU).state_dict()
    path = tmp_path / "run.ckpt"
    path.write_bytes(b"the last complete checkpoint")
    monkeypatch.setattr(checkpoint, "open", FullDisk(500), raising=False)
    with pytest.raises(OSError) as caught:
        checkpoint.write_checkpoint(path, state)
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(path)
    assert "the existing run.ckpt is kept" in caught.value.strerror
    assert listing(tmp_path) == {"run.ckpt": b"the last complete checkpoint"}


def test_defect03_a_stop_whose_save_fails_points_at_the_last_complete_checkpoint(tmp_path, monkeypatch):
    import tomgs.train.trainer as trainer
    from tests.train.test_train import background_writes, run_clip
    from tomgs.train import FitInterrupted

    background_writes(monkeypatch, {})
    monkeypatch.setattr(trainer, "write_checkpoint",
                        lambda path, state: (_ for _ in ()).throw(OSError(errno.ENOSPC, "No space left on device",
                                                                         str(path))))
    with pytest.raises(FitInterrupted) as caught:
        run_clip(40, interrupt_at=20, checkpoint=tmp_path / "run.ckpt", checkpoint_interval_s=0.0, log_interval=1)
    assert caught.value.checkpoint == tmp_path / "run.ckpt"
    assert "could not be saved" in caught.value.message() and "last complete checkpoint" in caught.value.message()


def test_defect03_a_full_disk_at_the_final_save_is_one_line_naming_the_scene(clip, tmp_path, monkeypatch):
    import tomgs.io.scene as scene_io

    monkeypatch.setattr(scene_io, "open", FullDisk(0), raising=False)
    out = tmp_path / "s.ply"
    result = run("fit", clip, "-o", out, "--iterations", "3", "--device", "cpu", "--poses", "identity", "-q")
    line = one_line_refusal(result, code=1)
    assert str(out) in line and "No space left on device" in line and "run the fit again" in line, line
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


# -- 11. lesser ---------------------------------------------------------------------------------------------


def test_defect11_compaction_never_leaves_an_empty_scene_and_an_empty_scene_exports(clip, tmp_path):
    """`--compact inf` wrote a 0-Gaussian scene (exit 0), and exporting that crashed."""
    out = tmp_path / "s.ply"
    result = run("fit", clip, "-o", out, "--iterations", "3", "--device", "cpu", "--poses", "identity",
                 "--compact", "1e6")
    assert result.exit_code == 0, result.output
    assert len(load_scene(out).model) > 0 and "would leave out every Gaussian" in result.output
    empty = tiny_model()
    empty.replace({k: v.detach()[:0] for k, v in empty.parameters_by_name().items()})
    path = write_scene(tmp_path / "empty.ply", model=empty)
    for name in ("e.ply", "e.splat", "e.spz"):
        result = run("export", path, "-o", tmp_path / name, "--frame", "0")
        assert result.exit_code == 0 and "0 of 0 Gaussians" in result.output, result.output


def test_defect11_the_cap_holds_from_the_first_step(clip, tmp_path):
    """`--cap 100` ended with 171 Gaussians: the tracked points and a point a frame came on top of it."""
    out = tmp_path / "s.ply"
    result = run("fit", clip, "-o", out, "--iterations", "3", "--device", "cpu", "--cap", "5", "--compact", "0")
    assert result.exit_code == 0, result.output
    assert len(load_scene(out).model) <= 5


def test_defect11_a_resumed_fit_says_the_limit_it_ran_under():
    """A resume's note claimed a time limit longer than its --budget: the training seconds of both runs."""
    from tests.train.test_train import CPU, small_config, synthetic_clip
    from tomgs.train import Trainer

    images, cams, points, colors = synthetic_clip(2, 24, 14)
    trainer = Trainer(images, cams, points, colors, small_config(10**6), CPU)
    trainer.elapsed = 500.0  # as if resumed after 500 s of training
    result = trainer.run(Budget(iterations=trainer.config.iterations, training_until=501.0))
    note = [n for n in result.notes if n.startswith("training stopped")]
    assert note and "1 s of training in this run, 501 s in all" in note[0], result.notes


@pytest.mark.parametrize("option", ["--budget", "--compact"])
def test_defect11_nan_is_refused_not_ignored(option, clip, tmp_path):
    line = one_line_refusal(run("fit", clip, "-o", tmp_path / "s.ply", option, "nan"))
    assert option in line and "finite" in line


def test_defect11_ctrl_c_while_a_command_starts_exits_130_in_one_line(scene, tmp_path, monkeypatch):
    """Ctrl-C during start-up (a command's imports) exited 1 with "Aborted!"."""
    import tomgs.io.scene as scene_io

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(scene_io, "load_scene", interrupted)
    result = run("render", scene, "-o", tmp_path / "r.mp4")
    assert result.exit_code == 130, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert lines == ["interrupted (SIGINT): stopped, nothing half-written left"], result.output


@pytest.mark.parametrize("command", ["export", "edit", "info"])
def test_defect11_a_full_disk_names_the_file_in_every_command(command, scene, tmp_path, monkeypatch):
    import tomgs.outputs as outputs

    real = Path.write_bytes

    def full(self, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(Path, "write_bytes", full)
    monkeypatch.setattr(outputs, "_fsync_folder", lambda folder: None)
    import tomgs.io.scene as scene_io
    import tomgs.io.splats as splats

    monkeypatch.setattr(scene_io, "open", FullDisk(0), raising=False)
    monkeypatch.setattr(splats, "open", FullDisk(0), raising=False)
    target = {"export": tmp_path / "x.splat", "edit": tmp_path / "e.ply", "info": tmp_path / "p.png"}[command]
    args = {"export": ["export", scene, "-o", target, "--frame", "0"],
            "edit": ["edit", scene, "-o", target, "--translate", "1,0,0"],
            "info": ["info", scene, "--plot", target]}[command]
    line = one_line_refusal(run(*args), code=1)
    monkeypatch.setattr(Path, "write_bytes", real)
    assert line == f"Error: {target}: No space left on device; nothing was written", line
    assert list(tmp_path.iterdir()) == []


def test_defect11_a_full_disk_at_the_fits_lock_names_the_scene(clip, tmp_path, monkeypatch):
    """A fit into a folder with no room left: writing its process id into the lock failed with a bare
    "Error: No space left on device" naming no file (the safety trials' fit on a tmpfs found it). Now
    the line names the scene and what was kept, before any work, and no lock is left."""
    import tomgs.outputs as outputs

    class NoRoom:  # tomgs.outputs's `os`, whose writes find the disk full
        def __getattr__(self, name):
            return getattr(os, name)

        @staticmethod
        def write(fd, data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(outputs, "os", NoRoom())
    (tmp_path / "s.ply").write_bytes(b"an earlier scene")
    line = one_line_refusal(run("fit", clip, "-o", tmp_path / "s.ply", "--iterations", "3", "-y", "-q"), code=1)
    assert line == f"Error: {tmp_path / 's.ply'}: No space left on device; the existing s.ply is kept", line
    assert listing(tmp_path) == {"s.ply": b"an earlier scene"} and sorted(os.listdir(tmp_path)) == ["s.ply"]


# -- 4. --gpus N started N processes before any check ------------------------------------------------------


@pytest.mark.parametrize("args, gpus, cores, message", [
    (["--gpus", "12"], 0, 2, "--gpus 12: torch sees no GPU here; give --device cpu"),
    (["--gpus", "3", "--device", "cuda"], 2, 2, "--gpus 3: this host has 2 GPUs"),
    (["--gpus", "12", "--device", "cpu"], 0, 2, "--gpus 12 --device cpu: this machine has 2 CPU cores"),
    (["--gpus", "2", "--device", "cuda:1"], 2, 2, "each rank takes its own GPU"),
    (["--gpus", "100000"], 8, 64, "--gpus 100000: out of range; give processes in 1..1024"),
])
def test_defect04_gpus_beyond_the_host_are_refused_before_any_process_starts(args, gpus, cores, message, clip,
                                                                            tmp_path, monkeypatch):
    """`--gpus 12` on a machine without GPUs took 32 s and 2.4 GB before its refusal, and had no bound."""
    from tomgs.train.multigpu import pool as rank_pool

    started = []
    monkeypatch.setattr(rank_pool, "start", started.append)
    monkeypatch.setattr(rank_pool, "visible_gpus", lambda: gpus)
    monkeypatch.setattr(os, "cpu_count", lambda: cores)
    line = one_line_refusal(run("fit", clip, "-o", tmp_path / "s.ply", *args))
    assert message in line, line
    assert started == [] and list(tmp_path.iterdir()) == []


def test_defect04_gpus_are_counted_without_torch(monkeypatch, tmp_path):
    from tomgs.train.multigpu import pool as rank_pool

    monkeypatch.setattr(os, "listdir", lambda path: ["0000:01:00.0", "0000:02:00.0", "0000:03:00.0"]
                        if path == "/proc/driver/nvidia/gpus" else [])
    for visible, count in ((None, 3), ("1,0", 2), ("0,7,1", 1), ("", 0), ("-1", 0), ("GPU-abc,2", 2)):
        if visible is None:
            monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
        else:
            monkeypatch.setenv("CUDA_VISIBLE_DEVICES", visible)
        assert rank_pool.visible_gpus() == (count if os.uname().sysname == "Linux" else None), visible


# -- 5. a crafted checkpoint: stride-0 views declaring what their bytes do not hold ---------------------------


def test_defect05_a_checkpoint_of_views_declaring_more_than_their_storage_is_refused(tmp_path):
    """A 32 KB checkpoint whose tensors were stride-0 views declaring 200M rows over one made `--resume`
    allocate without bound (5.7 GB, then an allocator traceback)."""
    from tests.train.test_train import CPU, small_config, synthetic_clip
    from tomgs.errors import InputError
    from tomgs.train import Trainer, read_checkpoint

    images, cams, points, colors = synthetic_clip(2, 24, 14)
    state = Trainer(images, cams, points, colors, small_config(5), CPU).state_dict()
    rows = 200_000_000
    state = views_declaring(state, rows)
    path = tmp_path / "s.ckpt"
    torch.save(state, path)
    assert path.stat().st_size < 200_000
    with pytest.raises(InputError, match=r"a tensor of shape \(200000000, 3\) over [\d,]+ stored bytes"):
        read_checkpoint(path)


# -- 6. sizes declared that the bytes cannot fill -----------------------------------------------------------


def _texture(k: int, h: int = 48, w: int = 64) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([(x * 5 + 9 * k) % 256, (y * 7 + 3 * k) % 256, (x * y + k) % 256], -1).astype(np.uint8)


@pytest.mark.parametrize("progressive", [True, False])
def test_defect06_jpeg_frames_declaring_more_than_their_bytes_are_refused_before_decoding(progressive, tmp_path):
    """3 KB JPEGs patched to declare 16000x16000 made `poses` peak at 5.2 GB (progressive JPEG had a
    lower bound of 0 bytes) and `fit` end in an allocator traceback."""
    import cv2

    folder = tmp_path / "frames"
    folder.mkdir()
    for k in range(3):
        ok, data = cv2.imencode(".jpg", _texture(k), [cv2.IMWRITE_JPEG_PROGRESSIVE, int(progressive)])
        patched = declare_jpeg(data.tobytes(), b"\xff\xc2" if progressive else b"\xff\xc0", 16000, 16000)
        assert len(patched) < 4000
        (folder / f"{k:05d}.jpg").write_bytes(patched)
    for command in (["poses", folder, "-o", tmp_path / "c.json"], ["fit", folder, "-o", tmp_path / "s.ply"]):
        line = one_line_refusal(run(*command))
        assert "declares a 16000x16000 JPEG image, more than its" in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames"]


def test_defect06_a_motion_jpeg_video_declaring_more_than_its_bytes_is_refused(tmp_path):
    """A 27 KB MJPEG AVI whose frames declared large sizes peaked at 5.2 GB: videos were not checked."""
    from tomgs.io import write_frames

    write_frames([_texture(k) for k in range(8)], tmp_path / "small.avi")
    patched = declare_jpeg((tmp_path / "small.avi").read_bytes(), b"\xff\xc0", 16000, 16000)
    (tmp_path / "big.avi").write_bytes(patched)
    line = one_line_refusal(run("poses", tmp_path / "big.avi", "-o", tmp_path / "c.json"))
    assert "frame 0 declares a 16000x16000 JPEG, more than its" in line, line


def test_defect06_an_image_of_another_format_under_an_image_name_is_refused(tmp_path):
    """OpenCV decodes by content: a .png holding a format whose header tomgs does not read goes unchecked."""
    import cv2

    folder = tmp_path / "frames"
    folder.mkdir()
    ok, data = cv2.imencode(".ppm", _texture(0))
    (folder / "00000.png").write_bytes(data.tobytes())
    line = one_line_refusal(run("poses", folder, "-o", tmp_path / "c.json"))
    assert "not a PNG, JPEG, BMP or TIFF image" in line, line


def test_defect06_tiff_sizes_are_checked(tmp_path):
    import cv2

    from tomgs.io.images import image_size

    ok, data = cv2.imencode(".tiff", _texture(0), [cv2.IMWRITE_TIFF_COMPRESSION, 1])  # uncompressed
    folder = tmp_path / "frames"
    folder.mkdir()
    path = folder / "00000.tiff"
    path.write_bytes(data.tobytes())
    assert image_size(path) == (64, 48, "tiff", 64 * 48 * 3)
    raw = bytearray(data.tobytes())
    assert raw[:2] == b"II"
    ifd = int.from_bytes(raw[4:8], "little")
    for k in range(int.from_bytes(raw[ifd:ifd + 2], "little")):
        entry = ifd + 2 + 12 * k
        if int.from_bytes(raw[entry:entry + 2], "little") == 256:  # ImageWidth
            raw[entry + 8:entry + 8 + (2 if raw[entry + 2] == 3 else 4)] = (16000).to_bytes(
                2 if raw[entry + 2] == 3 else 4, "little")
    path.write_bytes(bytes(raw))
    line = one_line_refusal(run("poses", folder, "-o", tmp_path / "c.json"))
    assert "declares a 16000x48 TIFF image, more than its" in line, line


# -- 9. a truncated MP4 became a shorter clip -----------------------------------------------------------------


def test_defect09_a_truncated_mp4_is_refused_not_read_short(tmp_path):
    """An MP4 cut short (its index at the front) read as 10 of its 32 frames, exit 0."""
    from tomgs.io import read_video, write_frames

    whole = tmp_path / "whole.mp4"
    write_frames([_texture(k) for k in range(32)], whole)
    assert len(read_video(whole)) == 32
    cut = tmp_path / "cut.mp4"
    data = whole.read_bytes()
    cut.write_bytes(data[:len(data) // 3])
    line = one_line_refusal(run("poses", cut, "-o", tmp_path / "c.json"))
    assert "index lists 32 frames but the file holds" in line and "truncated" in line, line


# -- 7. SIGTERM left a render's temporary forever --------------------------------------------------------------


def _dead_pid() -> int:
    """The id of a process that has ended (and been reaped)."""
    import subprocess

    proc = subprocess.Popen(["true"])
    proc.wait()
    return proc.pid


def _long_scene(tmp_path) -> Path:
    cams = tiny_cameras(400)
    path = tmp_path / "long.ply"
    save_scene(path, tiny_model(200), cams, {"fps": 12.0})
    return path


def _signalled_render(tmp_path, name: str, signame: str, ignored: bool = False):
    """A render of a long scene into `tmp_path`/out/`name`, sent `signame` a few frames after it staged
    its output: (the process, its stderr, the output folder). The render starts with the stop signals
    at their defaults, whatever this test's starter set (nohup ignores SIGHUP, a shell's background
    job SIGINT), or with `signame` ignored."""
    import signal
    import subprocess
    import sys
    import time

    def dispositions():
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, signal.SIG_DFL)
        if ignored:
            signal.signal(getattr(signal, signame), signal.SIG_IGN)

    scene = _long_scene(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    proc = subprocess.Popen([sys.executable, "-m", "tomgs.cli", "render", str(scene), "-o", str(out / name), "-q",
                             "--device", "cpu"], stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env,
                            preexec_fn=dispositions)
    deadline = time.monotonic() + 120
    while not [p for p in out.iterdir() if p.name.endswith(".tmp")] and time.monotonic() < deadline:
        time.sleep(0.05)
    staged = [p for p in out.iterdir() if p.name.endswith(".tmp")]
    assert staged, "the render never staged its output"
    time.sleep(0.3)  # a few frames in
    proc.send_signal(getattr(signal, signame))
    _, err = proc.communicate(timeout=120)
    return proc, err, out


@pytest.mark.parametrize("name, signame", [("r.mp4", "SIGTERM"), ("frames", "SIGTERM"), ("r.mp4", "SIGHUP"),
                                           ("frames", "SIGINT")])
def test_defect07_sigterm_to_a_render_leaves_no_temporary_and_says_so(name, signame, tmp_path):
    """SIGTERM to a render left its temporary folder (.d.mp4.*.tmp/, or 10 MB of partial PNG frames);
    SIGHUP (a closed terminal) and SIGINT (Ctrl-C) take the same way out."""
    import signal

    proc, err, out = _signalled_render(tmp_path, name, signame)
    assert proc.returncode == 128 + getattr(signal, signame), err
    assert err.strip().splitlines()[-1] == f"interrupted ({signame}): stopped, nothing half-written left", err
    assert list(out.iterdir()) == []


def test_a_render_started_under_nohup_goes_on_through_sighup(tmp_path):
    """A stop signal its starter ignores stays ignored (`nohup tomgs render ...` outlives its terminal):
    the render finishes and writes its whole video."""
    import av

    proc, err, out = _signalled_render(tmp_path, "r.mp4", "SIGHUP", ignored=True)
    assert proc.returncode == 0 and err == "", err
    assert [p.name for p in out.iterdir()] == ["r.mp4"]
    with av.open(str(out / "r.mp4")) as video:
        assert video.streams.video[0].frames == 400


def test_defect07_writers_remove_their_own_stale_temporaries_and_nothing_else(scene, tmp_path):
    """Only `fit` removed stale temporaries, and only files: render, demo, export and edit leave theirs too."""
    dead = _dead_pid()
    stale_video = tmp_path / f".r.mp4.{dead}.abcd1234.tmp"
    stale_video.mkdir()
    (stale_video / "out.mp4").write_bytes(b"x" * 1000)
    stale_frames = tmp_path / f".frames.{dead}.efgh5678.tmp"
    stale_frames.mkdir()
    (stale_frames / "00003.png").write_bytes(b"png")
    stale_file = tmp_path / f".x.splat.{dead}.ijkl9012.tmp"
    stale_file.write_bytes(b"half a splat")
    users = tmp_path / f".r.mp4.{dead}.mine.tmp"  # not what a writer stages: kept
    users.mkdir()
    (users / "notes.txt").write_text("mine")
    live = tmp_path / f".e.ply.{os.getpid()}.live0000.tmp"  # a running writer's (this process)
    live.write_bytes(b"being written")
    assert run("render", scene, "-o", tmp_path / "r.mp4", "--device", "cpu").exit_code == 0
    assert run("render", scene, "-o", tmp_path / "frames", "--device", "cpu").exit_code == 0
    assert run("export", scene, "-o", tmp_path / "x.splat", "--frame", "0").exit_code == 0
    assert run("edit", scene, "-o", tmp_path / "e.ply", "--translate", "0,0,1").exit_code == 0
    assert not stale_video.exists() and not stale_frames.exists() and not stale_file.exists()
    assert (users / "notes.txt").read_text() == "mine" and live.read_bytes() == b"being written"


# -- 8. two fits to one output ----------------------------------------------------------------------------------


def test_defect08_a_second_fit_of_an_output_is_refused_while_the_first_runs(clip, tmp_path):
    """Two fits to one output both reported success; the later silently replaced the earlier's files."""
    from tomgs.outputs import output_lock

    out = tmp_path / "s.ply"
    with output_lock(out):  # the first fit, writing s.ply (another open of the lock: as another process)
        line = one_line_refusal(run("fit", clip, "-o", out, "--iterations", "3", "--device", "cpu", "-y"))
        assert f"{out}: another tomgs fit (process {os.getpid()}) is writing it now" in line, line
        assert sorted(p.name for p in tmp_path.iterdir()) == [".s.lock"]
    assert list(tmp_path.iterdir()) == []  # released and removed
    result = run("fit", clip, "-o", out, "--iterations", "3", "--device", "cpu", "--poses", "identity")
    assert result.exit_code == 0, result.output
    assert not (tmp_path / ".s.lock").exists()  # a finished fit leaves no lock


def test_a_fit_of_another_format_of_a_running_fit_s_output_is_refused(clip, tmp_path):
    """Fits of s.ply and s.tsog both ran at once (their locks were .s.ply.lock and .s.tsog.lock) and
    wrote the same s.ckpt, s.csv and s.psnr.png: the lock covers every file of the stem."""
    from tomgs.outputs import output_lock

    with output_lock(tmp_path / "s.ply"):  # the first fit, writing s.ply
        line = one_line_refusal(run("fit", clip, "-o", tmp_path / "s.tsog", "--iterations", "3", "--device", "cpu"))
        assert line == (f"Error: {tmp_path / 's.tsog'}: another tomgs fit (process {os.getpid()}) is writing s.ply "
                        "now, whose log, plot and checkpoint are this output's too; wait for it to end, or choose "
                        "another output path"), line
        assert sorted(p.name for p in tmp_path.iterdir()) == [".s.lock"]


def test_defect11_a_scene_far_from_the_origin_says_its_frames_are_off(tmp_path):
    """A scene 1e5 units from the origin rendered with 5.6% image error in float32, silently."""
    model = tiny_model()
    shift = np.array([1e5, 0.0, 0.0])
    with torch.no_grad():
        model.means += torch.tensor(shift, dtype=torch.float32)
    cams = tiny_cameras()
    c2w = cams.c2w.copy()
    c2w[:, :3, 3] += shift
    far = tmp_path / "far.ply"
    near = Cameras.create(cams.c2w, intrinsics(400.0, W, H), W, H, frame_indices=cams.frame_indices)  # a long lens
    save_scene(far, model, Cameras.create(c2w, near.K, W, H, frame_indices=cams.frame_indices), {"fps": 12.0})
    result = run("render", far, "-o", tmp_path / "far.mp4", "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert "note: the scene lies 1e+05 units from the world's origin" in result.output, result.output
    save_scene(tmp_path / "near.ply", tiny_model(), near, {"fps": 12.0})
    result = run("render", tmp_path / "near.ply", "-o", tmp_path / "near.mp4", "--device", "cpu")
    assert result.exit_code == 0 and "note:" not in result.output, result.output
