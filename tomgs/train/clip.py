"""The clip as a fit records it, so that a resume finds the same one: the options that change its frames
(built once, for one process and for every rank), what identifies its frames (source frame numbers,
size, thumbnails of every frame and mask), and the checks a resume makes against a checkpoint; the
frame rate the scene plays at; and where a trainer keeps the frames (`frame_store`, `uint8_planes`)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from tomgs.errors import InputError, counted
from tomgs.train.checkpoint import START_OVER, check_same_settings
from tomgs.train.config import TrainConfig


def fit_options(video, *, frames, max_side, masks, poses, focal, layer=None, mask_dilation=None) -> dict:
    """What a checkpoint records of a fit's options (checked by `check_options` and `check_clip`)."""
    return dict(frames=None if frames is None else str(frames), max_side=None if max_side is None else int(max_side),
                layer=layer, mask_dilation=int(mask_dilation) if layer == "background" else None,
                masks=masks is not None or (getattr(video, "masks", None) is not None), poses=poses_key(poses),
                focal=None if focal is None else float(focal))


def poses_key(poses) -> str:
    """The poses option as recorded: a method name, a file's absolute path, or '<type>' for an object."""
    if isinstance(poses, (str, os.PathLike)):
        text = str(poses)
        return str(Path(text).resolve()) if Path(text).exists() else text
    return f"<{type(poses).__name__}>"


def clip_identity(clip) -> dict:
    """What a resume must find again: source frame numbers, frame size, thumbnails of frames and masks
    (tomgs.io.video.thumbnails, as uint8 tensors)."""
    from tomgs.io.video import thumbnails

    return dict(frame_indices=[int(i) for i in clip.indices], size=[int(s) for s in clip.frames.shape[1:3]],
                thumbnails=torch.from_numpy(thumbnails(clip.frames)),
                mask_thumbnails=None if clip.masks is None else torch.from_numpy(thumbnails(clip.masks)))


def _describe(indices: list[int]) -> str:
    if not indices:
        return "no frames"
    step = indices[1] - indices[0] if len(indices) > 1 else 1
    regular = all(b - a == step for a, b in zip(indices, indices[1:]))
    span = f"{indices[0]}..{indices[-1]}" + (f" step {step}" if regular and step != 1 else "" if regular else ", irregular")
    return f"source frames {span} ({counted(len(indices), 'frame')})"


def _refuse(checkpoint, what: str, option: str) -> InputError:
    return InputError(f"{checkpoint} {what}: resume with the {option} it was started with, or {START_OVER}")


def check_options(saved: dict, options: dict, config: TrainConfig, checkpoint) -> None:
    """Before any work: the options a resume must repeat (layer, masks, poses, SH degree, temporal)."""
    was = saved["clip"].get("options", {})
    for key, option in (("layer", "--layer"), ("masks", "--masks"), ("mask_dilation", "--mask-dilation"),
                        ("focal", "--focal")):
        if key in was and was[key] != options[key]:
            raise _refuse(checkpoint, f"was fitted with {option} {_show(was[key])}, this run gives "
                                      f"{_show(options[key])}", option)
    objects = "<" in str(was.get("poses")) + options["poses"]  # poses given as Python objects: not comparable
    if "poses" in was and was["poses"] != options["poses"] and not objects:
        raise _refuse(checkpoint, f"was fitted with --poses {was['poses']}, this run gives {options['poses']}",
                      "--poses")
    check_same_settings(saved["config"], config, checkpoint)


def check_clip(was: dict, now: dict, options: dict, checkpoint) -> None:
    """After decoding, before the poses: the same source frames, size and content as the checkpoint's."""
    from tomgs.io.video import differing_thumbnails

    given = was.get("options", {})
    if "frame_indices" in was and was["frame_indices"] != now["frame_indices"]:
        raise _refuse(checkpoint, f"was fitted on {_describe(was['frame_indices'])} (--frames "
                                  f"{given.get('frames') or 'all'}), this run selects {_describe(now['frame_indices'])} "
                                  f"(--frames {options['frames'] or 'all'})", "--frames")
    if "size" in was and was["size"] != now["size"]:
        (h0, w0), (h1, w1) = was["size"], now["size"]
        raise _refuse(checkpoint, f"was fitted on frames of {w0}x{h0} (--max-side {given.get('max_side') or 'none'}), "
                                  f"this run reads {w1}x{h1} (--max-side {options['max_side'] or 'none'})",
                      "--max-side")
    for key, what, option in (("thumbnails", "frames", "video"), ("mask_thumbnails", "masks", "--masks")):
        if was.get(key) is None or now.get(key) is None:
            continue
        if not torch.is_tensor(was[key]):
            continue
        differ = differing_thumbnails(was[key].numpy(), now[key].numpy())
        if differ:
            raise _refuse(checkpoint, f"was fitted on other {what}: {differ} of this run's {len(now[key])} differ",
                          option)


def _show(value) -> str:
    return "none" if value is None or value is False else "given" if value is True else str(value)


def clip_fps(clip) -> float:
    """The fitted frames' rate: the source's (25 when unknown) over the step between them, so a fit on
    every k-th frame plays at the source's speed."""
    fps = clip.fps or 25.0
    steps = np.diff(np.asarray(clip.indices))
    if len(steps) and steps[0] > 1 and np.all(steps == steps[0]):
        fps /= int(steps[0])
    return float(fps)


FRAME_MEMORY_SHARE = 0.25  # of the free GPU memory: frames beyond it stay on the host


def frame_store(nbytes: float, device: torch.device) -> torch.device:
    """Where the clip's uint8 frames live: on `device`, or on the host when they would take more than
    FRAME_MEMORY_SHARE of a GPU's free memory (each step then copies one frame over)."""
    if device.type != "cuda":
        return device
    free, _ = torch.cuda.mem_get_info(device)
    return device if nbytes <= FRAME_MEMORY_SHARE * free else torch.device("cpu")


def uint8_planes(values, shape, name: str, device) -> torch.Tensor:
    """uint8 [T,H,W] (255 = 1) as given, or float [T,H,W] in [0,1] converted frame by frame -> uint8
    [T,H,W] on `device` (stored like the frames, converted per step)."""
    values = np.asarray(values)
    if values.shape != tuple(shape):
        raise ValueError(f"{name} must have shape {tuple(shape)} like the frames, got {values.shape}")
    if values.dtype != np.uint8:
        values = np.stack([np.rint(np.clip(v.astype(np.float32), 0.0, 1.0) * 255.0).astype(np.uint8) for v in values])
    return torch.as_tensor(values, device=device)
