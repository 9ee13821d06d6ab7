"""Foreground and background layers from masks: the background never sees the masked object, the
planar foreground stays on its plane and is transparent outside its mask, the two composite back
to the clip, either layer can be changed alone, and bad input exits with code 2 writing nothing."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from tomgs.cli import main
from tomgs.io import Video
from tomgs.io.scene import load_scene, save_scene
from tomgs.render.layers import render_layers
from tomgs.metrics import psnr
from tomgs.model import GaussianModel
from tomgs.render.frame import rasterize
from tomgs.render.sequence import render_sequence
from tomgs.train import fit, preset

T, H, W = 8, 32, 48


def square_clip(noise: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """uint8 [T,H,W,3] frames of a static smooth background with a 10x10 red square moving right
    3 px a frame, and its exact masks bool [T,H,W]; with `noise`, the square is random pixels."""
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    background = np.stack([0.5 + 0.3 * np.sin(xx / 6.0), 0.45 + 0.3 * np.cos(yy / 5.0), 0.2 + 0.5 * xx / W], -1)
    rng = np.random.default_rng(1)
    frames, masks = [], []
    for k in range(T):
        mask = np.zeros((H, W), bool)
        mask[10:20, 6 + 3 * k:16 + 3 * k] = True
        image = background.copy()
        image[mask] = rng.random((mask.sum(), 3)) if noise else \
            np.array([0.9, 0.15, 0.1]) + 0.05 * np.sin(xx[mask] / 2.0)[:, None]
        frames.append((np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8))
        masks.append(mask)
    return np.stack(frames), np.stack(masks)


def write_clip(folder: Path, frames: np.ndarray, masks: np.ndarray) -> tuple[Path, Path]:
    """DAVIS-style folders: frames/00000.png ..., masks/00000.png ... (white = object)."""
    (folder / "frames").mkdir(parents=True)
    (folder / "masks").mkdir()
    for k, (frame, mask) in enumerate(zip(frames, masks)):
        cv2.imwrite(str(folder / "frames" / f"{k:05d}.png"), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(folder / "masks" / f"{k:05d}.png"), mask.astype(np.uint8) * 255)
    return folder / "frames", folder / "masks"


def config(iterations: int):
    return preset("quick", iterations=iterations, log_interval=25, eval_interval_s=1e9, init_points_per_frame=60,
                  max_gaussians=2500, densify_start_fraction=20 / iterations, densify_stop_fraction=0.75,
                  densify_interval=20)


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """The clip on disk, and its background and foreground layers fitted by `tomgs.fit`."""
    folder = tmp_path_factory.mktemp("layers")
    frames, masks = square_clip()
    frame_dir, mask_dir = write_clip(folder, frames, masks)
    bg = fit(frame_dir, folder / "bg.ply", config(100), masks=mask_dir, poses="identity", device="cpu",
             layer="background")
    fg = fit(frame_dir, folder / "fg.ply", config(150), masks=mask_dir, device="cpu", layer="foreground")
    return dict(folder=folder, frames=frames, masks=masks, frame_dir=frame_dir, mask_dir=mask_dir, bg=bg, fg=fg,
                bg_path=folder / "bg.ply", fg_path=folder / "fg.ply")


def composite(base, *layers) -> torch.Tensor:
    """[T,H,W,3] renders of scene `base` with `layers` composited over it."""
    return torch.stack([image for _, image, _ in render_layers(
        base.model.render_inputs(), base.cameras, None, [(s.model.render_inputs(), s.cameras) for s in layers])])


def test_background_ignores_the_masked_pixels(tmp_path):
    """The masked square holds random noise in one clip and the smooth square in the other: the
    background fits are identical bit for bit, so nothing under the masks reaches the model."""
    results = []
    for noise in (False, True):
        frames, masks = square_clip(noise)
        clip = Video(frames, masks, None, np.arange(T), Path("<test>"))
        results.append(fit(clip, tmp_path / f"bg{int(noise)}.ply", config(40), poses="identity",
                           device="cpu", layer="background"))
    clean, noisy = results
    assert len(clean.model) != T * 60  # densification ran
    for name, value in clean.model.parameters_by_name().items():
        assert torch.equal(value, noisy.model.parameters_by_name()[name]), name
    assert clean.clip_psnr == noisy.clip_psnr


def parked_clip(moving: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frames, masks and the true background [T,H,W,3] float of a red square parked over one spot for
    frames 0..4, then gone to the right, so that spot is seen only in frames 5..7; with `moving`, an
    unmasked blue bar slides down the background (content the background layer must follow)."""
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    background = np.stack([0.5 + 0.3 * np.sin(xx / 6.0), 0.45 + 0.3 * np.cos(yy / 5.0), 0.2 + 0.5 * xx / W], -1)
    frames, masks, truth = [], [], []
    for k in range(T):
        x = 6 if k < 5 else 30 + 3 * (k - 5)
        mask = np.zeros((H, W), bool)
        mask[10:20, x:x + 10] = True
        image = background.copy()
        if moving:
            image[2 + 3 * k:6 + 3 * k, 30:44] = (0.1, 0.2, 0.9)
        truth.append(image.copy())
        image[mask] = (0.9, 0.15, 0.1)
        frames.append((np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8))
        masks.append(mask)
    return np.stack(frames), np.stack(masks), np.stack(truth)


def layer_renders(scene) -> tuple[torch.Tensor, torch.Tensor]:
    """(colour [T,H,W,3] premultiplied, alpha [T,H,W]) of every frame of a scene."""
    g, views, Ks = scene.model.render_inputs(), scene.cameras.viewmats("cpu"), scene.cameras.Ks("cpu")
    colours, alphas = [], []
    with torch.no_grad():
        for k in range(len(scene.cameras)):
            colour, alpha, _ = rasterize(**g, viewmat=views[k], K=Ks[k], width=W, height=H,
                                         t=float(scene.cameras.times[k]))
            colours.append(colour)
            alphas.append(alpha[..., 0])
    return torch.stack(colours), torch.stack(alphas)


def test_background_fills_the_objects_place(tmp_path):
    """Where the square covers a spot (frames 0..4) the temporal background layer still shows the
    background there, opaque and in its colours, from the frames that saw it (5..7)."""
    frames, masks, truth = parked_clip()
    fit(Video(frames, masks, None, np.arange(T), Path("<test>")), tmp_path / "bg.ply", config(100),
        poses="identity", device="cpu", layer="background")
    colour, alpha = layer_renders(load_scene(tmp_path / "bg.ply"))
    under = torch.as_tensor(masks[:5])
    # measured: alpha 1.000, colour error 0.033 (frame 0) .. 0.006 (frame 4); before the layer's
    # clip-wide Gaussians and alpha target, alpha 0.88..0.98 and error 0.080..0.011
    assert float(alpha[:5][under].min()) > 0.9
    for k in range(5):
        assert float(alpha[k][under[k]].mean()) > 0.97, k
        error = (colour[k] - torch.as_tensor(truth[k]).float()).abs()[under[k]].mean()
        assert float(error) < 0.05, (k, float(error))


@pytest.mark.slow  # a long fit
def test_background_follows_moving_content(tmp_path):
    """A bar moving over the background (not masked) is still fitted by the temporal background."""
    frames, masks, truth = parked_clip(moving=True)
    fit(Video(frames, masks, None, np.arange(T), Path("<test>")), tmp_path / "bg.ply", config(300),
        poses="identity", device="cpu", layer="background")
    colour, alpha = layer_renders(load_scene(tmp_path / "bg.ply"))
    outside = torch.as_tensor(~masks)
    error = (colour - torch.as_tensor(frames).float() / 255.0).square()[outside].mean()
    # measured 25.6 dB (27.1 dB when every Gaussian started around its own frame; 24.5 dB when all
    # started clip-wide)
    assert -10 * torch.log10(error) > 24.0


def test_background_fits_the_unmasked_pixels(fitted):
    bg = load_scene(fitted["bg_path"])
    assert bg.info["layer"] == "background"
    images = torch.stack([image for _, image, _ in render_sequence(bg.model.render_inputs(), bg.cameras)])
    target = torch.as_tensor(fitted["frames"]).float() / 255.0
    outside = torch.as_tensor(~fitted["masks"])
    mse = (images - target).square()[outside].mean()
    assert -10 * torch.log10(mse) > 35.0  # measured 45.5-46.7 dB


def test_foreground_stays_on_its_plane(fitted):
    fg = load_scene(fitted["fg_path"])  # an ordinary scene: full 3D Gaussians, camera A per frame
    assert fg.info["layer"] == "foreground" and len(fg.cameras) == T
    assert len(fg.model) > T * 60  # densification cloned and split
    assert fg.model.means[:, 2].abs().max() < 1e-6
    assert fg.model.scales[:, 2].max() < 1.01e-8  # flat along the normal
    assert fg.model.quats[:, 1:3].abs().max() == 0  # rotations about the normal only
    assert torch.equal(torch.as_tensor(fg.cameras.c2w[:, :3, :3]), torch.eye(3, dtype=torch.float64).expand(T, 3, 3))


def test_foreground_is_opaque_on_the_object_and_clear_elsewhere(fitted):
    fg = load_scene(fitted["fg_path"])
    g, views, Ks = fg.model.render_inputs(), fg.cameras.viewmats("cpu"), fg.cameras.Ks("cpu")
    inside, outside = [], []
    with torch.no_grad():
        for k in range(T):
            _, alpha, _ = rasterize(**g, viewmat=views[k], K=Ks[k], width=W, height=H, t=float(fg.cameras.times[k]))
            mask = torch.as_tensor(fitted["masks"][k])
            inside.append(alpha[..., 0][mask].mean())
            outside.append(alpha[..., 0][~mask].mean())
    assert min(inside) > 0.6 and max(outside) < 0.05, (inside, outside)  # measured >= 0.79 and <= 0.016


def test_layers_composite_back_to_the_clip(fitted, tmp_path):
    bg, fg = load_scene(fitted["bg_path"]), load_scene(fitted["fg_path"])
    images = composite(bg, fg)
    target = torch.as_tensor(fitted["frames"]).float() / 255.0
    # measured 31.4 dB (26.3..34.5 per frame): the error sits on the square, where 150 iterations
    # leave the foreground 80-90% opaque; the background alone, without the square, gets 21.9 dB
    assert float(psnr(images, target).mean()) > 25.0
    without = float(psnr(composite(bg), target).mean())
    assert float(psnr(images, target).mean()) > without + 5  # the foreground puts the square back

    out = tmp_path / "out"
    result = run("render", fitted["bg_path"], "--layer", fitted["fg_path"], "-o", out, "--device", "cpu")
    assert result.exit_code == 0, result.output
    written = np.stack([cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB) for p in sorted(out.iterdir())])
    assert np.abs(written.astype(int) - (images.numpy() * 255 + 0.5).astype(int)).max() <= 1


def test_layers_add_nothing_when_absent_or_empty(fitted, tmp_path):
    bg, fg = load_scene(fitted["bg_path"]), load_scene(fitted["fg_path"])
    base = torch.stack([image for _, image, _ in render_sequence(bg.model.render_inputs(), bg.cameras)])
    assert torch.equal(composite(bg), base)
    empty = {name: value[:0] for name, value in fg.model.parameters_by_name().items()}
    save_scene(tmp_path / "none.ply", GaussianModel(**empty), fg.cameras, fg.info)  # every Gaussian removed
    assert torch.equal(composite(bg, load_scene(tmp_path / "none.ply")), base)


def test_a_layer_edited_alone_composites_again(fitted, tmp_path):
    """Moving the foreground 8 px down the frame moves the square in the composite and leaves the
    background alone away from the object."""
    bg, fg = load_scene(fitted["bg_path"]), load_scene(fitted["fg_path"])
    before = composite(bg, fg)
    params = {name: value.detach().clone() for name, value in fg.model.parameters_by_name().items()}
    params["means"][:, 1] += 8.0 / fg.cameras.focal  # +y is down the frame, as in every scene
    save_scene(tmp_path / "moved.ply", GaussianModel(**params), fg.cameras, fg.info)
    after = composite(bg, load_scene(tmp_path / "moved.ply"))

    masks = fitted["masks"]
    moved = np.zeros_like(masks)
    moved[:, 8:] = masks[:, :-8]
    target = np.zeros_like(fitted["frames"])
    target[:, 8:] = fitted["frames"][:, :-8]
    there = torch.as_tensor(moved)
    error = (after - torch.as_tensor(target).float() / 255.0).square()[there].mean()
    assert -10 * torch.log10(error) > 17.0  # measured 21 dB (22 dB for the unmoved square)
    away = ~torch.as_tensor(np.stack([cv2.dilate((m | n).astype(np.uint8), np.ones((11, 11), np.uint8))
                                      for m, n in zip(masks, moved)]) > 0)  # 5 px from where it was or is
    assert (after - before).abs()[away].max() < 0.03  # measured 0.003-0.008: faint temporal ghosts only


def test_fit_layer_from_the_command_line(fitted, tmp_path):
    result = run("fit", fitted["frame_dir"], "--masks", fitted["mask_dir"], "--layer", "foreground", "-o",
                 tmp_path / "fg.ply", "--preset", "quick", "--iterations", "5", "--device", "cpu")
    assert result.exit_code == 0, result.output
    assert "foreground layer" in result.output and load_scene(tmp_path / "fg.ply").info["layer"] == "foreground"
    assert "full-clip PSNR" in result.output  # its views: every frame and its mirror, not "80 of 40 frames"


def _bad_masks(folder: Path, kind: str, masks: np.ndarray) -> Path:
    out = folder / f"masks-{kind}"
    out.mkdir()
    for k, mask in enumerate(masks):
        if kind == "fewer" and k == T - 1:
            break
        image = mask.astype(np.uint8) * 255
        if kind == "size":
            image = cv2.resize(image, (W // 2, H // 2))
        if kind == "empty":
            image[:] = 0
        cv2.imwrite(str(out / f"{k:05d}.png"), image)
    return out


@pytest.mark.parametrize("layer, masks, message", [
    ("background", None, "needs masks"),
    ("foreground", "missing", "does not exist"),
    ("foreground", "fewer", "7 masks but the clip has 8 frames"),
    ("background", "size", "masks must have the size"),
    ("foreground", "empty", "empty in every frame"),
])
def test_fit_layer_bad_input(fitted, tmp_path, layer, masks, message):
    work = tmp_path / "work"
    work.mkdir()
    args = ["fit", fitted["frame_dir"], "--layer", layer, "-o", work / "s.ply", "--preset", "quick",
            "--iterations", "5", "--device", "cpu", "--poses", "identity"]
    if masks is not None:
        args += ["--masks", tmp_path / "nowhere" if masks == "missing" else _bad_masks(tmp_path, masks, fitted["masks"])]
    result = run(*args)
    assert result.exit_code == 2, result.output
    assert message in result.output
    assert list(work.iterdir()) == []


@pytest.mark.parametrize("change, message", [("frames", "has 4 frames"), ("size", "is 24x16")])
def test_render_layer_mismatch(fitted, tmp_path, change, message):
    fg = load_scene(fitted["fg_path"])
    cameras = fg.cameras[:4] if change == "frames" else fg.cameras.resized(W // 2, H // 2)
    save_scene(tmp_path / "other.ply", fg.model, cameras, fg.info)
    result = run("render", fitted["bg_path"], "--layer", tmp_path / "other.ply", "-o", tmp_path / "out.mp4",
                 "--device", "cpu")
    assert result.exit_code == 2, result.output
    assert message in result.output and "other.ply" in result.output
    assert not (tmp_path / "out.mp4").exists()
