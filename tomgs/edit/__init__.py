"""Editing TOM-GS scenes: selections, Gaussians <-> tetrahedra, edits over time, tet cages.

    selection   `select(model, cameras, ["box:...", "mask:FOLDER", ...])` -> scene indices
    tets        `gaussians_to_tets`, `tets_to_gaussians`, `deform` (exact, float64)
    transforms  `edit_model` (move, duplicate, remove), `Keyframes`, per-frame clouds
    cage        `make_tets`: one tet per Gaussian, or a voxel cage with the Gaussians bound into it
    physics     `simulate` (soft body on a cage; its own module)

Public names are resolved lazily, as in `tomgs`.
"""

from __future__ import annotations

from tomgs._lazy import lazy_exports

_EXPORTS = {
    "Selector": "tomgs.edit.selection",
    "parse_selector": "tomgs.edit.selection",
    "select": "tomgs.edit.selection",
    "gaussians_to_tets": "tomgs.edit.tets",
    "tets_to_gaussians": "tomgs.edit.tets",
    "deform": "tomgs.edit.tets",
    "affine": "tomgs.edit.transforms",
    "edit_model": "tomgs.edit.transforms",
    "Keyframes": "tomgs.edit.transforms",
    "load_keyframes": "tomgs.edit.transforms",
    "keyframed_clouds": "tomgs.edit.transforms",
    "sequence_clouds": "tomgs.edit.transforms",
    "deformed_model": "tomgs.edit.transforms",
    "build_cage": "tomgs.edit.cage",
    "make_tets": "tomgs.edit.cage",
}

__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, globals(), _EXPORTS)
