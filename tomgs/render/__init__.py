"""Rendering: Gaussians and cameras in, images out, in pipeline order.

    inputs     `prepare_inputs`: checks and activates a frame's inputs (RasterInputs)
    sh         view-dependent colour from spherical harmonics (`eval_sh`, `sh_to_colors`)
    stages     the three stages (project -> bin -> raster) as they launch their kernels
    frame      the frame layer that issues them, and the public `rasterize`, `render_frame`,
               `blend_weights`, `FrameCounts`, `project_stage`, `bin_stage`
    alive      the alive index: which Gaussians a frame's time can see
    captured   `FrameGraph`: frames replayed from CUDA graphs
    sequence   `render_sequence`, `ClipRenderer`: a clip's frames, pipelined
    reference  the float64 torch oracle every kernel is checked against
    layers     compositing scenes (foreground over background) and a layer fit's inputs
    jobs       a planned render to video or PNG frames (what `tomgs render` runs)

Public names are resolved lazily, as in `tomgs`.
"""

from __future__ import annotations

from tomgs._lazy import lazy_exports

_EXPORTS = {
    "RasterInputs": "tomgs.render.inputs",
    "prepare_inputs": "tomgs.render.inputs",
    "eval_sh": "tomgs.render.sh",
    "sh_to_colors": "tomgs.render.sh",
    "rasterize": "tomgs.render.frame",
    "render_frame": "tomgs.render.frame",
    "blend_weights": "tomgs.render.frame",
    "FrameCounts": "tomgs.render.frame",
    "project_stage": "tomgs.render.frame",
    "bin_stage": "tomgs.render.frame",
    "FrameGraph": "tomgs.render.captured",
    "render_sequence": "tomgs.render.sequence",
    "ClipRenderer": "tomgs.render.sequence",
    "rasterize_reference": "tomgs.render.reference",
    "render_layers": "tomgs.render.layers",
}

__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, globals(), _EXPORTS)
