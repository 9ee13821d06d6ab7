"""The package's layering: what importing a module loads, its floors, and no import circle.

Each import check runs in a fresh interpreter (a subprocess), so that what this test process already
imported cannot hide a heavy import. The floor and circle checks read the source (no import runs):
every `import` and `from ... import` of a tomgs module, at module level and inside functions, is an
edge, and so is the package a module sits in (importing tomgs.io.video runs tomgs/io/__init__.py first).

The floors, lowest first: kernels import only constants; model, cameras, temporal and geometry import
no io, render, train or edit; io imports no render, train or edit; render no train or edit; train's
single-process modules no train.multigpu (only the api hands a fit to it). An import from a
lower floor up is an arrow up whether it sits at module level or inside a function, with one kind of
exception, each listed in DELEGATIONS: a public method of a lower floor's value type that hands the
reading of a file to the io module that owns the format (`Cameras.load` -> tomgs.io.cameras), imported
inside that method; the module it reaches imports nothing of the lower one (the circle check holds it).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "tomgs"


def modules() -> dict[str, Path]:
    """Every module of tomgs: dotted name -> file."""
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        found[name] = path
    return found


def loaded_by(statement: str) -> list[str]:
    """The modules that `statement` leaves in sys.modules, run in a fresh interpreter from the repo root."""
    code = f"import json, sys\n{statement}\nprint(json.dumps(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300,
                         env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.splitlines()[-1])


def heavy(loaded: list[str]) -> list[str]:
    return sorted({m.split(".")[0] for m in loaded} & {"torch", "warp", "numpy", "av", "PIL", "viser"})


def test_kernels_import_no_torch():
    """Kernels are Warp only: importing every kernels module loads Warp (and numpy) but never torch."""
    names = [m for m in modules() if m.startswith("tomgs.kernels")]
    loaded = loaded_by("\n".join(f"import {m}" for m in names))
    assert "warp" in loaded and "torch" not in loaded, heavy(loaded)


@pytest.mark.parametrize("module", [m for m in modules() if m.startswith("tomgs.kernels.")])
def test_each_kernels_module_imports_no_torch(module):
    assert "torch" not in loaded_by(f"import {module}")


def test_rank_pool_imports_nothing_heavy():
    """The CLI starts its ranks before its own imports: the pool module loads no torch, Warp or numpy."""
    loaded = loaded_by("from tomgs.train.multigpu import pool\nfrom tomgs.train import multigpu")
    assert heavy(loaded) == [], heavy(loaded)


@pytest.mark.parametrize("statement", ["import tomgs", "import tomgs.render", "import tomgs.train",
                                       "import tomgs.edit", "import tomgs.viewer", "import tomgs.errors"])
def test_packages_import_cheaply(statement):
    """Importing a package resolves its public names lazily: no torch, Warp, numpy, PyAV, Pillow or viser."""
    loaded = loaded_by(statement)
    assert heavy(loaded) == [], heavy(loaded)


def import_edges(path: Path, name: str, known: set[str]) -> set[tuple[str, str]]:
    """(tomgs module, where) for each import of module `name` (file `path`): `where` is the qualified
    name of the function or class the import sits in, '' at module level."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()

    def visit(node: ast.AST, where: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                visit(child, f"{where}.{child.name}" if where else child.name)
                continue
            visit(child, where)
            if isinstance(child, ast.Import):
                targets = [a.name for a in child.names]
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    parts = package.split(".")
                    base = ".".join(parts[: len(parts) - child.level + 1] + ([base] if base else []))
                # `from pkg import sub` imports the submodule pkg.sub when there is one
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in child.names]
            else:
                continue
            for target in targets:
                while target and target not in known:  # `import tomgs.x.y` of a name inside a module
                    target = target.rpartition(".")[0]
                while target:  # the module and every package above it run
                    if target != name and target != "tomgs":  # tomgs/__init__ imports only tomgs._lazy
                        found.add((target, where))
                    target = target.rpartition(".")[0]

    visit(ast.parse(path.read_text(), str(path)), "")
    return found


def imports_of(path: Path, name: str, known: set[str]) -> set[str]:
    """The tomgs modules that module `name` (file `path`) imports anywhere in its source."""
    return {target for target, _ in import_edges(path, name, known)}


def cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle of `graph` as [a, b, ..., a], or None (depth-first search)."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def import_graph() -> dict[str, set[str]]:
    known = modules()
    return {name: imports_of(path, name, set(known)) for name, path in known.items()}


def test_the_graph_sees_imports_inside_functions_and_packages():
    """The walk finds a function-level import, a `from pkg import module` and the package above."""
    graph = import_graph()
    assert "tomgs.errors" in graph["tomgs.io"]  # package __init__ at module level
    assert "tomgs.io" in graph["tomgs.io.scene"]  # the package a sibling sits in
    assert "tomgs.train.multigpu.launch" in graph["tomgs.train.api"]  # imported inside fit()
    assert cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert cycle({"a": {"b"}, "b": set()}) is None


def test_no_import_circle():
    """No module of tomgs imports, at any depth and at any level (module or function), itself."""
    assert cycle(import_graph()) is None


BASE = ("tomgs.model", "tomgs.cameras", "tomgs.temporal", "tomgs.geometry")
FLOORS = [  # (the modules of a floor, what they may not import, what of that they may)
    (("tomgs.constants",), ("tomgs",), ()),
    (("tomgs.kernels",), ("tomgs",), ("tomgs.kernels", "tomgs.constants")),
    (BASE, ("tomgs.io", "tomgs.render", "tomgs.train", "tomgs.edit"), ()),
    (("tomgs.io",), ("tomgs.render", "tomgs.train", "tomgs.edit"), ()),
    (("tomgs.render",), ("tomgs.train", "tomgs.edit"), ()),
    (("tomgs.train",), ("tomgs.train.multigpu",), ()),  # multigpu itself and the api aside (below)
]
ABOVE_TRAIN = ("tomgs.train.multigpu", "tomgs.train.api")  # a sharded fit's modules, and the fit that starts one
DELEGATIONS = {  # (lower module, its method, the io module it hands a file's reading to)
    ("tomgs.cameras", "Cameras.load", "tomgs.io.cameras"),
    ("tomgs.cameras", "Cameras.from_anycam", "tomgs.io.cameras"),
    ("tomgs.cameras", "Cameras.from_colmap", "tomgs.io.cameras"),
}


def within(module: str, prefixes) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def delegated(name: str, target: str, where: str) -> bool:
    """Whether `name` imports `target` (a module or a package above it) as one of DELEGATIONS."""
    return any((name, where) == (lower, method) and within(io, (target,)) for lower, method, io in DELEGATIONS)


def arrows_up(graph: dict[str, set[tuple[str, str]]]) -> list[str]:
    """'importer -> imported (in function)' for every import that runs from a floor up, delegations aside."""
    bad = []
    for name, edges in sorted(graph.items()):
        for target, where in sorted(edges):
            up = any(within(name, floor) and within(target, above) and not within(target, allowed)
                     for floor, above, allowed in FLOORS if floor != ("tomgs.train",) or not within(name, ABOVE_TRAIN))
            if up and not delegated(name, target, where):
                bad.append(f"{name} -> {target}" + (f" (in {where})" if where else ""))
    return bad


def edge_graph() -> dict[str, set[tuple[str, str]]]:
    known = modules()
    return {name: import_edges(path, name, set(known)) for name, path in known.items()}


def test_the_floors_see_arrows_up():
    """The check finds an arrow up at module level and inside a function, and passes a delegation."""
    assert arrows_up({"tomgs.model": {("tomgs.render.sh", "")}}) == ["tomgs.model -> tomgs.render.sh"]
    assert arrows_up({"tomgs.io.tets": {("tomgs.edit.tets", "gaussian_tet_indices")}}) == \
        ["tomgs.io.tets -> tomgs.edit.tets (in gaussian_tet_indices)"]
    assert arrows_up({"tomgs.kernels.sh": {("tomgs.runtime", "")}}) == ["tomgs.kernels.sh -> tomgs.runtime"]
    assert arrows_up({"tomgs.train.warm": {("tomgs.train.multigpu.shards", "warm_up")}}) != []
    assert arrows_up({"tomgs.train.api": {("tomgs.train.multigpu.launch", "fit")},
                      "tomgs.kernels.sh": {("tomgs.constants", ""), ("tomgs.kernels.rows", "")},
                      "tomgs.cameras": {("tomgs.io.cameras", "Cameras.load")}}) == []
    assert arrows_up({"tomgs.cameras": {("tomgs.io.cameras", "Cameras.save")}}) != []


def test_no_import_runs_from_a_floor_up():
    """Every floor imports nothing above it (module docstring), at module level or in a function."""
    assert arrows_up(edge_graph()) == []


def test_each_delegation_is_used():
    """A delegation no code makes any more leaves DELEGATIONS."""
    graph = edge_graph()
    assert [d for d in sorted(DELEGATIONS) if (d[2], d[1]) not in graph[d[0]]] == []


def test_no_module_imports_another_modules_private_names():
    """What two modules share is public in one of them: no `from tomgs.x import _name`."""
    known = modules()
    bad = []
    for name, path in known.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("tomgs"):
                bad += [f"{name}: from {node.module} import {a.name}" for a in node.names
                        if a.name.startswith("_") and a.name != "__version__"]
    assert bad == []


def test_module_sizes_and_the_top_level():
    """No module over 800 lines; at most a dozen modules directly in tomgs/ (packages aside)."""
    long = {name: n for name, path in modules().items() if (n := len(path.read_text().splitlines())) > 800}
    assert long == {}
    top = [p.name for p in PACKAGE.glob("*.py") if p.name != "__init__.py"]
    assert len(top) <= 12, top


# -- the fit spine: one place for each of its concepts (tomgs.train.pipeline, budget, loop, metrics) ------

TRAIN = PACKAGE / "train"
LONGEST_FUNCTION = 80  # lines of a function in tomgs/train, its docstring included
RANK_LINES = 350  # a sharded rank is the fit's pipeline with its hooks, no second fit


def shown(path: Path) -> str:
    """`path` as the counts name it: relative to the repository, or its name elsewhere."""
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else path.name


def functions_over(path: Path, limit: int) -> list[str]:
    """'file:function (lines)' for every function (methods and nested ones too) of `path` over `limit` lines."""
    tree = ast.parse(path.read_text())
    return [f"{shown(path)}:{node.name} ({node.end_lineno - node.lineno + 1})" for node in ast.walk(tree)
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno + 1 > limit]


def attribute_reads(path: Path, names: set[str]) -> list[str]:
    """'file:line .name' for every read of an attribute in `names` in `path`."""
    tree = ast.parse(path.read_text())
    return [f"{shown(path)}:{node.lineno} .{node.attr}" for node in ast.walk(tree)
            if isinstance(node, ast.Attribute) and node.attr in names and isinstance(node.ctx, ast.Load)]


def calls_of(path: Path, names: set[str]) -> list[str]:
    """'file:line name' for every call of a function or method named in `names` in `path`."""
    tree = ast.parse(path.read_text())
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            name = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", None)
            if name in names:
                out.append(f"{shown(path)}:{node.lineno} {name}")
    return out


def test_the_spine_checks_see_what_they_count(tmp_path):
    """The counts find a long function, an attribute read (not a write or a keyword) and a call."""
    source = tmp_path / "x.py"
    source.write_text("def f(config):\n" + "    a = 1\n" * 80 + "    config.max_seconds = 1\n"
                      "    g(max_seconds=2)\n    return config.max_seconds + ssim(a, a)\n")
    assert functions_over(source, LONGEST_FUNCTION) == ["x.py:f (84)"]
    assert attribute_reads(source, {"max_seconds"}) == ["x.py:84 .max_seconds"]
    assert calls_of(source, {"ssim"}) == ["x.py:84 ssim"]


def test_no_function_in_train_is_over_80_lines():
    """Every function of tomgs/train reads in one screen: the Trainer's run is its cadences (tomgs.train.loop),
    the fit its phases (tomgs.train.pipeline)."""
    assert [f for path in sorted(TRAIN.rglob("*.py")) for f in functions_over(path, LONGEST_FUNCTION)] == []


def test_a_rank_is_the_fit_pipeline_with_its_hooks():
    """A sharded rank subclasses the one-process fit's Pipeline and stays short: it overrides hooks, it does
    not restate the fit."""
    source = (TRAIN / "multigpu" / "rank.py").read_text()
    assert len(source.splitlines()) < RANK_LINES
    assert "class ShardedPipeline(Pipeline):" in source


def test_only_the_budget_reads_max_seconds_and_the_iteration_stop():
    """TrainConfig.max_seconds and stop_at_iterations are read in one place, tomgs.train.budget; the rest of the
    package asks the Budget."""
    reads = [r for path in sorted(PACKAGE.rglob("*.py")) if path != TRAIN / "budget.py"
             for r in attribute_reads(path, {"max_seconds", "stop_at_iterations"})]
    assert reads == []


def test_one_loss_formula():
    """Every training step (the Trainer's eager one, its captured one, a rank's joint refinement, which is the
    Trainer's) takes its loss from tomgs.metrics.training_loss; nothing in tomgs/train computes L1, SSIM or
    their mix itself."""
    own = [c for path in sorted(TRAIN.rglob("*.py"))
           for c in calls_of(path, {"ssim", "ssim_map", "ssim_map_conv", "l1_dssim", "l1_dssim_and_psnr"})]
    assert own == []
    users = sorted({c.split(":")[0] for path in sorted(TRAIN.rglob("*.py"))
                    for c in calls_of(path, {"training_loss"})})
    assert users == ["tomgs/train/captured_step.py", "tomgs/train/trainer.py"]
