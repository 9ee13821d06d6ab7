"""Input and output of pixels: video files, frame folders and masks and PNG/MP4 frames out.

`InputError` is the one exception type for bad user input anywhere in tomgs: a ValueError whose
message names the file and the fix. The CLI turns it into exit code 2.
"""

from __future__ import annotations


class InputError(ValueError):
    """Bad user input (missing file, corrupt video, mismatched masks, ...): message says the fix."""


from tomgs.io.video import Video, parse_frames, read_video  # noqa: E402  (needs InputError)
from tomgs.io.writer import write_frames  # noqa: E402

__all__ = ["InputError", "Video", "parse_frames", "read_video", "write_frames"]
