"""tomgs: editable video as static 3D Gaussians with temporal opacity (TOM-GS).

Importing this package is cheap: no kernel is compiled and no GPU is touched until the first call.
Public names are resolved lazily from the module that owns them.
"""

from __future__ import annotations

import time

from tomgs._lazy import lazy_exports

# tomgs's first instant (time.perf_counter()): a command's budget counts from it. Not the process's
# start: a shell's `sleep 15 && tomgs fit ...` hands its 15 s old process to tomgs.
STARTED = time.perf_counter()

__version__ = "0.1.0"

# public name -> owning module (one module owns each concept; docs/design.md)
_EXPORTS = {
    "rasterize": "tomgs.render",
    "FrameGraph": "tomgs.render.captured",
    "ClipRenderer": "tomgs.render.sequence",
    "render_sequence": "tomgs.render.sequence",
    "RenderError": "tomgs.errors",
    "rasterize_reference": "tomgs.render.reference",
    "eval_sh": "tomgs.render.sh",
    "InputError": "tomgs.errors",
    "Video": "tomgs.io",
    "read_video": "tomgs.io",
    "Cameras": "tomgs.cameras",
    "estimate_cameras": "tomgs.poses",
    "PoseReport": "tomgs.poses",
    "GaussianModel": "tomgs.model",
    "fit": "tomgs.train",
    "TrainConfig": "tomgs.train",
    "psnr": "tomgs.metrics",
    "ssim": "tomgs.metrics",
    "LPIPS": "tomgs.metrics",
    "EvalReport": "tomgs.metrics",
    "evaluate": "tomgs.metrics",
    "save_scene": "tomgs.io.scene",
    "load_scene": "tomgs.io.scene",
    "Scene": "tomgs.io.scene",
    "gaussians_to_tets": "tomgs.edit.tets",
    "tets_to_gaussians": "tomgs.edit.tets",
    "deform": "tomgs.edit.tets",
    "edit_model": "tomgs.edit.transforms",
    "make_tets": "tomgs.edit.cage",
    "Tets": "tomgs.io.tets",
    "save_tets": "tomgs.io.tets",
    "load_tets": "tomgs.io.tets",
}

__all__ = ["__version__", *_EXPORTS]
__getattr__, __dir__ = lazy_exports(__name__, globals(), _EXPORTS)
