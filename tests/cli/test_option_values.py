"""Every numeric option of every command, given random and extreme values: the command ends with
exit 0, or with exit 2 and one line naming the option, never a traceback.

The options are found by walking the click commands, so an option added later is covered (and one
declared with click's own number types, whose refusal prints the usage text, fails the census).
Commands whose work on a tiny scene costs milliseconds (render, edit, export, tets export, compress)
run for real on every accepted value; the others (fit, poses, demo, simulate, tets import, view)
stop where their work would begin, and the value they were handed is checked to be in range.
"""

from __future__ import annotations

import math
import os

import click
import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tomgs.cli import main
from tomgs.cli.params import Colour, Number, Numbers, Size

EXTREMES = ["nan", "-nan", "inf", "-inf", "1e308", "-1e308", "1e-308", "5e-324", "-5e-324", "0", "-0", "0.0", "1",
            "-1", "0.5", str(2**31), str(2**63 - 1), str(2**63), str(2**64), str(2**70), f"-{2**70}", "1e6", "1e7",
            "16384", "16385", "65536", "1e400", "", " ", "abc", "0x10", "1_000", "1e", "--1", "٣", "1,2", "1,2,3",
            "1,2,3,4", "0,0,0", "nan,0,0", "1e308,1,1", "1x1", "16384x16384", "0x5", "5x99999", "1e3x2"]
RUNS = {"render", "edit", "export", "tets export", "compress"}  # cheap on a tiny scene: run for real


class Reached(Exception):
    """Where a heavy command's work would begin: the door let its values through."""


def numeric_options():
    """(command path, option name, its type) of every numeric option of every command."""
    found = []

    def walk(group, prefix):
        for name, command in sorted(group.commands.items()):
            if isinstance(command, click.Group):
                walk(command, prefix + [name])
                continue
            for param in command.params:
                kind = param.type
                numeric = isinstance(kind, (Number, Numbers, Size)) or isinstance(
                    kind, (click.types.IntParamType, click.types.FloatParamType))
                if numeric and isinstance(param, click.Option):
                    found.append((" ".join(prefix + [name]), max(param.opts, key=len), kind))
    walk(main, [])
    return found


OPTIONS = numeric_options()


def test_every_numeric_option_is_checked_by_the_cli_types():
    """No option falls back to click's own numbers (their refusal prints the usage text, unbounded)."""
    assert len(OPTIONS) >= 30
    loose = [(c, o) for c, o, kind in OPTIONS if not isinstance(kind, (Number, Numbers, Size))]
    assert loose == []


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A tiny scene (2 frames of 16x12), its tets and a one-frame vertex sequence, a tiny clip."""
    from tests.test_safety import tiny_cameras, tiny_model

    from tomgs.io.scene import save_scene

    root = tmp_path_factory.mktemp("inputs")
    scene = root / "s.ply"
    save_scene(scene, tiny_model(12), tiny_cameras(2), {"fps": 12.0})
    result = CliRunner().invoke(main, ["tets", "export", str(scene), "-o", str(root / "t.ply")])
    assert result.exit_code == 0, result.output
    from tomgs.io.tets import load_tets

    np.savez(root / "seq.npz", vertices=load_tets(root / "t.ply").vertices[None])
    clip = root / "clip.mp4"
    assert CliRunner().invoke(main, ["demo", "-o", str(clip), "--frames", "3", "--size", "16x12",
                                     "--device", "cpu"]).exit_code == 0
    out = root / "out"
    out.mkdir()
    return dict(scene=str(scene), tets=str(root / "t.ply"), seq=str(root / "seq.npz"), clip=str(clip), out=out)


def base_args(command: str, option: str, i: dict) -> list[str]:
    """A tiny run of `command` to which `option` is added."""
    o = i["out"]
    if command == "export" and option in ("--frame", "--time"):
        return ["export", i["scene"], "-o", f"{o}/x.splat", "-y"]
    return {
        "compress": ["compress", i["scene"], "-o", f"{o}/c.tsog", "-y"],
        "demo": ["demo", "-o", f"{o}/d.mp4", "-y", "--device", "cpu"],
        "edit": ["edit", i["scene"], "-o", f"{o}/e.ply", "--translate", "0,0,0.1", "-y"],
        "export": ["export", i["scene"], "-o", f"{o}/x.splat", "--frame", "0", "-y"],
        "fit": ["fit", i["clip"], "-o", f"{o}/f.ply", "-y", "--device", "cpu"],
        "poses": ["poses", i["clip"], "-o", f"{o}/p.json", "-y"],
        "render": ["render", i["scene"], "-o", f"{o}/r.mp4", "-y", "--device", "cpu"],
        "simulate": ["simulate", i["scene"], "-o", f"{o}/s.npz", "-y", "--device", "cpu"],
        "tets export": ["tets", "export", i["scene"], "-o", f"{o}/t.ply", "-y", "--cage"],
        "tets import": ["tets", "import", i["scene"], i["tets"], i["seq"], "-o", f"{o}/ti.mp4", "-y"],
        "view": ["view", i["scene"]],
    }[command]


@pytest.fixture
def stubs(monkeypatch):
    """The heavy commands stop where their work begins, raising Reached with what they were handed."""
    import tomgs.demo
    import tomgs.edit.cage
    import tomgs.io
    import tomgs.io.tets
    import tomgs.train
    from tomgs.train.multigpu import pool

    def reached(*args, **kwargs):
        raise Reached(args, kwargs)

    monkeypatch.setattr(tomgs.train, "fit", reached)
    monkeypatch.setattr(tomgs.io, "read_video", reached)
    monkeypatch.setattr(tomgs.demo, "demo_scene", reached)
    monkeypatch.setattr(tomgs.edit.cage, "simulate_selection", reached)
    monkeypatch.setattr(tomgs.io.tets, "load_tets", reached)
    monkeypatch.setattr(pool, "start", lambda world: None)
    try:
        import tomgs.viewer.server

        monkeypatch.setattr(tomgs.viewer.server, "open_viewer", reached)
    except ImportError:  # the [view] extra: `tomgs view` refuses at once without it
        pass


def finite_numbers(value) -> bool:
    """Every number in `value` (nested args, kwargs, a config) is finite."""
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, (list, tuple)):
        return all(finite_numbers(v) for v in value)
    if isinstance(value, dict):
        return all(finite_numbers(v) for v in value.values())
    if hasattr(value, "__dataclass_fields__"):
        return all(finite_numbers(getattr(value, k)) for k in value.__dataclass_fields__)
    return True


def check(command: str, option: str, value: str, inputs: dict) -> str:
    """Run `command` with `option value`; 'ran', 'reached' or 'refused', else an AssertionError."""
    args = base_args(command, option, inputs) + [f"{option}={value}"]
    result = CliRunner().invoke(main, args + ["-q"])
    if isinstance(result.exception, Reached):
        assert command not in RUNS
        assert finite_numbers(result.exception.args), (args, result.exception.args)
        return "reached"
    if result.exit_code == 0:
        return "ran"
    assert result.exit_code == 2, (args, result.exit_code, result.output, result.exception)
    assert isinstance(result.exception, SystemExit), (args, result.exception)
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error: "), (args, result.output)
    assert "Traceback" not in result.output
    return "refused"


@pytest.mark.parametrize("command, option", [(c, o) for c, o, _ in OPTIONS])
def test_every_numeric_option_at_its_extremes(command, option, inputs, stubs):
    outcomes = {value: check(command, option, value, inputs) for value in EXTREMES}
    assert outcomes["nan"] == outcomes["inf"] == outcomes["abc"] == "refused", outcomes


def option_values():
    number = st.one_of(
        st.floats(allow_nan=True, allow_infinity=True).map(repr),
        st.floats(width=32).map(str),
        st.integers(min_value=-2**80, max_value=2**80).map(str),
        st.integers(min_value=-5, max_value=20).map(str),
        st.sampled_from(EXTREMES),
        st.text(max_size=6),
    )
    return st.one_of(number, st.lists(number, min_size=1, max_size=4).map(",".join),
                     st.tuples(number, number).map("x".join))


@settings(max_examples=int(os.environ.get("TOMGS_OPTION_EXAMPLES", "800")), deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(which=st.sampled_from([(c, o) for c, o, _ in OPTIONS]), value=option_values())
def test_random_values_at_every_numeric_option(which, value, inputs, stubs):
    command, option = which
    if "\x00" in value:  # a command line cannot hold NUL
        return
    check(command, option, value, inputs)
