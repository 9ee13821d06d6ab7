"""Input and output of pixels: video files, frame folders and masks and PNG/MP4 frames out.

`InputError` (from tomgs.errors) is re-exported here for callers that imported it from tomgs.io.
The other names resolve lazily, as the package's own do, so that importing one module of tomgs.io
(a writer's output check, say) imports no other.
"""

from __future__ import annotations

from tomgs._lazy import lazy_exports
from tomgs.errors import InputError

_EXPORTS = {"Video": "tomgs.io.video", "parse_frames": "tomgs.io.video", "read_video": "tomgs.io.video",
            "write_frames": "tomgs.io.writer"}

__all__ = ["InputError", *_EXPORTS]
__getattr__, __dir__ = lazy_exports(__name__, globals(), _EXPORTS)
