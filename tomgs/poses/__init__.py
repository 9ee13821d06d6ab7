"""Camera poses for a clip: the built-in tracker, pose files, and ONNX models.

`estimate_cameras(frames, masks=None, method="auto", focal=None, progress=None, device=None)`
-> (Cameras, points, colors, report); frames may be any sequence of uint8 frames (read one at a time).
Public names are resolved lazily, as in `tomgs`.
"""

from __future__ import annotations

from tomgs._lazy import lazy_exports

_EXPORTS = {"PoseReport": "tomgs.poses.estimate", "estimate_cameras": "tomgs.poses.estimate"}

__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, globals(), _EXPORTS)
