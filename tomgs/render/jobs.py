"""Render jobs: what `tomgs render`, `edit --render`, `tets import`, `simulate --render` and `demo`
share. A job is planned (every input and the output checked before any work), then run (frames
rendered, layers composited, written atomically) and reported.

    plan = plan_render("out.mp4", scene.cameras, frames="0:40", device="auto", background=None)
    report = run_render(plan, scene, scene.model.render_inputs())
    print(report.summary())
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from tomgs.cameras import Cameras
from tomgs.errors import InputError, counted
from tomgs.io.writer import FPS_RANGE


@dataclass
class RenderPlan:
    """A render checked before any work: where it goes and what it covers."""

    output: str  # a video file or a PNG folder, checked writable (tomgs.io.writer.check_output)
    positions: np.ndarray  # [F] int64 positions into the scene's cameras
    background: tuple | None  # RGB in [0, 1]; None: the scene's own
    device: object  # torch.device
    behind: object = None  # a scene (tomgs.io.scene.Scene) rendered behind this one, or None
    overwrite: bool = False


@dataclass
class RenderReport:
    """What a render did: frames written, time, and how many Gaussians each frame used."""

    output: str
    frames: int
    seconds: float
    device: object
    what: str  # frame numbers and size, e.g. "(0..39) at 320x180"
    gaussians: tuple[int, int]  # fewest, most Gaussians over the clouds rendered (per-frame clouds vary)
    alive: tuple[int, int] = (0, 0)  # fewest, most alive per frame
    notes: tuple[str, ...] = ()  # what the user should know about the frames (far_from_origin)

    def summary(self) -> str:
        fps = self.frames / max(self.seconds, 1e-9)
        low, high = self.gaussians
        total = f"{low:,}" if low == high else f"{low:,}..{high:,}"
        return (f"{self.output}: {counted(self.frames, 'frame')} {self.what} on {self.device} in {self.seconds:.1f} s "
                f"({fps:.1f} fps)\n  {total} Gaussians; alive per frame {self.alive[0]:,}..{self.alive[1]:,}: only "
                f"those alive near each frame's time were projected" + "".join(f"\n  note: {n}" for n in self.notes))


FLOAT32_EPS = 2.0 ** -24  # float32's relative rounding
FAR_PIXELS = 0.25  # a projection this far off (pixels) is said


def far_from_origin(cams: Cameras, means) -> str | None:
    """A note when `cams` and the Gaussians at `means` [N,3] lie so far from the world's origin,
    against the distance between them, that float32 projection (x_cam = R x + t, both terms that
    large) is off by more than FAR_PIXELS pixels; None otherwise."""
    means = np.asarray(means.detach().cpu() if hasattr(means, "detach") else means, dtype=np.float64)
    if len(means) == 0:
        return None
    centres = cams.c2w[:, :3, 3]
    sample = means[:: max(1, len(means) // 4096)]
    reach = max(float(np.abs(centres).max()), float(np.abs(sample).max()))
    distance = float(np.median(np.linalg.norm(sample - centres[0], axis=1)))
    off = FLOAT32_EPS * reach / max(distance, 1e-30) * float(cams.K[0, 0])
    if not np.isfinite(off) or off <= FAR_PIXELS:
        return None
    return (f"the scene lies {reach:.3g} units from the world's origin, {reach / max(distance, 1e-30):.3g} times "
            f"its distance from the cameras: float32 projection is off by ~{off:.2g} px there; move the scene and its "
            f"cameras nearer the origin for exact frames")


def plan_render(output, cameras, frames=None, device="auto", background=None, overwrite: bool = False, *,
                only=None, over=None, name: str = "the scene") -> RenderPlan:
    """Check a render of `cameras`' frames `frames` (a range in the scene's frame numbers, None: all)
    to `output` before any work. `background`: RGB in [0, 1], or None for the scene's. `only`: camera positions that
    have something to render (a sequence's). `over`: the path of a scene to render behind, checked
    against `cameras` (the scene called `name`) like a `render --layer` layer."""
    from tomgs.io.scene import load_scene
    from tomgs.io.writer import check_output
    from tomgs.render.layers import check_layers
    from tomgs.runtime import resolve_device

    check_output(output, overwrite)
    rgb = None if background is None else tuple(float(v) for v in background)
    if rgb is not None and (len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb)):
        raise InputError(f"background must be three numbers in [0, 1], got {background!r}")
    behind = None
    if over is not None:
        behind = load_scene(over)
        check_layers(behind.cameras, [cameras], [f"{name} (in front of --over {over})"])
    positions = select_frames(cameras, frames)
    if only is not None:
        positions = np.array([k for k in positions.tolist() if k in only], dtype=np.int64)
        if len(positions) == 0:
            raise InputError(f"the sequence covers none of the frames {frames!r}: pick frames it covers")
    return RenderPlan(str(output), positions, rgb, resolve_device(device), behind, overwrite)


def run_render(plan: RenderPlan, scene, gaussians, fps: float | None = None, layers=(),
               progress: Callable[[int], None] | None = None) -> RenderReport:
    """Render `gaussians` (the rasterizer's inputs, or a callable frame -> inputs) of `scene`
    (tomgs.io.scene.Scene: cameras and info) with `layers` ((gaussians, cameras) pairs) composited
    over them, as `plan` says; the plan's `behind` scene is the base, `gaussians` go over it.
    `progress(frames_done)` is called after each frame."""
    cams = scene.cameras
    numbers = cams.frame_indices[plan.positions]
    default_rgb, default_fps = render_defaults(scene.info)
    if plan.behind is not None:
        layers = [(gaussians, cams), *layers]
        gaussians, cams = plan.behind.model.render_inputs(), plan.behind.cameras
        default_rgb = render_defaults(plan.behind.info)[0]
    return render_frames(plan.output, gaussians, cams, plan.positions.tolist(), plan.background or default_rgb,
                         plan.device, fps or default_fps, what=f"({numbers[0]}..{numbers[-1]}) at "
                         f"{cams.width}x{cams.height}", layers=layers, numbers=numbers.tolist(),
                         overwrite=plan.overwrite, progress=progress)


def render_frames(output, gaussians, cams, positions, background, device, fps: float, what: str, layers=(),
                  numbers=None, overwrite: bool = False, progress=None) -> RenderReport:
    """Render frames `positions` of `cams` to `output` (video or PNG folder, its PNGs named by
    `numbers`, the frames' numbers: default the positions), `layers` composited over them, and
    count the Gaussians each frame used. `gaussians` and each layer's: the rasterizer's inputs, or
    a callable frame -> inputs (`tomgs.render.render_sequence`)."""
    from tomgs.io import write_frames
    from tomgs.render.layers import render_layers

    positions = list(positions)
    alive, fixed, varying = [], [], []  # Gaussians: in the fixed clouds; per frame in each per-frame one
    start = time.perf_counter()

    def counted(cloud):
        if not callable(cloud):
            fixed.append(int(cloud["means"].shape[0]))
            return cloud
        sizes = []  # a per-frame cloud: count each frame's Gaussians as it is made
        varying.append(sizes)

        def source(k):
            made = cloud(k)
            sizes.append(int(made["means"].shape[0]))
            return made
        return source

    source = counted(gaussians)
    layers = [(counted(g), layer_cams) for g, layer_cams in layers]

    def images():
        for _, image, meta in render_layers(source, cams, positions, layers, background=background, device=device):
            alive.append(int(meta["n_alive"]))
            yield (image.numpy() * 255.0 + 0.5).astype(np.uint8)
            if progress is not None:
                progress(len(alive))

    count = write_frames(images(), output, fps=fps, numbers=positions if numbers is None else numbers,
                         overwrite=overwrite)
    low = sum(fixed) + sum(min(sizes) for sizes in varying)
    high = sum(fixed) + sum(max(sizes) for sizes in varying)
    far = None if callable(gaussians) else far_from_origin(cams, gaussians["means"])
    return RenderReport(str(output), count, time.perf_counter() - start, device, what, (low, high),
                        (min(alive), max(alive)), tuple(n for n in (far,) if n))


# ---- which frames, and the scene's defaults ---------------------------------------------------

def select_frames(cameras: Cameras, spec) -> np.ndarray:
    """Positions (into `cameras`) of the frames that `spec` ('a:b', 'a:b:c', 'k', None = all) picks, in
    the scene's frame numbering (`cameras.frame_indices`, the source video's frame numbers).

    Numbers follow Python slices over 0 .. last frame number (negative counts from the end): a stop
    past the last frame is clamped to it, as slicing does (`0:90:3` picks frames 0..87 of a scene
    fitted on every third of 90 frames); a start outside the scene's frames, a stop before its
    first, or a range that holds none of them, raises InputError.
    """
    from tomgs.io.video import parse_frames

    numbers = cameras.frame_indices
    first, last = int(numbers.min()), int(numbers.max())
    span = f"{first}:{last + 1}" if len(numbers) == last - first + 1 else \
        f"{len(numbers)} frames numbered {first}..{last}"
    sel = parse_frames(spec)
    if spec is None or sel == slice(None):
        return np.arange(len(cameras))
    for value, what, hi in ((sel.start, "start", last), (sel.stop, "stop", last + 1)):
        if value is None or (what == "stop" and value > hi):  # a stop past the end: clamped by the slice
            continue
        absolute = value + last + 1 if value < 0 else value
        if not first <= absolute <= hi:
            raise InputError(f"frame range {spec!r}: {what} {value} is outside the scene's frames ({span}); "
                             f"pick a range inside {first}:{last + 1}")
    # the numbers that range(last + 1)[sel] holds, by arithmetic: no array as long as the largest number
    picked = range(last + 1)[sel]
    positions = np.array([k for k, num in enumerate(numbers.tolist()) if num in picked], dtype=np.int64)
    if len(positions) == 0:
        raise InputError(f"frame range {spec!r} holds none of the scene's frames ({span})")
    return positions


def render_defaults(info: dict) -> tuple[tuple[float, float, float], float]:
    """(background RGB, frames per second) for rendering a scene: its info's `background` and `fps`
    when they are valid (a rate in tomgs.io.writer.FPS_RANGE), else black and 25."""
    background, fps = (0.0, 0.0, 0.0), 25.0
    try:
        rgb = tuple(float(v) for v in info.get("background", ()))
        if len(rgb) == 3 and all(0.0 <= v <= 1.0 for v in rgb):
            background = rgb
    except (TypeError, ValueError):
        pass
    try:
        value = float(info.get("fps", fps))
        if FPS_RANGE[0] <= value <= FPS_RANGE[1]:
            fps = value
    except (TypeError, ValueError, OverflowError):
        pass
    return background, fps
