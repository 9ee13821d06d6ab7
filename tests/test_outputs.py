"""Outputs never destroy what tomgs did not write: existing files and folders are refused without
--overwrite (exit 2, nothing touched), every output path is checked before any work, temporary
files are private and cleaned on every exit path."""

from __future__ import annotations

import os
import re
import stat

import numpy as np
import pytest
from click.testing import CliRunner

from scenes import object_scene
from tomgs.cli import main
from tomgs.errors import InputError
from tomgs.io.scene import load_scene, save_scene
from tomgs.io.tets import save_sequence
from tomgs.io.writer import write_frames
from tomgs.outputs import atomic_file, check_file_output, remove_stale_temporaries, write_text

BALL = "sphere:0,0,2.5,0.9"


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    model, cams, _ = object_scene()
    path = tmp_path_factory.mktemp("scene") / "ball.ply"
    save_scene(path, model, cams, {"fps": 10.0})
    return path


def user_folder(path):
    """A folder of the user's: a document, a subfolder and a PNG that is not a frame."""
    path.mkdir()
    (path / "thesis.txt").write_text("years of work")
    (path / "photos").mkdir()
    (path / "photos" / "a.jpg").write_bytes(b"jpg")
    (path / "cover.png").write_bytes(b"png")
    return path


def snapshot(path):
    return sorted((str(p.relative_to(path)), p.read_bytes() if p.is_file() else None) for p in path.rglob("*"))


def tets_args(scene, tmp_path):
    """Arguments of `tets import` with a one-frame sequence of the ball's tets."""
    from tomgs.io.tets import load_tets

    tets = tmp_path / "tets.ply"
    assert run("tets", "export", scene, "-o", tets, "--select", BALL).exit_code == 0
    vertices = load_tets(tets).vertices
    save_sequence(tmp_path / "seq.npz", np.stack([vertices, vertices + [0.1, 0, 0]]))
    return ["tets", "import", scene, tets, tmp_path / "seq.npz"]


# The commands that render frames: each gets an existing folder of the user's as its output.
RENDERERS = {
    "render": lambda scene, tmp, out: ["render", scene, "-o", out],
    "demo": lambda scene, tmp, out: ["demo", "-o", out, "--frames", "2", "--size", "32x24"],
    "edit --render": lambda scene, tmp, out: ["edit", scene, "-o", tmp / "e.ply", "--select", BALL,
                                              "--translate", "0.1,0,0", "--render", out],
    "tets import": lambda scene, tmp, out: [*tets_args(scene, tmp), "-o", out],
    "simulate --render": lambda scene, tmp, out: ["simulate", scene, "--select", BALL, "-o", tmp / "s.npz",
                                                  "--frames", "2", "--render", out],
}


@pytest.mark.parametrize("command", sorted(RENDERERS))
def test_an_existing_folder_is_never_emptied(command, scene, tmp_path):
    docs = user_folder(tmp_path / "mydocs")
    before = snapshot(docs)
    result = run(*RENDERERS[command](scene, tmp_path, docs))
    assert result.exit_code == 2, result.output
    assert "not empty" in result.output and "--overwrite" in result.output
    assert snapshot(docs) == before
    assert not (tmp_path / "e.ply").exists() and not (tmp_path / "s.npz").exists()  # refused before any work


def test_overwrite_replaces_only_frames_in_a_folder(scene, tmp_path):
    docs = user_folder(tmp_path / "mydocs")
    (docs / "00099.png").write_bytes(b"an earlier render's frame")
    result = run("render", scene, "-o", docs, "--overwrite")
    assert result.exit_code == 0, result.output
    names = sorted(p.name for p in docs.iterdir())
    assert names == ["00000.png", "00001.png", "00002.png", "00003.png", "00004.png", "cover.png", "photos",
                     "thesis.txt"]
    assert (docs / "thesis.txt").read_text() == "years of work" and (docs / "photos" / "a.jpg").exists()
    assert not [p for p in docs.iterdir() if p.name.endswith(".tmp")]


def test_demo_into_the_current_folder_keeps_it(scene, tmp_path, monkeypatch):
    """`tomgs demo -o .` used to empty the current folder, the input scene included."""
    here = tmp_path / "work"
    here.mkdir()
    (here / "ball.ply").write_bytes(scene.read_bytes())
    monkeypatch.chdir(here)
    before = snapshot(here)
    result = run("demo", "-o", ".", "--frames", "2", "--size", "32x24")
    assert result.exit_code == 2 and "not empty" in result.output
    assert snapshot(here) == before
    result = run("demo", "-o", ".", "--frames", "2", "--size", "32x24", "-y")
    assert result.exit_code == 0, result.output
    assert (here / "ball.ply").read_bytes() == scene.read_bytes() and (here / "00001.png").exists()


def test_an_empty_folder_is_written_into(scene, tmp_path):
    (tmp_path / "frames").mkdir()
    assert run("render", scene, "-o", tmp_path / "frames").exit_code == 0
    assert len(list((tmp_path / "frames").iterdir())) == 5


def existing_file_commands(scene, tmp_path, out):
    """Every command that writes one file, with `out` (an existing file) as that file."""
    video = tmp_path / "clip"
    assert run("render", scene, "-o", video).exit_code == 0
    return {
        "render": ["render", scene, "-o", out.with_suffix(".mp4")],
        "demo": ["demo", "-o", out.with_suffix(".mp4"), "--frames", "2", "--size", "32x24"],
        "poses": ["poses", video, "-o", out.with_suffix(".json"), "--method", "identity"],
        "eval --json": ["eval", scene, video, "--json", out.with_suffix(".json")],
        "info --plot": ["info", scene, "--plot", out.with_suffix(".png")],
        "edit": ["edit", scene, "-o", out.with_suffix(".ply"), "--select", BALL, "--remove"],
        "tets export": ["tets", "export", scene, "-o", out.with_suffix(".ply"), "--select", BALL],
        "simulate": ["simulate", scene, "-o", out.with_suffix(".npz"), "--select", BALL, "--frames", "2"],
    }


def test_an_existing_file_is_refused_then_replaced_with_overwrite(scene, tmp_path):
    out = tmp_path / "mine"
    commands = existing_file_commands(scene, tmp_path, out)
    for name, args in commands.items():
        target = [a for a in args if str(a).startswith(str(out))][0]
        target.write_bytes(b"the user's file")
        result = run(*args)
        assert result.exit_code == 2, (name, result.output)
        assert "exists" in result.output and "--overwrite" in result.output, (name, result.output)
        assert target.read_bytes() == b"the user's file", name
        result = run(*args, "--overwrite")
        assert result.exit_code == 0, (name, result.output)
        assert target.read_bytes() != b"the user's file", name
        target.unlink()


def test_simulate_refuses_an_existing_cage_file(scene, tmp_path):
    (tmp_path / "s.cage.ply").write_bytes(b"mine")
    result = run("simulate", scene, "-o", tmp_path / "s.npz", "--select", BALL, "--frames", "2")
    assert result.exit_code == 2 and "s.cage.ply exists" in result.output
    assert (tmp_path / "s.cage.ply").read_bytes() == b"mine" and not (tmp_path / "s.npz").exists()


@pytest.mark.parametrize("case", ["folder where a file goes", "under a regular file", "missing folder"])
def test_bad_output_paths_fail_before_any_work(case, scene, tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    (tmp_path / "dir.mp4").mkdir()
    (tmp_path / "dir.ply").mkdir()
    (tmp_path / "dir.json").mkdir()
    outputs = {"folder where a file goes": ("dir", "is a (folder|directory)"),  # click says "directory"
               "under a regular file": ("a-file/x", "is a file"), "missing folder": ("nowhere/x", "does not exist")}
    stem, message = outputs[case]
    for args in (["render", scene, "-o", f"{stem}.mp4"], ["edit", scene, "-o", f"{stem}.ply", "--select", BALL,
                                                          "--remove"],
                 ["eval", scene, tmp_path / "nothing-read", "--json", f"{stem}.json"],
                 ["tets", "export", scene, "-o", f"{stem}.ply"], ["poses", "nothing-read", "-o", f"{stem}.json"]):
        args = [tmp_path / a if isinstance(a, str) and a.startswith(stem) else a for a in args]
        result = run(*args)
        assert result.exit_code == 2, (args, result.output)
        assert re.search(message, result.output), (args, result.output)
        assert result.exception is None or isinstance(result.exception, SystemExit)


def test_unwritable_folders_fail_before_any_work(scene, tmp_path):
    """/proc refuses new files even to root (os.access says yes there); a chmod'ed folder does for others."""
    targets = [os.path.join("/proc", "tomgs-out.mp4")]
    if os.geteuid() != 0:
        locked = tmp_path / "locked"
        locked.mkdir()
        locked.chmod(stat.S_IRUSR | stat.S_IXUSR)
        targets.append(str(locked / "out.mp4"))
    for target in targets:
        for args in (["render", scene, "-o", target], ["demo", "-o", target],
                     ["edit", scene, "-o", target[:-4] + ".ply", "--select", BALL, "--remove"]):
            result = run(*args)
            assert result.exit_code == 2, (args, result.output)
            assert "cannot write" in result.output, (args, result.output)


def test_temporary_files_are_never_followed_through_planted_links(scene, tmp_path):
    """The old predictable names (`.NAME.<pid>.tmp`, `NAME.tmp`) planted as links to a victim."""
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    for name in ("scene.ply", "cams.json"):
        for planted in (f".{name}.{os.getpid()}.tmp", f"{name}.tmp"):
            (tmp_path / planted).symlink_to(victim)
    loaded = load_scene(scene)
    save_scene(tmp_path / "scene.ply", loaded.model, loaded.cameras, {})
    loaded.cameras.save(tmp_path / "cams.json")
    assert victim.read_text() == "precious"
    assert load_scene(tmp_path / "scene.ply").cameras.width == loaded.cameras.width


def test_atomic_file_cleans_up_on_every_exit_path(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    for error in (RuntimeError("disk"), KeyboardInterrupt()):
        with pytest.raises(type(error)):
            with atomic_file(target) as tmp:
                tmp.write_text("half")
                raise error
        assert target.read_text() == "old"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]
    write_text(target, "new")
    assert target.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]
    assert stat.S_IMODE(target.stat().st_mode) == 0o666 & ~_umask()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_stale_temporaries_are_removed_but_fresh_ones_kept(tmp_path):
    out = tmp_path / "scene.ply"
    stale, fresh = tmp_path / ".scene.ply.abc.tmp", tmp_path / ".scene.ply.def.tmp"
    other = tmp_path / ".other.ply.abc.tmp"
    for p in (stale, fresh, other):
        p.write_text("x")
    os.utime(stale, (0, 0))
    os.utime(other, (0, 0))
    assert remove_stale_temporaries(out) == [stale]
    assert fresh.exists() and other.exists()


def test_library_writers_refuse_to_replace_without_overwrite(tmp_path):
    frame = np.zeros((4, 4, 3), np.uint8)
    (tmp_path / "f").mkdir()
    (tmp_path / "f" / "notes.txt").write_text("keep")
    with pytest.raises(InputError, match="not empty"):
        write_frames([frame], tmp_path / "f")
    assert write_frames([frame], tmp_path / "f", overwrite=True) == 1
    assert (tmp_path / "f" / "notes.txt").read_text() == "keep"
    (tmp_path / "v.mp4").write_bytes(b"mine")
    with pytest.raises(InputError, match="exists"):
        write_frames([frame], tmp_path / "v.mp4")
    with pytest.raises(InputError, match="exists"):
        check_file_output(tmp_path / "v.mp4")
    dangling = tmp_path / "link.json"
    dangling.symlink_to(tmp_path / "missing")
    with pytest.raises(InputError, match="not a regular file"):
        check_file_output(dangling, overwrite=True)


def test_fit_refuses_to_replace_its_outputs_before_reading_the_video(tmp_path):
    """`fit -o x.ply` used to delete an existing x.csv and replace x.psnr.png without a word."""
    for name in ("x.ply", "x.csv", "x.psnr.png"):
        for stale in tmp_path.iterdir():
            stale.unlink()
        (tmp_path / name).write_bytes(b"the user's")
        result = run("fit", tmp_path / "no-such-video.mp4", "-o", tmp_path / "x.ply")
        assert result.exit_code == 2, result.output
        assert f"{name} exists" in result.output and "--overwrite" in result.output, result.output
        assert (tmp_path / name).read_bytes() == b"the user's"
    result = run("fit", tmp_path / "no-such-video.mp4", "-o", "/proc/x.ply")
    assert result.exit_code == 2 and "cannot write" in result.output, result.output


@pytest.mark.slow  # fresh Python processes, each importing torch
def test_stdout_carries_results_only(scene, tmp_path):
    """Progress bars and notes go to stderr; `--json -` makes stdout pure JSON; -q silences stderr."""
    import json
    import subprocess
    import sys

    def tomgs(*args):
        return subprocess.run([sys.executable, "-m", "tomgs.cli", *map(str, args)], capture_output=True, text=True)

    frames = tmp_path / "frames"
    out = tomgs("render", scene, "-o", frames, "--device", "cpu")
    assert out.returncode == 0 and out.stdout.startswith(f"{frames}: 5 frames") and "render" in out.stderr
    out = tomgs("poses", frames, "-o", tmp_path / "cams.json", "--method", "identity", "--json", "-")
    assert out.returncode == 0 and json.loads(out.stdout)["frames"] == 5
    out = tomgs("eval", scene, frames, "--json", "-", "--device", "cpu")
    assert out.returncode == 0 and len(json.loads(out.stdout)["per_frame"]) == 5 and "frame" in out.stderr
    out = tomgs("-q", "render", scene, "-o", tmp_path / "again", "--device", "cpu")
    assert out.returncode == 0 and out.stderr == "" and "5 frames" in out.stdout
    out = tomgs("render", scene, "-o", tmp_path / "after", "--device", "cpu", "-q")  # after the command too
    assert out.returncode == 0 and out.stderr == "" and "5 frames" in out.stdout
    for args in (["-q", "-v", "info", scene], ["fit", scene, "-q", "-v"]):
        out = tomgs(*args)
        assert out.returncode == 2 and "contradict" in out.stderr
    out = tomgs("info", scene, "-v")  # -v shows training rows: only the commands that train offer it
    assert out.returncode == 2 and "No such option" in out.stderr
