"""Fixtures shared by the test files."""

from __future__ import annotations

import os
import shutil

import pytest


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
    """Blender, for the round trip through its Python (tests/test_blender.py)."""
    return required_program("blender", "Debian: apt-get install blender python3-numpy")


@pytest.fixture
def fresh_bounds(monkeypatch):
    """A process's bounds of its own (tomgs.render's keys bound), so a test sets them without reaching
    other tests."""
    from tomgs.render import frame as render

    bounds = render._Bounds()
    monkeypatch.setattr(render, "_bounds", bounds)
    return bounds
