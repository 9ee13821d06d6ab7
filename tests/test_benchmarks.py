"""The benchmark suite (benchmarks/README.md): every script runs its `--smoke` mode (a tiny synthetic case
on the CPU) and writes its table, each profiler its CPU dry run, and the scripts import nothing of the
suite but `benchmarks.common`, which imports none of them: no import circles."""

from __future__ import annotations

import ast
import importlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
SCRIPTS = sorted(p.stem for p in BENCHMARKS.glob("*.py") if p.stem not in ("__init__", "common"))
COMMON = "benchmarks.common"


def module_name(path: Path) -> str:
    """benchmarks/profilers/raster.py -> benchmarks.profilers.raster (a package's __init__: the package)."""
    parts = path.relative_to(BENCHMARKS.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def suite_imports(path: Path) -> set[str]:
    """The modules of the suite that the file at `path` imports: absolute (`benchmarks.x`), relative
    (`.common`, `..common`) or, as a script run as a file imports its sibling, by bare name (`common`)."""
    package = module_name(path).rsplit(".", 1)[0] if path.stem != "__init__" else module_name(path)
    siblings = {p.stem for p in path.parent.glob("*.py")}
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.split(".")[0] == "benchmarks"}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[:len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            elif node.module.split(".")[0] == "benchmarks":
                target = node.module
            elif node.module.split(".")[0] in siblings:
                target = f"{package}.{node.module}"
            else:
                continue
            found.add(target)
    return found


def import_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """A cycle of `graph` (module -> the modules it imports) as a list of modules, or None."""
    state: dict[str, str] = {}

    def visit(node: str, path: list[str]):
        state[node] = "open"
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                return path[path.index(nxt):] + [nxt]
            if nxt not in state:
                cycle = visit(nxt, path + [nxt])
                if cycle:
                    return cycle
        state[node] = "done"
        return None

    for start in sorted(graph):
        if start not in state:
            cycle = visit(start, [start])
            if cycle:
                return cycle
    return None


def suite_graph() -> dict[str, set[str]]:
    return {module_name(p): suite_imports(p) for p in BENCHMARKS.rglob("*.py")}


def test_import_cycle_is_found():
    assert import_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert import_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None
    sample = BENCHMARKS / "profilers" / "raster.py"
    assert suite_imports(sample) == {COMMON}  # relative imports resolve to the module they name


def test_scripts_share_only_common_and_nothing_imports_in_a_circle():
    graph = suite_graph()
    assert {f"benchmarks.{name}" for name in SCRIPTS} <= set(graph)
    assert import_cycle(graph) is None
    assert graph[COMMON] == set(), "benchmarks.common imports a script of the suite"
    for module, imports in graph.items():
        if module != COMMON:
            assert imports <= {COMMON}, f"{module} imports {sorted(imports - {COMMON})}: share through common.py"


def report(folder: Path, name: str) -> dict:
    """The JSON a script wrote beside its table, after checking the table says what ran where."""
    text = (folder / f"{name}.md").read_text()
    assert f"command: `python -m benchmarks.{name} --smoke" in text and "commit:" in text and "device:" in text
    assert "|---" in text  # a table
    return json.loads((folder / f"{name}.json").read_text())["results"]


def check_davis(r):
    (row,) = r
    assert row["iterations"] == 40 and row["psnr"] > 15 and row["fps"] > 0 and row["fps_call"] > 0


def check_render_speed(r):
    assert r["gaussians"] > 0 and all(fps > 0 for fps in r["fps"].values())
    assert r["indexed_share"] >= r["alive_share"]  # the index lists a superset of what is alive


def check_alive_index(r):
    assert r["index"]["rows_share"] >= r["index"]["alive_share_measured"] > 0
    assert all(fps > 0 for fps in r["render_fps"].values())


def check_view_speed(r):
    assert r["updates"] == r["frames"] and r["splats_per_update_mean"] > 0  # every frame shown once


def check_bench_physics(r):
    assert [row["call"] for row in r] == ["first", "warm"] and all(row["inverted_frames"] == 0 for row in r)


def check_check_needles(r):
    assert max(max(row["grads"].values()) for row in r) < 1e-3  # the claim: within 1e-3 of the float64 reference


def check_interop(r):
    native = r["table"]["native scene"]
    assert native["gsply"]["positions"] == 0.0 and r["round trip"]["max pixel difference with --cameras"] == 0.0


def check_kill_resume(r):
    (kill,) = r["kills"]
    assert kill["psnr"] == kill["reference_psnr"] and not kill["stale_temporaries"]


def check_phone_video(r):
    (case,) = r
    assert case["iterations"] == 10 and case["psnr_end"] > 10 and case["peak_host_gib"] > 0


def check_phone(r):
    (row,) = r
    assert row["iterations"] == 30 and row["psnr"] > 10 and row["worst_frame_psnr"] <= row["psnr"]
    assert len(row["frame_psnr"]) == row["frames"] == 6 and row["first_step_s"] > 0
    assert row["curve"] and row["curve"][-1][3] == row["gaussians"]  # the log's last row is the scene's count


def check_bench_poses(r):
    clip, orbit = r
    assert clip["reproj_px"] < 1.0 and orbit["case"] == "orbit:10:64x36"


def check_phone_cameras(r):
    (row,) = r
    ours, ref, truth = row["tomgs"], row["reference"], row["truth"]
    assert ours["mode"] == "general" and abs(ours["focal"] / truth["focal"] - 1) < 0.05 and truth["path_error"] < 0.02
    if ref is not None:  # pycolmap installed: the reference solved the orbit and agrees
        assert ref["registered"] == ref["frames"] == 12 and abs(row["compare"]["focal_ratio"] - 1) < 0.05
        assert row["compare"]["rotation_error_deg"] < 1 and row["compare"]["path_error"] < 0.02


def check_shards(r):
    assert set(r["results"]) == {"half0", "half1", "full_2gpu"} and r["goal"] is not None


def check_compress(reports):
    (r,) = reports
    assert r["clip"] == "smoke" and r["gaussians"] == 3000 and r["frames"] == 4
    assert 0 < r["output_bytes"] < r["input_bytes"] and r["clip_jpeg_bytes"] > 0
    assert r["bits_per_pixel"] == 8 * r["output_bytes"] / (96 * 54 * 4)
    assert r["compress_seconds"] > 0 and r["load_seconds"] > 0
    assert set(r["image_bytes_per_gaussian"]) >= {"means_hi", "means_lo", "quats", "t_hi", "t_lo"}
    assert r["psnr_input"] > 28 and r["psnr_output"] > 28  # the clip is the input's own render as JPEGs (4:2:0)
    assert abs(r["psnr_drop"] - r["predicted_drop"]) < 0.1  # what `tomgs compress` checks predicts the loss


def check_safety_trials(r):
    (row,) = r
    assert row["command"] == "render" and row["broken"] == [] and sum(row["sigterm"].values()) == 1


def check_declared_sizes(r):
    assert [row["case"] for row in r] == ["png", "jpeg_progressive", "checkpoint"]
    assert all(row["said"].startswith("refused") and row["grew_mib"] < 64 for row in r)
def check_door(r):
    assert len(r["rows"]) == 10 and r["python_start_s"] > 0
    for row in r["rows"]:  # answered at once: one line, exit 2, no torch or Warp (numpy and PyAV only to read files)
        assert row["exit"] == 2 and row["lines"] == 1 and row["said"].startswith("Error:"), row
        assert not set(row["heavy"]) & {"torch", "warp", "cv2"}, row


def check_compact(r):
    assert [row["quality"] for row in r] == ["default", "max"]
    for row in r:
        assert row["gaussians"] > 0 and row["scene_bytes"] > 0 and row["psnr"] > 10 and 0 < row["ssim"] <= 1
        assert row["curve"] and row["curve"][-1][1] == row["gaussians"]  # the log's last row is the scene's count
        assert row["psnr_300s"] is None  # past the fit's end: no figure


def check_same_fit(r):
    assert len(r["params"]) == 8 and r["log"] and r["clip_psnr"]  # every parameter fingerprinted, the log read


def check_joint_step(r):
    assert r["version"] == "trainer" and r["steps"] == 4 and r["steps_per_s"] > 0 and r["shared"] == 400


def check_shards_plan(r):
    two = next(row for row in r["rows"] if row["ranks"] == 2)
    assert round(two["gap_db"], 2) == -0.61  # the measured gap of the two-H200 run it models (benchmarks/README.md)


@pytest.mark.parametrize("name", SCRIPTS)
def test_smoke(name, tmp_path):
    """`python -m benchmarks.<name> --smoke`, in this process; a script of the suite has a `main(argv)`."""
    importlib.import_module(f"benchmarks.{name}").main(["--smoke", "--out", str(tmp_path)])
    if name == "bench_raster":
        (table,) = tmp_path.glob("bench_raster_*.md")
        (data,) = tmp_path.glob("bench_raster_*.json")
        assert "command: `python -m benchmarks.bench_raster --smoke" in table.read_text()
        cases = json.loads(data.read_text())["cases"]
        assert len(cases) == 2 and all(c["sanity"]["img_max_abs"] < 1e-4 for c in cases)  # the float64 reference
        return
    checks = globals().get(f"check_{name}")
    result = report(tmp_path, name)
    if checks is not None:
        checks(result)


def test_profilers_dry_run(tmp_path, capsys):
    from benchmarks.common import smoke_clip_folder

    importlib.import_module("benchmarks.profilers.raster").main(
        ["--device", "cpu", "--size", "32x18", "--n", "200", "--iters", "2", "--host"])
    assert "wall" in capsys.readouterr().out
    clip = smoke_clip_folder(tmp_path, "clip")
    importlib.import_module("benchmarks.profilers.fit").main(
        [str(clip), "--device", "cpu", "--points-per-frame", "100", "--iters", "2"])
    assert "ms per iteration" in capsys.readouterr().out


@pytest.mark.parametrize("script", ["davis.py", "bench_raster.py"])
def test_scripts_run_as_files(script):
    """`python benchmarks/davis.py ...` and `python benchmarks/bench_raster.py ...` work as they always did:
    run as a file, a script finds common.py beside it, and nothing in benchmarks/ shadows the standard
    library (a `profile` folder there hid the stdlib module that Warp imports through cProfile)."""
    done = subprocess.run([sys.executable, str(BENCHMARKS / script), "--help"], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "--smoke" in done.stdout
