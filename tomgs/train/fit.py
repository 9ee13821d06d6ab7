"""`tomgs.fit`: video in, scene file out, with the error-against-run-time record beside it.

    scene.ply         the Gaussians, cameras and frame times (tomgs.load_scene reads it)
    scene.csv         iteration, wall seconds, training PSNR, full-clip PSNR, Gaussians, memory
    scene.psnr.png    PSNR against wall-clock time
    scene.ckpt        the checkpoint while training runs (removed when the fit completes)
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from tomgs.errors import InputError
from tomgs.train.config import TrainConfig
from tomgs.train.trainer import FitResult, Trainer


def output_paths(scene_path) -> dict[str, Path]:
    scene = Path(scene_path)
    stem = scene.with_suffix("")
    return dict(scene=scene, csv=Path(f"{stem}.csv"), plot=Path(f"{stem}.psnr.png"), checkpoint=Path(f"{stem}.ckpt"))


def fit(video, output, config: TrainConfig | None = None, *, masks=None, frames=None, max_side=None,
        poses="auto", focal=None, device=None, resume: bool = False, progress=None, pose_progress=None,
        layer: str | None = None, mask_dilation: int = 2) -> FitResult:
    """Fit a TOM-GS scene to `video` (a file, a frame folder or a `tomgs.Video`) and save it to `output`.

    poses: "auto" (built-in tracker), "identity" (fixed camera, also the ablation), a cameras file,
    or anything `tomgs.estimate_cameras` takes. resume: continue from `output`'s checkpoint.
    layer: None (the whole frame), "background" (the pixels outside the masks, dilated by
    `mask_dilation` pixels) or "foreground" (the masked object on a plane, no poses); see tomgs.layers.
    """
    from tomgs.io import Video, read_video
    from tomgs.io.scene import save_scene
    from tomgs.poses import estimate_cameras
    from tomgs.render import resolve_device

    config = config or TrainConfig()
    device = resolve_device(device)
    paths = output_paths(output)
    if not paths["scene"].parent.exists():
        raise InputError(f"{output}: folder {paths['scene'].parent} does not exist; create it first")
    if paths["scene"].suffix.lower() != ".ply":
        raise InputError(f"{output}: a scene is written as .ply; name the output like scene.ply")
    if resume and not paths["checkpoint"].exists():
        raise InputError(f"{paths['checkpoint']}: no checkpoint to resume from; run without --resume")

    clip = video if isinstance(video, Video) else read_video(video, frames=frames, max_side=max_side, masks=masks)
    inputs = _layer_inputs(clip, layer, config, mask_dilation, masks, device)  # checks the masks before any work
    t0 = time.perf_counter()
    point_frames = None
    if inputs.cameras is None:
        cameras, points, colors, report = estimate_cameras(clip, method=poses, focal=focal, progress=pose_progress)
        pose_notes = [f"poses: {report.summary()}", *report.notes]
        views, point_frames = cameras, report.point_frames
    else:  # the foreground layer's fixed cameras
        cameras, views, points, colors, pose_notes = inputs.scene_cameras, inputs.cameras, (), (), []
    pose_seconds = time.perf_counter() - t0

    torch.manual_seed(config.seed)
    trainer = Trainer(inputs.frames, views, points, colors, config, device, point_frames=point_frames, **inputs.hooks)
    trainer.notes[:0] = [*pose_notes, *inputs.notes]
    if resume:
        trainer.load_checkpoint(paths["checkpoint"])
        _rewrite_csv(paths["csv"], trainer.history)
    elif paths["csv"].exists():
        paths["csv"].unlink()
    result = trainer.run(checkpoint=paths["checkpoint"], log_csv=paths["csv"], progress=progress)

    info = dict(source=str(getattr(video, "path", video)) if not isinstance(video, Video) else "<Video>",
                iterations=result.iterations, train_seconds=round(result.seconds, 2),
                pose_seconds=round(pose_seconds, 2), clip_psnr=round(result.clip_psnr, 3), extent=trainer.extent,
                fps=_fps(clip), background=[0.0, 0.0, 0.0],
                config={k: v for k, v in vars(config).items()}, notes=result.notes)
    if layer is not None:
        info["layer"] = layer
    result.cameras = cameras
    save_scene(paths["scene"], result.model, cameras, info)
    _plot(paths["plot"], result.history)
    paths["checkpoint"].unlink(missing_ok=True)
    return result


def _fps(clip) -> float:
    """The fitted frames' rate: the source's (25 when unknown) over the step between them, so a fit on
    every k-th frame plays at the source's speed."""
    fps = clip.fps or 25.0
    steps = np.diff(np.asarray(clip.indices))
    if len(steps) and steps[0] > 1 and np.all(steps == steps[0]):
        fps /= int(steps[0])
    return float(fps)


def _layer_inputs(clip, layer, config, mask_dilation, masks_path, device):
    """tomgs.layers.LayerInputs for `layer`; for None, the whole clip with estimated cameras."""
    if layer is None:
        from tomgs.layers import LayerInputs

        return LayerInputs(clip.frames, None, {})
    from tomgs.layers import background_inputs, foreground_inputs

    if layer == "background":
        return background_inputs(clip, mask_dilation, masks_path)
    if layer == "foreground":
        return foreground_inputs(clip, config, masks_path, device.type)
    raise InputError(f"unknown layer {layer!r}: use background or foreground")


def _rewrite_csv(path: Path, history: list[dict]) -> None:
    from tomgs.train.trainer import _append_csv

    path.unlink(missing_ok=True)
    for row in history:
        _append_csv(path, row)


def _plot(path: Path, history: list[dict]) -> None:
    from tomgs.plots import line_plot_png

    train = [(r["wall_s"], r["train_psnr"]) for r in history if r["train_psnr"] != ""]
    clip = [(r["wall_s"], r["clip_psnr"]) for r in history if r["clip_psnr"] != ""]
    series = {}
    if train:
        series["training frames (running)"] = tuple(np.array(v, dtype=float) for v in zip(*train))
    if clip:
        series["full clip"] = tuple(np.array(v, dtype=float) for v in zip(*clip))
    if series:
        line_plot_png(path, series, xlabel="wall-clock seconds", ylabel="PSNR (dB)", title="PSNR against run time")
