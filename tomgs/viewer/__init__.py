"""`tomgs view`: a scene in the browser (viser), its time scrubbed (server: the scene, the frames
sent, the selection tools). Public names are resolved lazily, as in `tomgs`: importing the package
needs no viser."""

from __future__ import annotations

from tomgs._lazy import lazy_exports

_EXPORTS = {"open_viewer": "tomgs.viewer.server"}

__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, globals(), _EXPORTS)
