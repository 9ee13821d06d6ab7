"""The `tomgs` command line: version, help, the demo render, and bad input (exit code 2, nothing written)."""

from __future__ import annotations

import re
import subprocess
import sys
import time

import cv2
import pytest
from click.testing import CliRunner

import tomgs
from tomgs.cli import main


def run(*args):
    return CliRunner().invoke(main, list(args), catch_exceptions=False)


def test_version_and_help():
    assert run("--version").output.strip().endswith(tomgs.__version__)
    help_text = run("--help").output
    for command in ("demo", "poses"):
        assert command in help_text


def test_every_option_of_every_command_says_what_it_does():
    """`-h` is where a newcomer learns an option: none is listed without a line of help (--sampling,
    --seed and demo's --frames once were)."""
    import click

    context = click.Context(main)
    bare = []

    def walk(command, path):
        if isinstance(command, click.Group):
            for name in command.list_commands(context):
                walk(command.get_command(context, name), [*path, name])
            return
        assert command.help, f"{' '.join(path)} has no help"
        bare.extend(f"{' '.join(path)} {'/'.join(p.opts)}" for p in command.params
                    if isinstance(p, click.Option) and not p.hidden and not (p.help or "").strip())

    walk(main, ["tomgs"])
    assert bare == []


def test_every_help_points_to_what_exists():
    """A help that names a README section names one the README has, a docs/ page one the repository
    has, and `jq .KEY` a key of the JSON (`edit --help` sent readers to a README "Editing" section
    that lives in docs/editing.md; `eval --help` to a `mean` that eval's JSON does not have)."""
    import click
    from pathlib import Path

    from tomgs.metrics import EvalReport

    root = Path(tomgs.__file__).parents[1]
    headings = [line.lstrip("#").strip() for line in (root / "README.md").read_text().splitlines()
                if line.startswith("#")]
    context = click.Context(main)
    texts = {}

    def walk(command, path):
        if isinstance(command, click.Group):
            for name in command.list_commands(context):
                walk(command.get_command(context, name), [*path, name])
        texts[" ".join(path)] = " ".join(run(*path, "--help").output.split())

    walk(main, [])
    for name, text in texts.items():
        for section in re.findall(r'README "([^"]+)"', text):
            assert any(section in heading for heading in headings), f"tomgs {name} --help: README {section!r}"
        for page in re.findall(r"\bdocs/[\w-]+\.md", text):
            assert (root / page).is_file(), f"tomgs {name} --help: {page}"
    report = EvalReport(frames=[0], psnr=[30.0], ssim=[0.9], width=4, height=4, seconds=1.0)
    for key in re.findall(r"jq \.(\w+)", texts["eval"]):
        assert key in report.to_dict(), f"tomgs eval --help: jq .{key}"


def test_console_script_entry_point():
    out = subprocess.run([sys.executable, "-m", "tomgs.cli", "--version"], capture_output=True, text=True, check=True)
    assert tomgs.__version__ in out.stdout


@pytest.mark.slow  # fresh Python processes, each importing torch
def test_cpu_only_machine_gets_no_cuda_driver_warning(tmp_path):
    """Warp's native library warns about the missing CUDA driver on fd 2; where torch sees no GPU the
    commands keep that noise out of their output (and still print their own errors there)."""
    import torch

    if torch.cuda.is_available():
        pytest.skip("a GPU machine: the warning is not printed there")
    out = subprocess.run([sys.executable, "-m", "tomgs.cli", "demo", "-o", str(tmp_path / "d.mp4"), "--frames", "2",
                          "--size", "32x18", "--device", "cpu"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "CUDA driver" not in out.stderr + out.stdout
    bad = subprocess.run([sys.executable, "-m", "tomgs.cli", "demo", "-o", str(tmp_path / "e.mp4"), "--frames", "0"],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "frames" in bad.stderr


def test_demo_writes_a_video(tmp_path):
    out = tmp_path / "demo.mp4"
    result = run("demo", "-o", str(out), "--frames", "6", "--size", "96x54", "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert "6 frames at 96x54" in result.output and "alive per frame" in result.output
    video = cv2.VideoCapture(str(out))
    assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == 6
    ok, frame = video.read()
    assert ok and frame.shape == (54, 96, 3) and frame.std() > 10  # a picture, not a blank
    assert sorted(p.name for p in tmp_path.iterdir()) == ["demo.mp4"]  # no temporary left behind


def test_demo_writes_png_frames_and_the_ball_moves(tmp_path):
    out = tmp_path / "frames"
    assert run("demo", "-o", str(out), "--frames", "5", "--size", "64x36", "--device", "cpu").exit_code == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == [f"{k:05d}.png" for k in range(5)]
    first, last = (cv2.imread(str(out / n)).astype(float) for n in (names[0], names[-1]))
    assert abs(first - last).mean() > 2.0


@pytest.mark.parametrize("args, message", [
    (["--size", "big"], "--size"),
    (["--size", "0x10"], "--size"),
    (["--device", "tpu"], "device"),
    (["-o", "{tmp}/out.gif"], "unknown output type"),
    (["-o", "{tmp}/missing/out.mp4"], "does not exist"),
])
def test_demo_bad_input(tmp_path, args, message):
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    result = CliRunner().invoke(main, ["demo", "--frames", "2", "--size", "32x18", *args] if "--size" not in args
                                else ["demo", "--frames", "2", *args])
    assert result.exit_code == 2, result.output
    assert message in result.output
    assert list(tmp_path.iterdir()) == []


def test_outputs_get_default_permissions(tmp_path):
    """Atomic writes go through private temporary names; the published output must not stay private."""
    import os

    from tomgs.io.plots import line_plot_png

    umask = os.umask(0)
    os.umask(umask)
    frames = tmp_path / "frames"
    assert run("demo", "-o", str(frames), "--frames", "2", "--size", "32x18", "--device", "cpu").exit_code == 0
    plot = line_plot_png(tmp_path / "p.png", {"a": ([0.0, 1.0], [0.0, 1.0])})
    assert frames.stat().st_mode & 0o777 == 0o777 & ~umask
    assert plot.stat().st_mode & 0o777 == 0o666 & ~umask


def test_example_files_ship_with_the_package():
    """The README's first command fits `tomgs example ball.mp4`: the clip, its masks and the Blender
    script are package data, found where the package is installed (tomgs/data), not in a checkout's
    assets/."""
    import importlib.metadata
    from pathlib import Path

    listing = run("example").output
    assert "ball.mp4" in listing and "ball_masks" in listing and "blender_softbody.py" in listing
    path = Path(run("example", "ball.mp4").output.strip())
    assert path.is_file() and path.parent == Path(tomgs.__file__).parent / "data"
    masks = Path(run("example", "ball_masks").output.strip())
    assert len(list(masks.glob("*.png"))) == 40
    assert CliRunner().invoke(main, ["example", "missing.mp4"]).exit_code == 2
    assert importlib.metadata.version("tomgs") == tomgs.__version__  # one version source: pyproject reads it


def test_progress_lines_keep_coming_while_the_work_is_silent(capsys):
    """Where stderr is not a terminal (a log, CI, `| tee`) progress is a line a phase starts and then one
    every interval from a thread, even while the work reports nothing (a long step, a compilation):
    the time so far, the phase, how far it is, what it said last and an ETA."""
    from tomgs.cli.common import ProgressLines

    lines = ProgressLines(interval=0.01)
    lines.update("training", 0.5, "iteration 5, PSNR 20.00 dB, 1,000 Gaussians")
    deadline = time.monotonic() + 30
    seen = ""
    while seen.count("\n") < 3 and time.monotonic() < deadline:
        time.sleep(0.02)
        seen += capsys.readouterr().err
    lines.close()
    rows = seen.splitlines()
    assert len(rows) >= 3, seen  # the first at the phase's start, the others from the thread alone
    when = r"[\d.]+ (s|min)"
    want = rf"\[ *{when}\] training 50%: iteration 5, PSNR 20.00 dB, 1,000 Gaussians, ETA {when}"
    assert all(re.fullmatch(want, row) for row in rows), rows


def test_out_of_memory_names_the_options_the_command_has():
    """An allocation that fails says how to give the command less to hold with its own options: render has
    --frames but no --max-side or --cap (a 480-byte cameras file asking for 16384x16384 frames ends there)."""
    import click

    from tomgs.cli import main
    from tomgs.cli.common import out_of_memory

    said = {}
    for name in ("render", "fit", "info"):
        with click.Context(main) as parent:
            command = main.get_command(parent, name)
            with click.Context(command, parent=parent):
                said[name] = out_of_memory(MemoryError("can't allocate 3221225472 bytes"))
    assert said["render"] == ("out of memory (can't allocate 3221225472 bytes); give the command less to hold: "
                              "fewer or smaller frames (--frames)")
    assert said["fit"].endswith("fewer or smaller frames (--frames, --max-side), or a lower --cap")
    assert said["info"].endswith("less to hold: fewer or smaller frames")
    assert out_of_memory(MemoryError()).startswith("out of memory (the allocator refused)")
