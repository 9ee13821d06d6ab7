"""Camera poses for a clip: the built-in tracker, pose files, and ONNX models.

`estimate_cameras(frames, masks=None, method="auto", focal=None, progress=None, device=None)`
-> (Cameras, points, colors, report); frames may be any sequence of uint8 frames (read one at a time).
"""

from __future__ import annotations

from tomgs.poses.estimate import PoseReport, estimate_cameras

__all__ = ["PoseReport", "estimate_cameras"]
