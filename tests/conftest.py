"""Fixtures shared by the test files."""

from __future__ import annotations

import os
import shutil

import pytest

# Test files behind the `slow` marker: `pytest` alone leaves them out (pyproject's addopts), `-m slow`
# runs them, and CI runs both. Other people's programs and readers (Blender, Chromium, viser, gsply and
# open3d, onnxruntime), several processes, fuzzing. Single long tests elsewhere carry the marker themselves.
SLOW_FILES = {"test_blender.py", "test_view.py", "test_video_out.py", "test_export.py", "test_poses_onnx.py",
              "test_shards.py", "test_fuzz_loaders.py", "test_fuzz_render.py"}


@pytest.hookimpl(tryfirst=True)  # before `-m` deselects by marker
def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.path.name in SLOW_FILES:
            item.add_marker(pytest.mark.slow)


def required_program(name: str, install: str) -> str:
    """Path of the program `name` for tests that run it. Skips when it is not on PATH, unless
    TOMGS_REQUIRE_<NAME>=1 (CI sets it, after installing it), then fails."""
    exe = shutil.which(name)
    if exe is None:
        flag = f"TOMGS_REQUIRE_{name.upper()}"
        if os.environ.get(flag) == "1":
            pytest.fail(f"{flag}=1 but `{name}` is not on PATH ({install})")
        pytest.skip(f"`{name}` is not on PATH ({install})")
    return exe


@pytest.fixture(scope="session")
def chromium() -> str:
    """Debian's Chromium, for the browser tests."""
    return required_program("chromium", "Debian: apt-get install chromium")


@pytest.fixture(scope="session")
def blender() -> str:
    """Blender, for the round trip through its Python (tests/io/test_blender.py)."""
    return required_program("blender", "Debian: apt-get install blender python3-numpy")


@pytest.fixture
def fresh_bounds(monkeypatch):
    """A process's bounds of its own (tomgs.render's keys bound), so a test sets them without reaching
    other tests."""
    from tomgs.render import frame as render

    bounds = render.KeyBounds()
    monkeypatch.setattr(render, "key_bounds", bounds)
    return bounds
