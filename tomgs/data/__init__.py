"""The files shipped in tomgs/data (`tomgs example`): their names, what each is for and where they are
installed, with nothing heavy imported, so that `tomgs example` answers at once. tomgs.demo renders
the clip and its masks."""

from __future__ import annotations

from pathlib import Path

# the files shipped in tomgs/data, each with what it is for
EXAMPLE_FILES = {
    "ball.mp4": "40 frames at 160x96 to fit: a ball bounces across a room, the camera moves sideways",
    "ball_masks": "the ball's masks, one PNG a frame (white on the ball), for --masks and --select mask:",
    "blender_softbody.py": "drops a `tomgs tets export --cage` cage in Blender, headless",
    "LICENSE-ball.txt": "the licence of ball.mp4 and its masks (CC0: made by tomgs, `tomgs.demo.write_example`)",
}


def example_file(name: str) -> Path:
    """The installed path of a bundled example file (one of EXAMPLE_FILES)."""
    from importlib.resources import files

    from tomgs.errors import InputError

    if name not in EXAMPLE_FILES:
        raise InputError(f"no example file {name!r}; the examples are {', '.join(EXAMPLE_FILES)}")
    return Path(str(files("tomgs") / "data" / name))
