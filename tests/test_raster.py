"""The Warp rasterizer against the float64 torch reference: values, gradients, meta, temporal culling."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

import tomgs
from tomgs.constants import ALPHA_MIN
from scenes import INPUT_NAMES, devices, random_scene, render_both, rel_l2

IMAGE_TOL = 1e-4  # max abs error of image and alpha
GRAD_TOL = 1e-3  # relative L2 error of each input's gradient

DEVICES = devices()


def assert_matches_reference(scene: dict, device: str, grad_tol: float = GRAD_TOL, **kw) -> dict:
    (image, alpha, meta), (ref_image, ref_alpha, ref_meta), ours_in, ref_in = render_both(scene, device, **kw)
    assert image.shape == (scene["height"], scene["width"], 3) and alpha.shape == (scene["height"], scene["width"], 1)
    assert image.device.type == device
    assert (image.double().cpu() - ref_image).abs().max() <= IMAGE_TOL
    assert (alpha.double().cpu() - ref_alpha).abs().max() <= IMAGE_TOL
    assert torch.equal(meta["radii"].long().cpu(), ref_meta["radii"])
    assert meta["n_visible"] == ref_meta["n_visible"]

    g = torch.Generator().manual_seed(7)
    w_image = torch.rand(ref_image.shape, generator=g, dtype=torch.float64) - 0.3
    w_alpha = torch.rand(ref_alpha.shape, generator=g, dtype=torch.float64) - 0.3
    loss = (image * w_image.to(image)).sum() + (alpha * w_alpha.to(alpha)).sum()
    ref_loss = (ref_image * w_image).sum() + (ref_alpha * w_alpha).sum()
    grads = torch.autograd.grad(loss, ours_in)
    ref_grads = torch.autograd.grad(ref_loss, ref_in)
    for name, grad, ref_grad in zip(INPUT_NAMES, grads, ref_grads):
        assert torch.isfinite(grad).all(), name
        assert rel_l2(grad, ref_grad) <= grad_tol, (name, rel_l2(grad, ref_grad))
    return meta


def render_three(scene: dict, device: str, t: float | None = None, **kw):
    """(ours, float64 reference, float32 reference, their input tensors) on the float32-representable
    values of `scene`, at time t (a float64, not rounded; default scene["t"]); gradients enabled."""
    scene = {k: (v.float().double() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    t = scene["t"] if t is None else t
    out = []
    for fn, where, extra in ((tomgs.rasterize, device, {}), (tomgs.rasterize_reference, "cpu", {}),
                             (tomgs.rasterize_reference, "cpu", dict(dtype=torch.float32))):
        tensors = [scene[k].detach().to(where).requires_grad_(True) for k in INPUT_NAMES]
        outputs = fn(**dict(zip(INPUT_NAMES, tensors)), width=scene["width"], height=scene["height"], t=t, **kw,
                     **extra)
        out.append((outputs, tensors))
    return out


def radii_match(radii: torch.Tensor, ref_radii: torch.Tensor, extent: torch.Tensor) -> bool:
    """Equal, but for a difference of one where the float64 radius before rounding up lies within
    float32's reach of an integer (a tie no float32 computation can call)."""
    radii, ref_radii = radii.long().cpu(), ref_radii.long().cpu()
    tie = (extent - extent.round()).abs() <= 1e-5 * extent + 1e-6
    return bool(((radii == ref_radii) | (tie & ((radii - ref_radii).abs() <= 1))).all())


def assert_matches_within_float32(scene: dict, device: str, factor: float = 3.0, t: float | None = None,
                                  **kw) -> dict:
    """`assert_matches_reference` where float32 itself is the limit: image, alpha and each gradient
    within IMAGE_TOL / GRAD_TOL of the float64 reference, or within `factor` times the error of the
    float32 torch reference on the same scene where that is larger (inputs on which float32
    arithmetic cannot do better, e.g. a needle pointing at the camera); radii equal up to ties."""
    (ours, ours_in), (ref, ref_in), (f32, f32_in) = render_three(scene, device, t, **kw)
    (image, alpha, meta), (ref_image, ref_alpha, ref_meta), (f32_image, f32_alpha, _) = ours, ref, f32
    assert torch.isfinite(image).all() and torch.isfinite(alpha).all()
    for got, want, yard in ((image, ref_image, f32_image), (alpha, ref_alpha, f32_alpha)):
        got, want, yard = got.detach().double().cpu(), want.detach(), yard.detach().double()
        tol = max(IMAGE_TOL, factor * float((yard - want).abs().max()))
        assert float((got - want).abs().max()) <= tol, (float((got - want).abs().max()), tol)
    assert radii_match(meta["radii"], ref_meta["radii"], ref_meta["extent"])
    assert int(meta["n_visible"]) == ref_meta["n_visible"]

    g = torch.Generator().manual_seed(7)
    w_image = torch.rand(ref_image.shape, generator=g, dtype=torch.float64) - 0.3
    w_alpha = torch.rand(ref_alpha.shape, generator=g, dtype=torch.float64) - 0.3
    grads = []
    for (img, alp), tensors in (((image, alpha), ours_in), ((ref_image, ref_alpha), ref_in),
                                ((f32_image, f32_alpha), f32_in)):
        loss = (img * w_image.to(img)).sum() + (alp * w_alpha.to(alp)).sum()
        grads.append(torch.autograd.grad(loss, tensors))
    for name, grad, ref_grad, f32_grad in zip(INPUT_NAMES, *grads):
        assert torch.isfinite(grad).all(), name
        tol = max(GRAD_TOL, factor * rel_l2(f32_grad, ref_grad))
        assert rel_l2(grad, ref_grad) <= tol, (name, rel_l2(grad, ref_grad), tol)
    return meta


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("seed", range(6))
def test_random_scenes_match_reference(seed, device):
    scene = random_scene(seed)
    meta = assert_matches_reference(scene, device)
    # the scene really exercises culling and overlap
    assert 0 < meta["n_visible"] < scene["means"].shape[0]
    assert meta["n_intersections"] > meta["n_visible"]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
def test_sh_colors_match_reference(sh_degree, device):
    assert_matches_reference(random_scene(10 + sh_degree, n=60, sh_degree=sh_degree), device)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("size", [(16, 16), (33, 17), (64, 48)])
def test_image_sizes(size, device):
    width, height = size
    assert_matches_reference(random_scene(20, n=80, width=width, height=height), device)


@pytest.mark.parametrize("device", DEVICES)
def test_dense_overlap_stops_on_transmittance(device):
    scene = random_scene(30, n=300)
    c2w = torch.linalg.inv(scene["viewmat"])
    centre = c2w[:3, :3] @ torch.tensor([0.0, 0.0, 2.5], dtype=torch.float64) + c2w[:3, 3]
    scene["means"] = centre + 0.05 * torch.randn(300, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    scene["t_scales"] = torch.full((300,), 10.0, dtype=torch.float64)
    (image, alpha, meta), _, _, _ = render_both(scene, device)
    assert alpha.max() > 0.999  # compositing stopped on transmittance, not on running out of Gaussians
    assert_matches_reference(scene, device)


@pytest.mark.parametrize("device", DEVICES)
def test_dead_gaussians_cost_no_tile_work(device):
    """A Gaussian whose temporal opacity is below 1/255 at t is culled in projection."""
    scene = random_scene(40, n=100)
    scene["t"] = 0.5
    scene["t_means"][:50] = 0.5
    scene["t_scales"][:50] = 1.0
    scene["t_means"][50:] = 0.0
    scene["t_scales"][50:] = 0.05  # z = 10 at t = 0.5: o = a exp(-50), dead
    (image, alpha, meta), (ref_image, _, _), _, _ = render_both(scene, device)
    assert meta["n_alive"] == 50
    assert (meta["radii"][50:] == 0).all()
    assert (meta["opacities_t"][50:] < 1 / 255).all()
    alive_only = {k: (v[:50] if isinstance(v, torch.Tensor) and v.shape[:1] == (100,) else v) for k, v in scene.items()}
    (image_alive, _, meta_alive), _, _, _ = render_both(alive_only, device)
    assert torch.equal(image, image_alive)
    assert meta["n_intersections"] == meta_alive["n_intersections"]


@pytest.mark.parametrize("device", DEVICES)
def test_temporal_opacity_formula(device):
    scene = random_scene(50, n=40)
    (_, _, meta), (_, _, ref_meta), _, _ = render_both(scene, device)
    z = (scene["t"] - scene["t_means"]) / scene["t_scales"]
    expected = scene["opacities"] * torch.exp(-0.5 * z * z)
    assert torch.allclose(meta["opacities_t"].double().cpu(), expected, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("device", DEVICES)
def test_meta_screen_space_gradients(device):
    """meta['means2d'] can retain its gradient, as densification strategies need."""
    scene = random_scene(60, n=50)
    (image, _, meta), _, _, _ = render_both(scene, device)
    meta["means2d"].retain_grad()
    image.sum().backward()
    grad = meta["means2d"].grad
    assert grad is not None and grad.shape == (50, 2)
    visible = meta["radii"].amax(-1) > 0
    assert (grad[~visible] == 0).all() and grad[visible].abs().sum() > 0


def test_float32_inputs_give_float32_outputs():
    scene = random_scene(70, n=30, dtype=torch.float32)
    named = {k: scene[k] for k in INPUT_NAMES if k != "background"}
    image, alpha, meta = tomgs.rasterize(**named, width=scene["width"], height=scene["height"], t=scene["t"])
    assert image.dtype == torch.float32 and alpha.dtype == torch.float32
    assert meta["radii"].dtype == torch.int32


def test_import_is_cheap():
    """Importing tomgs loads no Warp (so compiles no kernel and touches no GPU)."""
    code = "import sys, tomgs; print(tomgs.__version__); assert 'warp' not in sys.modules, 'warp imported'; " \
           "assert 'tomgs.render' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True)


@pytest.mark.parametrize("device", DEVICES)
def test_sequences_gather_only_what_is_alive_and_render_the_same(device):
    """render_sequence renders each few frames from the Gaussians alive around their times: the
    images equal a render of every Gaussian, and a Gaussian alive only at one frame is kept."""
    from tomgs.cameras import Cameras
    from tomgs.render import alive_window, render_sequence

    scene = random_scene(11, n=300, width=40, height=30)
    g = torch.Generator().manual_seed(3)
    n = scene["means"].shape[0]
    gaussians = {k: scene[k].float().to(device) for k in ("means", "quats", "scales", "opacities", "colors")}
    gaussians["t_means"] = torch.rand(n, generator=g).to(device)
    gaussians["t_scales"] = (10.0 ** (-3 + 3 * torch.rand(n, generator=g))).to(device)  # 1e-3 .. 1: mostly short
    gaussians["opacities"][0] = ALPHA_MIN  # alive only at the instant t = t_mean
    gaussians["t_means"][0] = 12 / 29
    viewmat = scene["viewmat"].numpy()
    cams = Cameras.create(np.repeat(np.linalg.inv(viewmat)[None], 30, 0), scene["K"].numpy(), 40, 30)
    frames = list(range(30))[::-1]
    alive_counts = []
    for k, image, meta in render_sequence(gaussians, cams, frames, device=device, to_cpu=False):
        full, _, full_meta = tomgs.rasterize(**gaussians, viewmat=scene["viewmat"].float().to(device),
                                             K=scene["K"].float().to(device), width=40, height=30,
                                             t=float(cams.times[k]))
        assert torch.equal(image, full.clamp(0, 1)), k
        assert int(meta["n_alive"]) == int(full_meta["n_alive"])
        alive_counts.append(int(meta["radii"].shape[0]))
    assert max(alive_counts) < n  # some frames really rendered a subset
    first, last = alive_window(gaussians["opacities"], gaussians["t_means"], gaussians["t_scales"])
    assert first[0] <= 12 / 29 <= last[0]


def test_an_unfinished_sequence_leaves_gradients_on():
    """render_sequence renders without gradients, but a caller that stops early (or between frames)
    must find autograd as it left it."""
    from tomgs.cameras import Cameras
    from tomgs.render import render_sequence

    scene = random_scene(5, n=40, width=16, height=12)
    gaussians = {k: scene[k].float() for k in ("means", "quats", "scales", "opacities", "colors")}
    gaussians["t_means"], gaussians["t_scales"] = torch.zeros(40), torch.ones(40)
    cams = Cameras.create(np.repeat(np.linalg.inv(scene["viewmat"].numpy())[None], 3, 0), scene["K"].numpy(), 16, 12)
    frames = render_sequence(gaussians, cams)
    next(frames)
    assert torch.is_grad_enabled()
    del frames
    assert torch.is_grad_enabled()
