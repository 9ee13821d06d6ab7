"""Fixtures shared by the test files."""

from __future__ import annotations

import os
import shutil

import pytest


@pytest.fixture(scope="session")
def chromium() -> str:
    """Path of Debian's Chromium for the browser tests. Skips when it is not installed, unless
    TOMGS_REQUIRE_CHROMIUM=1 (CI sets it, after installing it), then fails."""
    exe = shutil.which("chromium")
    if exe is None:
        if os.environ.get("TOMGS_REQUIRE_CHROMIUM") == "1":
            pytest.fail("TOMGS_REQUIRE_CHROMIUM=1 but `chromium` is not on PATH (apt-get install chromium)")
        pytest.skip("Debian's chromium is not installed (apt-get install chromium)")
    return exe
