"""`tomgs edit`, `tomgs tets export|import` end to end on a tiny scene, and their bad input (exit 2, nothing written)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from scenes import object_scene
from tomgs.cli import main
from tomgs.io.scene import load_scene, save_scene
from tomgs.io.tets import load_tets, save_sequence, to_blender
from tomgs.render.sequence import render_sequence

BALL = "sphere:0,0,2.5,0.9"


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    model, cams, _ = object_scene()
    path = tmp_path_factory.mktemp("scene") / "ball.ply"
    save_scene(path, model, cams, {"fps": 10.0})
    return path


def pngs(folder):
    return [cv2.imread(str(p))[..., ::-1] for p in sorted(folder.iterdir())]


def test_help_has_examples():
    for command in (["edit"], ["tets", "export"], ["tets", "import"]):
        result = run(*command, "--help")
        assert result.exit_code == 0 and "Examples:" in result.output, command


def test_remove_writes_a_scene_that_render_and_info_open(tmp_path, scene):
    out = tmp_path / "clean.ply"
    result = run("edit", scene, "-o", out, "--select", BALL, "--remove", "--render", tmp_path / "clean")
    assert result.exit_code == 0, result.output
    assert "60 Gaussians removed; 208 Gaussians, 5 frames" in result.output
    edited = load_scene(out)
    assert len(edited.model) == 208 and edited.info["edits"][0]["remove"] is True and edited.info["fps"] == 10.0
    assert np.array_equal(edited.cameras.c2w, load_scene(scene).cameras.c2w)
    info = run("info", out)
    assert info.exit_code == 0 and "208 Gaussians, 5 frames" in info.output
    assert len(pngs(tmp_path / "clean")) == 5
    assert run("render", out, "-o", tmp_path / "again.mp4", "--device", "cpu").exit_code == 0


def test_duplicate_and_move(tmp_path, scene):
    out = tmp_path / "two.ply"
    result = run("edit", scene, "-o", out, "--select", BALL, "--duplicate", "0.8,0,0", "--scale", "0.5")
    assert result.exit_code == 0, result.output
    edited, original = load_scene(out).model, load_scene(scene).model
    assert len(edited) == 268 + 60 and torch.equal(edited.means[:268], original.means)
    assert torch.allclose(edited.log_scales[268:], original.log_scales[208:] + np.log(0.5), atol=1e-5)
    moved = run("edit", scene, "-o", tmp_path / "moved.ply", "--select", BALL, "--translate", "0,0.5,0",
                "--rotate", "0,0,90")
    assert moved.exit_code == 0, moved.output
    means = load_scene(tmp_path / "moved.ply").model.means
    assert torch.equal(means[:208], original.means[:208])
    assert not torch.allclose(means[208:], original.means[208:])


def test_keyframes_render_a_time_varying_edit(tmp_path, scene):
    keys = tmp_path / "keys.json"
    keys.write_text(json.dumps({"keyframes": [{"frame": 1, "translate": [0, 0, 0]},
                                              {"frame": 3, "translate": [0.6, 0, 0]}]}))
    result = run("edit", scene, "-o", tmp_path / "shot", "--select", BALL, "--keyframes", keys, "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert run("render", scene, "-o", tmp_path / "plain", "--device", "cpu").exit_code == 0
    shot, plain = pngs(tmp_path / "shot"), pngs(tmp_path / "plain")
    assert len(shot) == 5
    for k in (0, 1, 4):  # outside the window, and frame 1 is the identity key
        np.testing.assert_array_equal(shot[k], plain[k])
    assert np.abs(shot[3].astype(int) - plain[3]).max() > 60


def test_tets_export_and_import_equal_the_same_edit(tmp_path, scene):
    """Moving exported tets (as Blender would) and importing them gives the scene `tomgs edit` gives."""
    for flags in ([], ["--cage"]):
        out = tmp_path / ("cage" if flags else "gaussian")  # each variant writes its own files
        out.mkdir()
        tets = out / "tets.ply"
        result = run("tets", "export", scene, "-o", tets, "--select", BALL, *flags)
        assert result.exit_code == 0, result.output
        mesh = load_tets(tets)
        centre = 0.5 * (load_scene(scene).model.means[208:].min(0).values
                        + load_scene(scene).model.means[208:].max(0).values).detach().double().numpy()
        c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
        R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])  # 30 degrees about y
        moved = (mesh.vertices - centre) @ R.T + centre + [0.2, 0.0, 0.0]
        save_sequence(out / "one.npz", moved[None])
        result = run("tets", "import", scene, tets, out / "one.npz", "-o", out / "imported.ply")
        assert result.exit_code == 0, result.output
        result = run("edit", scene, "-o", out / "edited.ply", "--select", BALL, "--rotate", "0,30,0",
                     "--translate", "0.2,0,0")
        assert result.exit_code == 0, result.output
        a, b = load_scene(out / "imported.ply").model, load_scene(out / "edited.ply").model
        assert torch.allclose(a.means, b.means, atol=1e-4)
        ra, rb = (render_sequence(m.render_inputs(), load_scene(scene).cameras, [2]) for m in (a, b))
        assert (next(ra)[1] - next(rb)[1]).abs().max() < 0.02


def test_tets_import_renders_a_sequence(tmp_path, scene):
    tets = tmp_path / "cage.ply"
    assert run("tets", "export", scene, "-o", tets, "--select", BALL, "--cage", "--cell", "0.2").exit_code == 0
    mesh = load_tets(tets)
    falling = np.stack([mesh.vertices + [0.0, 0.15 * f, 0.0] for f in range(3)])
    save_sequence(tmp_path / "fall.npz", falling, frames=[1, 2, 3])
    result = run("tets", "import", scene, tets, tmp_path / "fall.npz", "-o", tmp_path / "shot", "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert "3 frames (1..3)" in result.output
    frames = pngs(tmp_path / "shot")
    assert len(frames) == 3 and np.abs(frames[2].astype(int) - frames[0]).max() > 60
    # a folder of PLY frames (what Blender writes) gives the same frames
    from plyfile import PlyData, PlyElement

    (tmp_path / "plys").mkdir()
    for f, row in enumerate(to_blender(falling)):
        v = np.empty(len(row), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
        v["x"], v["y"], v["z"] = row.T
        PlyData([PlyElement.describe(v, "vertex")]).write(str(tmp_path / "plys" / f"frame_{f + 1}.ply"))
    result = run("tets", "import", scene, tets, tmp_path / "plys", "-o", tmp_path / "shot2", "--device", "cpu")
    assert result.exit_code == 0, result.output
    save_sequence(tmp_path / "fall0.npz", falling)  # no 'frames': rows 0..2 are scene frames 0..2, as for the folder
    result = run("tets", "import", scene, tets, tmp_path / "fall0.npz", "-o", tmp_path / "shot3", "--device", "cpu")
    assert result.exit_code == 0, result.output
    for a, b in zip(pngs(tmp_path / "shot2"), pngs(tmp_path / "shot3"), strict=True):
        np.testing.assert_array_equal(a, b)


def _sequences(tmp_path, scene):
    """Bad sequences for the gaussian tets of the ball."""
    tets = tmp_path / "inputs" / "tets.ply"
    assert run("tets", "export", scene, "-o", tets, "--select", BALL).exit_code == 0
    rest = load_tets(tets).vertices
    save_sequence(tmp_path / "inputs" / "short.npz", rest[None, :-4])
    nan = np.stack([rest, rest])
    nan[1, 3] = np.nan
    np.savez(tmp_path / "inputs" / "nan.npz", vertices=to_blender(nan).astype(np.float32))
    flipped = rest.copy()
    flipped[[0, 1]] = flipped[[1, 0]]  # swapping two vertices of a tet turns it inside out
    save_sequence(tmp_path / "inputs" / "flipped.npz", np.stack([rest, flipped]))
    return tets


@pytest.mark.parametrize("case, args, message", [
    ("nothing", ["edit", "{scene}", "-o", "{out}/e.ply", "--select", "sphere:9,9,9,0.1", "--remove"], "matches nothing"),
    ("bad select", ["edit", "{scene}", "-o", "{out}/e.ply", "--select", "ball:1,2", "--remove"], "--select"),
    ("mask folder", ["edit", "{scene}", "-o", "{out}/e.ply", "--select", "mask:{inputs}/nomasks", "--remove"],
     "mask folder"),
    ("no edit", ["edit", "{scene}", "-o", "{out}/e.ply", "--select", BALL], "nothing to do"),
    ("translate", ["edit", "{scene}", "-o", "{out}/e.ply", "--translate", "1,2"], "--translate"),
    ("remove+move", ["edit", "{scene}", "-o", "{out}/e.ply", "--select", BALL, "--remove", "--scale", "2"], "--remove"),
    ("keys to ply", ["edit", "{scene}", "-o", "{out}/e.ply", "--keyframes", "{inputs}/k.json"], "time-varying"),
    ("render type", ["edit", "{scene}", "-o", "{out}/e.ply", "--select", BALL, "--remove", "--render", "{out}/e.gif"],
     "unknown output type"),
    ("export none", ["tets", "export", "{scene}", "-o", "{out}/t.ply", "--select", "box:50,50,50,60,60,60"], "matches nothing"),
    ("vertex count", ["tets", "import", "{scene}", "{tets}", "{inputs}/short.npz", "-o", "{out}/s"], "vertices, but"),
    ("nan", ["tets", "import", "{scene}", "{tets}", "{inputs}/nan.npz", "-o", "{out}/s"], "row 1: NaN"),
    ("inverted", ["tets", "import", "{scene}", "{tets}", "{inputs}/flipped.npz", "-o", "{out}/s"], "row 1: tet 0 is inverted"),
    ("one pose", ["tets", "import", "{scene}", "{tets}", "{inputs}/nan.npz", "-o", "{out}/s.ply"], "NaN"),
    ("not tets", ["tets", "import", "{scene}", "{scene}", "{inputs}/short.npz", "-o", "{out}/s"], "not a tomgs tets"),
])
def test_bad_input_exits_2_and_writes_nothing(tmp_path, scene, case, args, message):
    (tmp_path / "inputs").mkdir()
    (tmp_path / "out").mkdir()
    (tmp_path / "inputs" / "k.json").write_text('{"keyframes": [{"t": 0}, {"t": 1, "translate": [1, 0, 0]}]}')
    tets = _sequences(tmp_path, scene)
    result = run(*[a.format(inputs=tmp_path / "inputs", out=tmp_path / "out", scene=scene, tets=tets) for a in args])
    assert result.exit_code == 2, (case, result.output)
    assert message in result.output, (case, result.output)
    assert list((tmp_path / "out").iterdir()) == []


@pytest.fixture
def rigid_fall(monkeypatch):
    """A stand-in for tomgs.edit.physics (contract: EARTH_GRAVITY, simulate(rest [V,3], tets [T,4], SimConfig, device)
    -> [F,V,3] world axes): the body falls rigidly under gravity; records the configs it was given."""
    import dataclasses
    import sys
    import types

    @dataclasses.dataclass
    class SimConfig:
        frames: int = 80
        fps: float = 24.0
        gravity: tuple = (0.0, 9.81, 0.0)
        edge_compliance: float = 1e-3
        damping: float = 0.0
        initial_velocity: tuple = (0.0, 0.0, 0.0)
        initial_spin: tuple = (0.0, 0.0, 0.0)
        drop_height: float = 0.0

    def simulate(rest_vertices, tets, config, device="cpu"):
        calls.append((config, device, len(tets)))
        t = np.arange(config.frames)[:, None, None] / config.fps
        g = np.asarray(config.gravity)
        return rest_vertices[None] - config.drop_height * g / np.linalg.norm(g) + 0.5 * g * t ** 2

    def simulate_with_stats(rest_vertices, tets, config, device="cpu"):
        vertices = simulate(rest_vertices, tets, config, device)
        inverted = list(range(config.frames)) if config.edge_compliance > 0.1 else []  # "too soft": inverts
        return types.SimpleNamespace(vertices=vertices, inverted_frames=inverted,
                                     min_volume_ratio=-0.5 if inverted else 1.0)

    calls = []
    module = types.ModuleType("tomgs.edit.physics")
    module.SimConfig, module.simulate, module.simulate_with_stats = SimConfig, simulate, simulate_with_stats
    module.EARTH_GRAVITY = 9.81
    monkeypatch.setitem(sys.modules, "tomgs.edit.physics", module)
    return calls


def test_simulate_writes_a_replayable_shot(tmp_path, scene, rigid_fall):
    out = tmp_path / "fall.npz"
    result = run("simulate", scene, "--select", BALL, "--drop", "0.3", "--stiffness", "500", "--frames", "4",
                 "--size", "2", "-o", out, "--render", tmp_path / "shot", "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert "4 frames of 60 Gaussians" in result.output and "4 frames (0..3)" in result.output
    config, device, _ = rigid_fall[0]
    assert device == "cpu" and config.frames == 4 and config.fps == 10.0 and config.drop_height == 0.3
    assert config.edge_compliance == pytest.approx(1 / 500)
    extent = float(np.ptp(load_scene(scene).model.means[208:].detach().numpy(), axis=0).max())
    assert config.gravity == pytest.approx((0.0, 9.81 * extent / 2, 0.0))  # a 2 m object's fall
    cage = load_tets(tmp_path / "fall.cage.ply")
    assert cage.kind == "cage" and cage.gaussians.tolist() == list(range(208, 268))
    with np.load(out) as data:
        assert data["vertices"].shape == (4, len(cage.vertices), 3) and data["frames"].tolist() == [0, 1, 2, 3]
    shot = pngs(tmp_path / "shot")
    assert len(shot) == 4 and np.abs(shot[3].astype(int) - shot[0]).max() > 60  # the ball fell
    replay = run("tets", "import", scene, tmp_path / "fall.cage.ply", out, "-o", tmp_path / "replay", "--device", "cpu")
    assert replay.exit_code == 0, replay.output
    for a, b in zip(pngs(tmp_path / "replay"), shot, strict=True):
        assert np.abs(a.astype(int) - b).max() <= 1  # float32 on disk


def test_simulate_bad_input_writes_nothing(tmp_path, scene, rigid_fall):
    for args, message in ((["--frames", "9"], "the scene has 5 frames"), (["--spin", "1,2"], "--spin"),
                          (["--select", "sphere:9,9,9,0.1"], "matches nothing")):
        result = run("simulate", scene, "-o", tmp_path / "s.npz", *args)
        assert result.exit_code == 2 and message in result.output, (args, result.output)
    assert list(tmp_path.iterdir()) == [] and rigid_fall == []


def test_simulate_with_inverted_tets_fails_and_writes_nothing(tmp_path, scene, rigid_fall):
    # a shot whose cage turned a tet inside out would mirror the Gaussians bound to it: exit 2, no files
    result = run("simulate", scene, "--select", BALL, "--stiffness", "5", "--frames", "4", "-o", tmp_path / "s.npz",
                 "--render", tmp_path / "shot", "--device", "cpu")
    assert result.exit_code == 2 and "inside out in 4 frame(s), first frame 0" in result.output, result.output
    assert list(tmp_path.iterdir()) == [] and len(rigid_fall) == 1


@pytest.fixture(scope="module")
def layered(tmp_path_factory):
    """The ball alone (front.ply) and the wall alone (back.ply), the same cameras; back4.ply: the
    wall at 4 of the 5 frames, back_small.ply: at half size."""
    from tomgs.model import GaussianModel

    model, cams, ball = object_scene()
    folder = tmp_path_factory.mktemp("layered")
    params = model.parameters_by_name()
    paths = {}
    for name, rows, cameras in (("front", ball, cams), ("back", np.arange(ball[0]), cams),
                                ("back4", np.arange(ball[0]), cams[:4]),
                                ("back_small", np.arange(ball[0]), cams.resized(16, 12))):
        part = GaussianModel(**{k: v.detach()[torch.as_tensor(rows)].clone() for k, v in params.items()})
        paths[name] = folder / f"{name}.ply"
        save_scene(paths[name], part, cameras, {"fps": 10.0})
    return paths


def _check_over(shot, over, back):
    """`over`: the shot rendered --over the back scene; `shot`: alone (over black); `back`: the back
    scene alone. Where the shot is transparent the composite is the back scene; where it is opaque,
    not."""
    assert len(over) == len(shot) == len(back)
    clear = [s.max(-1) == 0 for s in shot]
    solid = [s[..., 0] > 150 for s in shot]
    assert sum(int(m.sum()) for m in clear) > 100 and sum(int(m.sum()) for m in solid) > 20
    for o, b, c, s in zip(over, back, clear, solid):
        assert np.abs(o.astype(int) - b)[c].max() <= 1
        if s.any():
            assert np.abs(o.astype(int) - b)[s].max(-1).mean() > 40


def test_over_composites_shots_over_a_background(tmp_path, layered, rigid_fall):
    front, back = layered["front"], layered["back"]
    assert run("render", back, "-o", tmp_path / "back", "--device", "cpu").exit_code == 0
    background = pngs(tmp_path / "back")
    for rendered in ("shot", "over"):
        extra = ["--over", back] if rendered == "over" else []
        result = run("simulate", front, "--select", BALL, "--drop", "0.3", "-o", tmp_path / f"{rendered}.npz",
                     "--render", tmp_path / f"sim_{rendered}", "--device", "cpu", *extra)
        assert result.exit_code == 0, result.output
    _check_over(pngs(tmp_path / "sim_shot"), pngs(tmp_path / "sim_over"), background)

    result = run("tets", "import", front, tmp_path / "shot.cage.ply", tmp_path / "shot.npz", "-o",
                 tmp_path / "imported", "--over", back, "--device", "cpu")
    assert result.exit_code == 0, result.output
    for a, b in zip(pngs(tmp_path / "imported"), pngs(tmp_path / "sim_over"), strict=True):
        assert np.abs(a.astype(int) - b).max() <= 1  # the replay, composited the same way

    for rendered in ("shot", "over"):
        extra = ["--over", back] if rendered == "over" else []
        result = run("edit", front, "-o", tmp_path / f"e_{rendered}.ply", "--select", BALL, "--translate",
                     "0.3,0,0", "--render", tmp_path / f"edit_{rendered}", "--device", "cpu", *extra)
        assert result.exit_code == 0, result.output
    _check_over(pngs(tmp_path / "edit_shot"), pngs(tmp_path / "edit_over"), background)


@pytest.mark.parametrize("back, message", [("back4", "has 5 frames (numbered 0..4) but the base scene has 4"),
                                           ("back_small", "is 32x24 but the base scene is 16x12")])
def test_over_mismatch_exits_2_and_writes_nothing(tmp_path, layered, rigid_fall, back, message):
    front, over = layered["front"], layered[back]
    out = tmp_path / "out"
    out.mkdir()
    tets = tmp_path / "cage.ply"
    assert run("tets", "export", front, "-o", tets, "--select", BALL, "--cage").exit_code == 0
    save_sequence(tmp_path / "seq.npz", np.stack([load_tets(tets).vertices] * 5))
    for args in (["simulate", front, "--select", BALL, "-o", out / "s.npz", "--render", out / "s"],
                 ["tets", "import", front, tets, tmp_path / "seq.npz", "-o", out / "t.mp4"],
                 ["edit", front, "-o", out / "e.ply", "--select", BALL, "--scale", "2", "--render", out / "e"]):
        result = run(*args, "--over", over, "--device", "cpu")
        assert result.exit_code == 2, (args, result.output)
        assert message in result.output and str(over) in result.output, result.output
        assert list(out.iterdir()) == [], args
    assert rigid_fall == []
