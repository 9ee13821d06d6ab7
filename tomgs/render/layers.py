"""Foreground and background layers from masks, and rendering layers together.

    background  the clip's scene fitted on the pixels outside the masks (dilated a little), with the
                clip's cameras: the masked object never enters it (Trainer `weights`). It fills the
                object's place: half its initial Gaussians start alive over the whole clip
                (Trainer `wide_fraction`), so what other frames saw behind the object stays alive
                where the object covers it, and its alpha is pulled to 1 everywhere
                (`alpha_targets`), so a spot never seen is filled from its surroundings.
    foreground  the masked object alone, MiraGe-style: flat Gaussians pinned to the plane z = 0
                (`tomgs.model.PlanarGaussianModel`) seen by two fixed cameras, A at z = -d looking
                along +z and B at z = +d looking back, B seeing the horizontally mirrored frame. No
                estimated poses: they follow the background's motion, not the object's. Supervised
                with the frame inside the mask (black outside) and its alpha against the mask, so it
                is transparent outside the object. Saved with camera A for every frame.

The plane is MiraGe's y = 0 turned into the scenes' OpenCV axes: camera A has the identity
rotation, like frame 0 of a fitted scene, so +y is down in the image as everywhere else in tomgs
(the physics' default gravity pulls the object down the frame, not into it).

`render_layers` composites layers over a base scene frame by frame: each layer rendered with its
own cameras at the same frame, its colour premultiplied by its alpha, over what lies behind it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from tomgs.cameras import Cameras
from tomgs.errors import InputError

PLANE_DISTANCE = 1.0  # d: the cameras' distance from the foreground plane (scene units)
# the share of the background's initial Gaussians that start alive over the whole clip (the rest
# around their own frame, for moving content): without them nothing is alive behind the object in
# the frames where it covers a spot, since no supervised pixel there asks for it, and the layer
# shows a hole; with them, the spot is filled from the frames that saw it
BACKGROUND_WIDE_FRACTION = 0.5


@dataclass
class LayerInputs:
    """What the trainer fits for a layer: frames uint8 [V,H,W,3] with their cameras [V] (V = T for
    the background, 2T for the foreground's two views), Trainer keyword arguments (`weights` and
    `alpha_targets` as uint8 [V,H,W], 255 = 1, `initial`), the cameras saved with the scene ([T]; None: the estimated ones),
    and notes for the fit's report."""

    frames: np.ndarray
    cameras: Cameras | None
    hooks: dict
    scene_cameras: Cameras | None = None
    notes: list[str] = field(default_factory=list)


def check_masks(clip, layer: str, masks_path=None) -> np.ndarray:
    """The clip's masks, bool [T,H,W], checked for `layer`; raises InputError naming the fix."""
    where = f"masks in {masks_path}" if masks_path is not None else "the masks"
    if clip.masks is None:
        raise InputError(f"the {layer} layer needs masks: give --masks MASKS (masks= in Python), a folder with "
                         "one mask image per frame, white on the object")
    masks = np.asarray(clip.masks, dtype=bool)
    if not masks.any():
        raise InputError(f"{where} are empty in every frame: the {layer} layer needs the object marked "
                         "white (> 127) in the frames where it appears")
    return masks


def dilate(masks: np.ndarray, pixels: int) -> np.ndarray:
    """bool [T,H,W] grown by `pixels` (a disc), so the edges of loose masks stay out of the background."""
    if pixels <= 0:
        return masks
    import cv2

    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * pixels + 1, 2 * pixels + 1))
    return np.stack([cv2.dilate(m.astype(np.uint8), kernel) > 0 for m in masks])


def background_inputs(clip, dilation: int = 2, masks_path=None) -> LayerInputs:
    """Loss weight 1 outside the masks dilated by `dilation` pixels, 0 inside; cameras estimated."""
    masks = check_masks(clip, "background", masks_path)
    covered = dilate(masks, dilation)
    full = np.flatnonzero(covered.all(axis=(1, 2)))
    if len(full):
        raise InputError(f"the mask of frame {int(clip.indices[full[0]])} (dilated by {dilation} px) covers the whole "
                         f"frame: the background layer needs pixels outside the mask in every frame; drop the frame "
                         f"with --frames or use a smaller --mask-dilation")
    # uint8 0..255 like the frames (the trainer's storage): float32 would take 4/3 of the clip twice
    weights = np.where(covered, 0, 255).astype(np.uint8)
    hooks = dict(weights=weights, wide_fraction=BACKGROUND_WIDE_FRACTION,
                 alpha_targets=np.full(weights.shape, 255, np.uint8))
    return LayerInputs(clip.frames, None, hooks, notes=[
        f"background layer: loss on the {100 - 100 * covered.mean():.1f}% of pixels outside the masks "
        f"(dilated by {dilation} px); PSNR measured there"])


def plane_cameras(n: int, width: int, height: int, times=None, frame_indices=None,
                  distance: float = PLANE_DISTANCE) -> tuple[Cameras, Cameras]:
    """(A, B): n frames each of the fixed cameras facing the foreground plane z = 0 from z = -d (A,
    identity rotation) and z = +d (B, turned half round the y axis: it sees A's image mirrored left to
    right). Focal max(W, H): the frame's long side spans `distance` on the plane."""
    from tomgs.cameras import frame_times, intrinsics

    front, back = np.eye(4), np.diag([-1.0, 1.0, -1.0, 1.0])
    front[2, 3], back[2, 3] = -distance, distance
    times = frame_times(n) if times is None else times
    indices = np.arange(n) if frame_indices is None else frame_indices
    K = intrinsics(float(max(width, height)), width, height)
    return tuple(Cameras(np.tile(c2w, (n, 1, 1)), K, width, height, times, indices) for c2w in (front, back))


def foreground_inputs(clip, config, masks_path=None, device_type: str = "cpu") -> LayerInputs:
    """The two views of every frame (A: the frame, B: mirrored), black outside the mask, alpha targets
    the mask, and the planar model initialised from the object's pixels."""
    masks = check_masks(clip, "foreground", masks_path)
    n, height, width = masks.shape
    front, back = plane_cameras(n, width, height, clip.times, clip.indices)
    cutout = np.where(masks[..., None], clip.frames, 0).astype(np.uint8)
    frames = np.concatenate([cutout, cutout[:, :, ::-1]])
    alpha = np.concatenate([masks, masks[:, :, ::-1]]).astype(np.uint8) * np.uint8(255)
    views = Cameras(np.concatenate([front.c2w, back.c2w]), front.K, width, height,
                    np.concatenate([front.times, back.times]), np.concatenate([front.frame_indices] * 2))
    model = planar_model(cutout, masks, front, config, device_type)
    return LayerInputs(frames, views, dict(alpha_targets=alpha, initial=(model, PLANE_DISTANCE)), front, [
        f"foreground layer: {len(model):,} flat Gaussians on the plane z = 0 from the masked pixels, two fixed "
        "cameras (the second sees the mirrored frame), no estimated poses; PSNR against the frames cut out by "
        "the masks"])


def planar_model(frames: np.ndarray, masks: np.ndarray, cameras: Cameras, config, device_type: str = "cpu"):
    """PlanarGaussianModel with `config.points_per_frame` Gaussians over the object in every frame where
    it appears (the object is the layer's whole subject), each the size of its share of the mask, on
    the plane where camera A sees its pixel and alive around its frame's time.
    frames uint8 [T,H,W,3], masks bool [T,H,W]."""
    from tomgs.model import PlanarGaussianModel
    from tomgs.temporal import frames_to_clip_time

    g = torch.Generator().manual_seed(config.seed)
    n, height, width = masks.shape
    per_frame = config.points_per_frame(int(masks.sum(axis=(1, 2)).max()), n, device_type)
    focal = float(cameras.K[0, 0])
    points, colors, times, sizes = [], [], [], []
    for k in range(n):
        pixels = torch.from_numpy(np.flatnonzero(masks[k]))
        if len(pixels) == 0:
            continue
        chosen = pixels[torch.randint(len(pixels), (per_frame,), generator=g)]
        v, u = chosen // width, chosen % width
        jitter = torch.rand(2, per_frame, generator=g, dtype=torch.float64)
        x = (u + jitter[0] - cameras.K[0, 2]) / focal * PLANE_DISTANCE  # camera A: identity rotation, depth d
        y = (v + jitter[1] - cameras.K[1, 2]) / focal * PLANE_DISTANCE
        points.append(torch.stack([x, y, torch.zeros_like(x)], -1))
        colors.append(torch.from_numpy(frames[k][v.numpy(), u.numpy()]).double() / 255.0)
        times.append(torch.full((per_frame,), float(cameras.times[k]), dtype=torch.float64))
        sizes.append(torch.full((per_frame,), PLANE_DISTANCE / focal * math.sqrt(len(pixels) / per_frame)))
    sigma = frames_to_clip_time(config.init_t_scale_frames, n)
    model = PlanarGaussianModel.from_points(torch.cat(points).float(), torch.cat(colors).float(),
                                            torch.cat(times).float(), sigma, max_sh_degree=config.sh_degree,
                                            sizes=torch.cat(sizes).float())
    model.sh_degree = config.sh_degree
    return model


# ---- rendering layers together -----------------------------------------------------------------

def check_layers(base: Cameras, layers, names=None) -> None:
    """Raise InputError unless every layer's cameras match the base's frames and image size."""
    for i, cams in enumerate(layers):
        name = names[i] if names else f"layer {i + 1}"
        if (cams.width, cams.height) != (base.width, base.height):
            raise InputError(f"{name} is {cams.width}x{cams.height} but the base scene is {base.width}x{base.height}: "
                             "layers must be fitted on the same frames at the same size (--max-side)")
        if len(cams) != len(base) or not np.array_equal(cams.frame_indices, base.frame_indices):
            raise InputError(f"{name} has {len(cams)} frames (numbered {int(cams.frame_indices.min())}.."
                             f"{int(cams.frame_indices.max())}) but the base scene has {len(base)} "
                             f"({int(base.frame_indices.min())}..{int(base.frame_indices.max())}): layers must be "
                             "fitted on the same frames (--frames)")


# ---- a layer in the base's world (one static cloud: `tomgs export --layer`, `tomgs view --layer`) --------

NEAR = 0.01  # the rasterizer's near plane (tomgs.rasterize's default `near`)
LAYER_GAP = 0.5  # a layer's farthest Gaussian sits at this fraction of the depth of the nearest one behind it


def layer_transform(base: Cameras, layer: Cameras, k: int, scale: float) -> np.ndarray:
    """[4,4] affine map from a layer's world to the base's at position k: the base camera k sees the
    mapped layer where the layer's camera k sees the layer, every point at `scale` times its depth
    (a perspective camera sees the same image when points move along their rays)."""
    intrinsics = np.eye(4)
    intrinsics[:3, :3] = np.linalg.inv(base.K) @ layer.K  # keeps depth: its last row is (0, 0, 1)
    return base.c2w[k] @ np.diag([scale, scale, scale, 1.0]) @ intrinsics @ np.linalg.inv(layer.c2w[k])


def place_layer(base: Cameras, layer: Cameras, k: int, behind, means) -> tuple[np.ndarray, np.ndarray]:
    """(matrix [4,4], keep bool [M]): where a layer's Gaussians at position k go in the base's world
    so that base camera k sees them as `render_layers` composites them, in front of `behind` (means
    [P,3] in the base's world, what lies behind the layer there). `means` [M,3] are the layer's,
    `keep` those in front of its camera's near plane (the rasterizer culls the rest). The layer is
    pulled along the rays until its farthest Gaussian is at LAYER_GAP of the nearest depth behind it,
    never nearer than twice the near plane."""
    def depths(cams, points):
        w2c = np.linalg.inv(cams.c2w[k])
        return np.asarray(points, np.float64) @ w2c[2, :3] + w2c[2, 3]

    ahead = depths(base, behind)
    ahead = ahead[ahead >= NEAR]
    depth = depths(layer, means)
    keep = depth >= NEAR
    scale = 1.0
    if keep.any() and len(ahead):
        nearest, farthest = float(depth[keep].min()), float(depth[keep].max())
        scale = max(LAYER_GAP * float(ahead.min()) / farthest, 2.0 * NEAR / nearest)
    return layer_transform(base, layer, k, scale), keep


def render_layers(gaussians, cameras: Cameras, positions=None, layers=(), *, background=None, device=None):
    """Yield (k, image [H,W,3] float32 in [0,1] on the CPU, meta) for frames `positions` of the base
    (`gaussians`, `cameras`, as `tomgs.render.render_sequence` takes them) with `layers`, a sequence
    of (gaussians, cameras) composited over it in order (the last in front); a layer's gaussians are
    the rasterizer's inputs or, like the base's, a callable k -> inputs (a per-frame cloud: an edit
    over time, a simulated shot). Frame k of a layer is rendered with its own camera k at its time
    k, colour premultiplied by alpha, then image = colour + (1 - alpha) * image. Without layers,
    exactly `render_sequence`. meta: the base frame's, with `n_alive` summed over the layers."""
    from tomgs.model import RENDER_INPUTS
    from tomgs.render.frame import rasterize
    from tomgs.render.sequence import render_sequence

    check_layers(cameras, [cams for _, cams in layers])
    base = render_sequence(gaussians, cameras, positions, background=background, device=device)
    if not layers:
        yield from base
        return
    where = torch.device(device) if device is not None else None if callable(gaussians) else gaussians["means"].device
    views = {}  # (layer, device) -> (viewmats, Ks)

    @torch.no_grad()  # inside a helper: a no_grad block around `yield` would leak into the caller
    def composite(k: int, image: torch.Tensor, meta: dict):
        dev = where or image.device
        image = image.to(dev)
        alive = int(meta["n_alive"])
        for i, (g, cams) in enumerate(layers):
            g = {name: value.detach().to(dev) for name, value in (g(k) if callable(g) else g).items()
                 if name in RENDER_INPUTS}
            if (i, dev) not in views:
                views[i, dev] = cams.viewmats(dev), cams.Ks(dev)
            viewmats, Ks = views[i, dev]
            colour, alpha, layer_meta = rasterize(**g, viewmat=viewmats[k], K=Ks[k], width=cams.width,
                                                  height=cams.height, t=float(cams.times[k]))
            image = colour + (1.0 - alpha) * image
            alive += int(layer_meta["n_alive"])
        return k, image.clamp(0.0, 1.0).cpu(), dict(meta, n_alive=alive)

    for k, image, meta in base:
        yield composite(k, image, meta)
