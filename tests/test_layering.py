"""The package's layering: what importing a module loads, and no import circle among tomgs's modules.

Each import check runs in a fresh interpreter (a subprocess), so that what this test process already
imported cannot hide a heavy import. The circle check reads the source (no import runs): every
`import` and `from ... import` of a tomgs module, at module level and inside functions, is an edge,
and so is the package a module sits in (importing tomgs.io.video runs tomgs/io/__init__.py first).
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


def imports_of(path: Path, name: str, known: set[str]) -> set[str]:
    """The tomgs modules that module `name` (file `path`) imports anywhere in its source."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
            # `from pkg import sub` imports the submodule pkg.sub when there is one
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names]
        else:
            continue
        for target in targets:
            while target and target not in known:  # `import tomgs.x.y` of a name inside a module
                target = target.rpartition(".")[0]
            while target:  # the module and every package above it run
                if target != name:
                    found.add(target)
                target = target.rpartition(".")[0]
    return found - {"tomgs"}  # tomgs/__init__ imports only tomgs._lazy: every module may sit under it


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
    assert "tomgs.train.multigpu.launch" in graph["tomgs.train.pipeline"]  # imported inside fit()
    assert cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert cycle({"a": {"b"}, "b": set()}) is None


def test_no_import_circle():
    """No module of tomgs imports, at any depth and at any level (module or function), itself."""
    assert cycle(import_graph()) is None


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
