"""What a command checks before it imports torch or Warp, so that a mistake is answered at once.

torch and Warp take seconds to import (more on a busy machine); the checks here need neither: a
device name and whether the machine has a CUDA GPU (the driver asked through ctypes), a clip's frame
count and size from its index and header (tomgs.io.video.probe_source), a scene's cameras from the
bytes after its Gaussians (tomgs.io.scene.read_scene_clip), selections and the files they name.
The CLI calls them first; the library repeats what it needs, for callers that never pass here.
Every failure is an InputError naming the argument and the fix.
"""

from __future__ import annotations

import re
from pathlib import Path

from tomgs.errors import InputError

DEVICE = re.compile(r"(auto|cpu|cuda)(?::(\d+))?")


def cuda_device_count() -> int:
    """CUDA devices the NVIDIA driver shows this process (CUDA_VISIBLE_DEVICES applies); 0 without a
    driver. Asks libcuda directly: no torch, no context created."""
    import ctypes

    for name in ("libcuda.so.1", "libcuda.so", "nvcuda.dll"):
        try:
            driver = ctypes.CDLL(name)
        except OSError:
            continue
        count = ctypes.c_int(0)
        if driver.cuInit(0) != 0 or driver.cuDeviceGetCount(ctypes.byref(count)) != 0:
            return 0
        return count.value
    return 0


def check_device(name: str | None) -> str:
    """`name` (auto, cpu, cuda or cuda:N) once this machine has it; InputError otherwise."""
    text = "auto" if name is None else str(name).strip()
    match = DEVICE.fullmatch(text)
    if match is None or (match.group(2) is not None and match.group(1) == "auto"):
        raise InputError(f"--device {text!r}: use auto, cpu, cuda or cuda:N")
    if match.group(1) == "cuda":
        count = cuda_device_count()
        index = int(match.group(2) or 0)
        if count == 0:
            raise InputError(f"--device {text}: this machine has no CUDA GPU (no NVIDIA driver answers); use --device "
                             "cpu or auto")
        if index >= count:
            raise InputError(f"--device {text}: this machine has {count} CUDA GPU{'s' if count > 1 else ''} "
                             f"(cuda:0..cuda:{count - 1})")
    return text


def check_clip(video, frames=None, max_side: int | None = None, masks=None, layer: str | None = None):
    """The clip a command will read, checked from its index and header (tomgs.io.video.Source):
    it exists and is a video or a frame folder, `frames` selects some of its frames, they fit in
    memory at `max_side`, and `masks` (needed by a `layer`) holds one per frame, of their size."""
    from tomgs.io.video import check_masks, parse_frames, probe_clip, probe_source

    parse_frames(frames)  # a malformed range is answered before the clip is opened
    source = probe_source(video)
    probe_clip(video, frames, max_side)
    if layer is not None and masks is None:
        raise InputError(f"--layer {layer} needs masks: give --masks MASKS, a folder with one mask image per frame "
                         "(white on the object)")
    if masks is not None:
        check_masks(masks, source)
    return source


def check_existing(path, what: str, folder: bool = False) -> Path:
    """`path` once it exists as a file (or, with `folder`, a folder); InputError naming `what`."""
    path = Path(path)
    ok = path.is_dir() if folder else path.is_file()
    if not ok:
        kind = "folder" if folder else "file"
        wrong = f" (it is a {'file' if folder else 'folder'})" if path.exists() else ""
        raise InputError(f"{what} {path} does not exist{wrong}: give an existing {kind}")
    return path


POSE_FILES = (".json", ".npy", ".onnx")


def check_poses(poses: str | None, option: str = "--poses") -> None:
    """`fit --poses` / `poses --method` when it names a file (a cameras .json, an AnyCam .npy, an
    .onnx model) or a folder (COLMAP text): it exists. Method names are checked where they are read
    (tomgs.poses)."""
    if poses is None:
        return
    path = Path(str(poses))
    named = path.suffix.lower() in POSE_FILES or len(path.parts) > 1 or str(poses).endswith(("/", "\\"))
    if named and not path.exists():
        raise InputError(f"{option} {poses} does not exist; give auto, identity, a cameras .json, an AnyCam "
                         ".npy, a COLMAP text folder or an .onnx model")


def check_selectors(selectors, cameras=None) -> list:
    """Each `--select` parsed (tomgs.edit.selection.parse_selector), the files it names present."""
    from tomgs.edit.selection import parse_selector

    parsed = [parse_selector(text) for text in selectors]
    for s in parsed:
        if s.kind == "index":
            check_existing(s.path, "--select's index file")
        elif s.kind == "mask":
            check_existing(s.path, "--select's mask folder", folder=True)
    return parsed


def check_scene(path, cameras=None):
    """(Cameras, info) of the scene file `path` (tomgs.io.scene.read_scene_clip): its header and
    cameras, not its Gaussians. The path itself is checked first (tomgs.io.kinds), before the scene
    reader and numpy are imported."""
    from tomgs.io.kinds import check_scene_path

    check_scene_path(path)
    from tomgs.io.scene import read_scene_clip

    return read_scene_clip(path, cameras=cameras)


def check_render_output(output, overwrite: bool = False, device=None) -> None:
    """The output of a render (a video or a PNG folder: its type and place, tomgs.io.writer.check_output)
    and its device, from the arguments alone: checked before a scene is read."""
    from tomgs.io.writer import check_output

    check_device(device)
    check_output(output, overwrite)


def check_render(output, cameras, frames=None, overwrite: bool = False, over=None, device=None) -> None:
    """A render of `cameras`' frames `frames` to `output` (a video or a PNG folder), before any work:
    the output and device (check_render_output), the range (tomgs.render.jobs.select_frames) and the
    scene to render `over`. tomgs.render.jobs.plan_render checks the rest."""
    from tomgs.render.jobs import select_frames

    check_render_output(output, overwrite, device)
    select_frames(cameras, frames)
    if over is not None:
        check_scene(over)


def check_eval_video(video, scene: str, cameras, info: dict, force: bool = False) -> tuple[list[str], bool]:
    """Whether `video` is the clip the scene `scene` (its `cameras` and `info`) was fitted on, from
    its index and header: frame count, size and aspect (tomgs.io.video.video_differences). A
    difference is an InputError naming it, unless `force`, which returns it as notes; with the notes,
    whether the video's frames can be compared only in part or resized (tomgs.io.video.read_video_against)."""
    from tomgs.io.video import video_differences

    impossible, differ = video_differences(video, cameras, info.get("clip"))
    if impossible and not force:
        raise InputError(f"{video} cannot be compared frame by frame with {scene}: {'; '.join(impossible)}. Give "
                         "the video it was fitted on, or --force to compare the frames both have, resized to the "
                         "scene's size")
    return refuse_or_note(video, scene, impossible + differ, force), bool(impossible)


def refuse_or_note(video, scene: str, differ: list[str], force: bool) -> list[str]:
    """`differ` as notes when `force`, else an InputError saying that `video` is not `scene`'s."""
    if differ and not force:
        raise InputError(f"{video} is not the video {scene} was fitted on: {'; '.join(differ)}. Give that video, or "
                         "--force to compare anyway")
    return [f"compared anyway (--force): {d}" for d in differ]
