"""Mistakes are answered at the door: the common ones get one line and exit 2 before torch, Warp, OpenCV
or numpy is imported (each command runs in a process where importing them fails; a mistake that can only
be seen in a file's contents may import what reads them: PyAV for a video's index, numpy for a scene's
cameras), and `tomgs eval` refuses a video that is not its scene's, naming what differs, unless asked to
compare anyway."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from scenes import object_scene
from tomgs.cli import main
from tomgs.data import example_file
from tomgs.io.scene import save_scene
from tomgs.io.video import clip_record, read_video
from tomgs.io.writer import write_frames

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "warp", "cv2", "numpy", "av")
# the CLI in a process where importing the packages named in TOMGS_REFUSE raises: a check that needs one
# fails with a traceback
GUARDED = """
import os
import sys

class Refuse:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in os.environ["TOMGS_REFUSE"].split(","):
            raise ImportError(f"{name} imported before the inputs were checked")

sys.meta_path.insert(0, Refuse())
sys.argv[0] = "tomgs"
from tomgs.cli import main
main()
"""


def at_the_door(*args, cwd, allowed=()):
    """The CLI run with `args` in a process where importing a HEAVY package not in `allowed` fails."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (str(ROOT), os.environ.get("PYTHONPATH")))),
           "CUDA_VISIBLE_DEVICES": "",  # no GPU visible, whatever the machine has
           "TOMGS_REFUSE": ",".join(p for p in HEAVY if p not in allowed)}
    return subprocess.run([sys.executable, "-c", GUARDED, *map(str, args)], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=120)


def frames_of(kind: str, count: int, width: int, height: int) -> np.ndarray:
    """uint8 [count, height, width, 3]: smooth frames that a video codec keeps ("ramp", or its mirror "flipped")."""
    y, x = np.meshgrid(np.linspace(0, 1, height), np.linspace(0, 1, width), indexing="ij")
    out = []
    for k in range(count):
        image = np.stack([x, y, np.full_like(x, k / count)], axis=2) * 200 + 20
        out.append(image[:, ::-1] if kind == "flipped" else image)
    return np.stack(out).astype(np.uint8)


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    """A scene fitted (as far as eval can tell) on clip a.mp4, and clips that are not a.mp4."""
    folder = tmp_path_factory.mktemp("door")
    clips = {"a": ("ramp", 6, 32, 24), "longer": ("ramp", 8, 32, 24), "larger": ("ramp", 6, 64, 48),
             "other": ("flipped", 6, 32, 24), "wide": ("ramp", 6, 48, 24),
             "shorter": ("ramp", 4, 32, 24)}
    for name, (kind, count, width, height) in clips.items():
        write_frames(frames_of(kind, count, width, height), folder / f"{name}.mp4", fps=10.0)
    model, cams, _ = object_scene(frames=6)
    save_scene(folder / "scene.ply", model, cams, {"clip": clip_record(read_video(folder / "a.mp4"))})
    (folder / "taken.ply").write_bytes(b"the user's")
    return folder


MISTAKES = {
    "path typo": (["fit", "clip.mpp4", "-o", "s.ply"], "clip.mpp4 does not exist"),
    "wrong type": (["render", "{clip}", "-o", "out.mp4"], "is a video, not a scene"),
    "missing -o": (["fit", "{clip}"], "Missing option '-o'"),
    "existing output": (["fit", "{clip}", "-o", "taken.ply"], "taken.ply exists"),
    "bad range": (["fit", "{clip}", "-o", "s.ply", "--frames", "0:x"], "bad frame range '0:x'"),
    "0-frame range": (["fit", "{clip}", "-o", "s.ply", "--frames", "40:50"], "selects no frames"),
    "wrong video for eval": (["eval", "scene.ply", "longer.mp4"], "longer.mp4 has 8 frames, the scene's clip had 6"),
    "cuda without a GPU": (["fit", "{clip}", "-o", "s.ply", "--device", "cuda"], "no CUDA GPU"),
    "bad select": (["edit", "scene.ply", "-o", "e.ply", "--select", "box:1,2", "--remove"], "box takes 6"),
    "unknown extension": (["render", "scene.ply", "-o", "out.xyz"], "unknown output type '.xyz'"),
    "eval: missing video": (["eval", "scene.ply", "nope.mp4"], "nope.mp4 does not exist"),
    "export: unknown extension": (["export", "scene.ply", "-o", "out.xyz", "--frame", "0"], "unknown format '.xyz'"),
    "export: no moment": (["export", "scene.ply", "-o", "out.ply"], "give the moment to export"),
    "export: nothing to write": (["export", "scene.ply"], "give -o OUT"),
    "poses: existing output": (["poses", "{clip}", "-o", "taken.ply"], "taken.ply exists"),
    "info: plot not a PNG": (["info", "scene.ply", "--plot", "out.jpg"], "the plot is a PNG"),
    "compress: not a scene": (["compress", "scene.ply", "-o", "out.xyz"], "a compressed scene is a .tsog"),
    "compress: existing output": (["compress", "scene.ply", "-o", "taken.ply"], "taken.ply exists"),
    "tets export: existing output": (["tets", "export", "scene.ply", "-o", "taken.ply"], "taken.ply exists"),
    "tets import: no tets file": (["tets", "import", "scene.ply", "no.ply", "no.npz", "-o", "x.mp4"],
                                  "no.ply does not exist"),
    "tets export: bad select": (["tets", "export", "scene.ply", "-o", "t.ply", "--select", "box:1"], "box takes 6"),
    "simulate: bad select": (["simulate", "scene.ply", "-o", "s.npz", "--select", "box:1"], "box takes 6"),
    "simulate: not a sequence": (["simulate", "scene.ply", "-o", "out.txt"], "an .npz"),
    "view: missing scene": (["view", "nope.ply"], "scene file nope.ply does not exist"),
    "demo: unknown extension": (["demo", "-o", "out.xyz"], "unknown output type '.xyz'"),
    "output is the input": (["edit", "scene.ply", "-o", "scene.ply", "--translate", "1,0,0"],
                            "Error: -o scene.ply is the input SCENE: writing it"),  # the path named once
    "example: unknown name": (["example", "nope.mp4"], "no example file 'nope.mp4'"),
}


# what a mistake seen only in a file's contents imports to read them
READERS = {"0-frame range": ("av",), "wrong video for eval": ("av", "numpy")}


@pytest.mark.parametrize("mistake", list(MISTAKES))
def test_a_mistake_is_one_line_and_exit_2_before_anything_heavy_is_imported(mistake, clips):
    args, message = MISTAKES[mistake]
    args = [a.replace("{clip}", str(example_file("ball.mp4"))) for a in args]
    before = sorted(p.name for p in clips.iterdir())
    done = at_the_door(*args, cwd=clips, allowed=READERS.get(mistake, ()))
    assert done.returncode == 2, done.stderr
    assert len(done.stderr.splitlines()) == 1 and done.stderr.startswith("Error:"), done.stderr
    assert message in done.stderr, done.stderr
    assert done.stdout == "" and sorted(p.name for p in clips.iterdir()) == before


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.mark.parametrize("video, differs", [
    ("longer.mp4", "longer.mp4 has 8 frames, the scene's clip had 6"),
    ("larger.mp4", "larger.mp4 is 64x48, the scene's clip was 32x24"),
    ("other.mp4", "6 of the scene's 6 frames differ from other.mp4's"),
])
def test_eval_refuses_another_clip_naming_what_differs_unless_forced(clips, video, differs):
    refused = run("eval", clips / "scene.ply", clips / video, "--device", "cpu")
    assert refused.exit_code == 2 and differs in refused.output and "--force" in refused.output, refused.output
    forced = run("eval", clips / "scene.ply", clips / video, "--device", "cpu", "--force")
    assert forced.exit_code == 0 and f"compared anyway (--force): {differs}" in forced.output, forced.output


def test_eval_of_the_scene_s_own_clip_says_nothing_of_differences(clips):
    result = run("eval", clips / "scene.ply", clips / "a.mp4", "--device", "cpu")
    assert result.exit_code == 0 and "compared anyway" not in result.output, result.output


@pytest.mark.parametrize("video, impossible, forced", [
    ("wide.mp4", "48x24", "wide.mp4's 48x24 frames resized to the scene's 32x24"),
    ("shorter.mp4", "shorter.mp4 has 4 frames", "compared the 4 of the scene's 6 frames that shorter.mp4 has"),
])
def test_eval_forced_compares_what_can_be_compared_and_says_so(clips, video, impossible, forced):
    refused = run("eval", clips / "scene.ply", clips / video, "--device", "cpu")
    assert refused.exit_code == 2 and "cannot be compared" in refused.output and impossible in refused.output, \
        refused.output
    assert "--force to compare the frames both have" in refused.output, refused.output
    result = run("eval", clips / "scene.ply", clips / video, "--device", "cpu", "--force", "--json", "-")
    assert result.exit_code == 0 and forced in result.stderr, result.output
    assert json.loads(result.stdout)["frames"] == (4 if video == "shorter.mp4" else 6)


def test_eval_with_its_json_on_stdout_and_quiet_prints_nothing_else(clips):
    """With `--json -` the per-frame lines are notes on stderr: -q silences them."""
    result = run("-q", "eval", clips / "scene.ply", clips / "a.mp4", "--device", "cpu", "--json", "-")
    assert result.exit_code == 0 and result.stderr == "", result.stderr
    assert set(json.loads(result.stdout)) >= {"psnr", "ssim", "per_frame"}
