"""One moment of a clip for static 3DGS tools, and the clip's cameras for tools that render views.

    scene = load_scene("scene.ply")
    moment = pick_moment(scene.cameras, frame=12)            # or time=0.5
    gaussians = static_moment(scene.model, moment.time)      # StaticGaussians: alive ones, opacity baked
    write_static("frame12.ply", gaussians)                   # .ply, .splat or .spz (tomgs.io.splats)
    write_cameras("cams/", scene.cameras)                    # COLMAP text, transforms.json, cameras.json

A static viewer shows every Gaussian at its base opacity, all frames at once; `static_moment` keeps
the Gaussians alive at that time (tomgs.temporal.frozen_at) with their opacity at that time,
a exp(-((t - m) / sigma)^2 / 2), stored as its logit. It computes in float64 from the stored
parameters, so positions, rotations, log scales and SH are the scene's bit for bit. Layers
(`fit --layer foreground`) join the moment in the base's world as tomgs.render.layers.place_layer puts them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from tomgs.cameras import Cameras
from tomgs.errors import InputError
from tomgs.io.splats import FIELDS, StaticGaussians
from tomgs.temporal import frozen_at


@dataclass
class Moment:
    """A time of the clip: `time` in [0, 1], and `position`, the camera position of the frame at
    (or, for a time between frames, nearest) it, whose camera places layers."""

    time: float
    position: int
    frame: int  # that camera's frame number

    def describe(self) -> str:
        return f"frame {self.frame} (t = {self.time:.6g})"


def pick_moment(cameras: Cameras, frame: int | None = None, time: float | None = None) -> Moment:
    """The moment of frame number `frame` (the scene's numbering, as `tomgs render --frames`) or of
    clip time `time` in [0, 1]; exactly one of them. InputError naming the valid range otherwise."""
    if (frame is None) == (time is None):
        raise InputError("give exactly one of --frame K (a frame number of the scene) or --time T (clip time in [0, 1])")
    numbers = cameras.frame_indices
    if frame is not None:
        hits = np.flatnonzero(numbers == frame)
        if not len(hits):
            raise InputError(f"frame {frame} is not one of the scene's frames ({len(numbers)} frames numbered "
                             f"{int(numbers.min())}..{int(numbers.max())}); pick one of them, or --time T")
        k = int(hits[0])
        return Moment(float(cameras.times[k]), k, int(numbers[k]))
    if not (np.isfinite(time) and 0.0 <= time <= 1.0):
        raise InputError(f"--time {time} is outside the clip; clip time runs from 0 (first frame) to 1 (last)")
    k = int(np.argmin(np.abs(cameras.times - time)))
    return Moment(float(time), k, int(numbers[k]))


def _float64_inputs(model) -> dict:
    """The rasterizer's inputs of `model` in float64, plus the stored values that export keeps."""
    with torch.no_grad():
        p = {name: getattr(model, name).detach().cpu().double() for name in
             ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest", "t_means", "log_t_scales")}
    return {"means": p["means"], "quats": p["quats"], "scales": torch.exp(p["log_scales"]),
            "opacities": torch.sigmoid(p["opacity_logits"]), "colors": p["sh_dc"], "sh_rest": p["sh_rest"],
            "log_scales": p["log_scales"], "t_means": p["t_means"], "t_scales": torch.exp(p["log_t_scales"])}


def static_moment(model, time: float, sh_degree: int | None = None) -> StaticGaussians:
    """The Gaussians of `model` (a GaussianModel) alive at clip time `time`, opacity at that time
    baked into the logit, SH at `sh_degree` (default the model's active degree; higher pads zeros)."""
    frozen = frozen_at(_float64_inputs(model), time)
    opacity = frozen["opacities"]
    degree = model.sh_degree if sh_degree is None else sh_degree
    g = StaticGaussians(
        means=frozen["means"].float().numpy(),
        quats=frozen["quats"].float().numpy(),
        log_scales=frozen["log_scales"].float().numpy(),
        opacity_logits=torch.log(opacity / (1.0 - opacity)).float().numpy(),
        sh_dc=frozen["colors"][:, 0].float().numpy(),
        sh_rest=frozen["sh_rest"][:, :(model.sh_degree + 1) ** 2 - 1].float().numpy(),
    )
    return g.with_sh_degree(degree)


def join(parts: list[StaticGaussians]) -> StaticGaussians:
    """One cloud of several, in order (SH at the highest degree among them, the others padded)."""
    degree = max(p.sh_degree for p in parts)
    parts = [p.with_sh_degree(degree) for p in parts]
    return StaticGaussians(*(np.concatenate([getattr(p, name) for p in parts]) for name in FIELDS))


def moment_with_layers(scene, moment: Moment, layers=(), sh_degree: int | None = None) -> StaticGaussians:
    """The base scene's Gaussians at `moment`, then each layer's (a Scene fitted on the same frames,
    tomgs.render.layers.check_layers) alive at that frame, moved into the base's world in front of what is
    behind it (tomgs.render.layers.place_layer), so the base camera at that frame sees what `tomgs render
    --layer` composites."""
    from tomgs.edit.transforms import transform_gaussians
    from tomgs.render.layers import check_layers, place_layer

    check_layers(scene.cameras, [layer.cameras for layer in layers])
    base = static_moment(scene.model, moment.time, sh_degree)
    parts, behind = [base], base.means
    for layer in layers:
        g = static_moment(layer.model, float(layer.cameras.times[moment.position]), sh_degree)
        matrix, keep = place_layer(scene.cameras, layer.cameras, moment.position, behind, g.means)
        g = g.rows(keep)
        means, quats, scales = transform_gaussians(g.means, g.quats, np.exp(g.log_scales.astype(np.float64)), matrix)
        g = StaticGaussians(means.astype(np.float32), quats.astype(np.float32),
                            np.log(scales).astype(np.float32), g.opacity_logits, g.sh_dc, g.sh_rest)
        parts.append(g)
        behind = g.means
    return join(parts)


def write_cameras(folder, cameras: Cameras) -> list[Path]:
    """The clip's cameras in `folder` (created; existing files of these names replaced): tomgs's
    cameras.json (what `--cameras` reads back, times and frame numbers included), nerfstudio's
    transforms.json (images/NNNNN.png) and a COLMAP text model in sparse/0/ (images NNNNN.png), so a
    frame folder from `tomgs render -o folder/` lines up with both."""
    import json

    from tomgs.io.cameras import colmap_text, nerfstudio
    from tomgs.outputs import write_text

    folder = Path(folder)
    (folder / "sparse" / "0").mkdir(parents=True, exist_ok=True)
    written = [cameras.save(folder / "cameras.json"),
               write_text(folder / "transforms.json", json.dumps(nerfstudio(cameras), indent=1))]
    for name, text in colmap_text(cameras).items():
        written.append(write_text(folder / "sparse" / "0" / name, text))
    return written
