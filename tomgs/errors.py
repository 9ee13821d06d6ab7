"""The project-wide errors for bad user input.

Both are ValueErrors whose message names the file or value and the fix. Library code raises
them for anything a caller passed or a file held; the CLI turns them into exit code 2.
"""

from __future__ import annotations


class InputError(ValueError):
    """Bad user input (missing file, corrupt video, mismatched masks, ...): message says the fix."""


class RenderError(ValueError):
    """Invalid rasterizer input or a frame too large to bin; the message says what to change."""
