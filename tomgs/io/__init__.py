"""Input and output of pixels: video files, frame folders and masks and PNG/MP4 frames out.

`InputError` (from tomgs.errors) is re-exported here for callers that imported it from tomgs.io.
"""

from __future__ import annotations

from tomgs.errors import InputError
from tomgs.io.video import Video, parse_frames, read_video
from tomgs.io.writer import write_frames

__all__ = ["InputError", "Video", "parse_frames", "read_video", "write_frames"]
