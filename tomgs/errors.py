"""The project-wide errors for bad user input, and how counts read in what tomgs says.

Both errors are ValueErrors whose message names the file or value and the fix. Library code raises
them for anything a caller passed or a file held; the CLI turns them into exit code 2. `counted`
puts a number and its noun in agreement, in messages, notes and plans alike; `short_repr` shows a
value read from a file in a message, cut short.
"""

from __future__ import annotations


class InputError(ValueError):
    """Bad user input (missing file, corrupt video, mismatched masks, ...): message says the fix."""


class RenderError(ValueError):
    """Invalid rasterizer input or a frame too large to bin; the message says what to change."""


def counted(n: int, noun: str, plural: str | None = None) -> str:
    """'1 frame', '2 frames', '12,000 Gaussians': `n` (thousands separated) and `noun`, or its
    `plural` (default noun + 's') unless n is 1."""
    return f"{n:,} {noun if n == 1 else plural or noun + 's'}"


def short_repr(value, limit: int = 60) -> str:
    """repr(value) cut to `limit` characters; never RecursionError on deeply nested file content."""
    try:
        text = repr(value)
    except RecursionError:
        return "<nested too deeply to show>"
    return text if len(text) <= limit else text[:limit] + "..."
