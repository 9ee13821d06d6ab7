"""Stiff and extreme inputs: outputs and gradients stay finite and match the reference where it is defined."""

from __future__ import annotations

import math

import pytest
import torch

import tomgs
from scenes import INPUT_NAMES, devices, random_scene, render_both
from test_raster import assert_matches_reference

DEVICES = devices()


def with_rows(scene: dict, rows: slice, **values) -> dict:
    """Copy of `scene` with the given per-Gaussian fields overwritten on `rows`."""
    out = {k: (v.clone() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    for name, value in values.items():
        out[name][rows] = torch.as_tensor(value, dtype=out[name].dtype)
    return out


def camera_point(scene: dict, x: float, y: float, z: float) -> torch.Tensor:
    """World position of camera-space point (x, y, z)."""
    c2w = torch.linalg.inv(scene["viewmat"])
    return c2w[:3, :3] @ torch.tensor([x, y, z], dtype=torch.float64) + c2w[:3, 3]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("sigma", [1e-6, 1e-3, 1.0, 1e3])
@pytest.mark.parametrize("offset", [0.0, 0.5, 3.0, 1e4])
def test_temporal_scales(sigma, offset, device):
    """t at the temporal mean (offset 0), inside (0.5, 3 sigma) and far outside (1e4 sigma)."""
    scene = random_scene(100, n=60)
    t = 0.4
    t_mean = t - offset * sigma
    scene = with_rows(scene, slice(0, 30), t_means=t_mean, t_scales=sigma)
    scene["t"] = t
    meta = assert_matches_reference(scene, device)
    alive = meta["opacities_t"][:30] >= 1 / 255
    if offset >= 1e4:
        assert not alive.any()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("scale", [1e-8, 1e4])
def test_tiny_and_huge_scales(scale, device):
    scene = random_scene(110, n=40)
    scene = with_rows(scene, slice(0, 10), scales=scale)
    assert_matches_reference(scene, device)


@pytest.mark.parametrize("device", DEVICES)
def test_flat_and_needle_gaussians(device):
    scene = random_scene(111, n=40)
    scene = with_rows(scene, slice(0, 5), scales=[3.0, 3.0, 1e-8])
    scene = with_rows(scene, slice(5, 10), scales=[1e-8, 1e-8, 2.0])
    assert_matches_reference(scene, device)


@pytest.mark.parametrize("device", DEVICES)
def test_degenerate_quaternions(device):
    scene = random_scene(120, n=40)
    scene = with_rows(scene, slice(0, 5), quats=[0.0, 0.0, 0.0, 0.0])
    scene["quats"][5:10] *= 1e3
    scene["quats"][10:15] *= 1e-3
    scene["quats"][15:20] *= 1e-13 / scene["quats"][15:20].norm(dim=-1, keepdim=True)  # below the epsilon
    for row in range(15, 20):
        scene["means"][row] = camera_point(scene, 0.1 * (row - 17), 0.0, 2.0 + 0.1 * row)  # no depth ties
    scene["scales"][15:20] = torch.tensor([0.3, 0.1, 0.05], dtype=torch.float64)
    scene["t_scales"][15:20] = 1e3
    assert_matches_reference(scene, device)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("opacity", [0.0, 1.0 - 1e-7])
def test_opacity_limits(opacity, device):
    scene = random_scene(130, n=40)
    scene = with_rows(scene, slice(0, 20), opacities=opacity, t_scales=1e3)
    # large Gaussians in front, so that some pixels see a raw alpha above the 0.99 clamp
    for row in range(3):
        scene["means"][row] = camera_point(scene, 0.2 * row - 0.2, 0.1 * row, 1.0 + row)
    scene["scales"][:3] = 0.4
    meta = assert_matches_reference(scene, device)
    if opacity == 0.0:
        assert (meta["radii"][:20] == 0).all()


@pytest.mark.parametrize("device", DEVICES)
def test_depth_extremes(device):
    scene = random_scene(140, n=30)
    points = {
        0: (0.0, 0.0, 0.01),  # exactly on the near plane: culled
        1: (0.001, 0.0, 0.0101),  # just in front of it
        2: (0.0, 0.0, -1.0),  # behind the camera
        3: (0.0, 0.0, 0.0),  # at the camera centre
        4: (1e3, -2e3, 1e9),  # huge depth
        5: (0.0, 0.0, 2e10),  # beyond the far plane
    }
    for row, xyz in points.items():
        scene["means"][row] = camera_point(scene, *xyz)
    scene["t_scales"][:6] = 1e3
    meta = assert_matches_reference(scene, device)
    assert meta["radii"][0].max() == 0 and meta["radii"][2].max() == 0 and meta["radii"][5].max() == 0


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("size", [(1, 1), (1, 7), (17, 3), (31, 33)])
def test_odd_image_sizes(size, device):
    width, height = size
    scene = random_scene(150, n=50, width=width, height=height)
    scene["K"][0, 2], scene["K"][1, 2] = width / 2, height / 2
    assert_matches_reference(scene, device)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("n", [0, 1])
def test_zero_and_one_gaussian(n, device):
    scene = random_scene(160, n=8)
    scene = {k: (v[:n] if isinstance(v, torch.Tensor) and v.shape[:1] == (8,) else v) for k, v in scene.items()}
    if n == 1:
        scene["means"][0] = camera_point(scene, 0.0, 0.0, 2.0)
        scene["t_scales"][0] = 1e3
    (image, alpha, meta), (ref_image, _, _), _, _ = render_both(scene, device)
    assert meta["n_visible"] == n
    if n == 0:
        assert torch.allclose(image.double().cpu(), ref_image) and (alpha == 0).all()
        image.sum().backward()  # the background still gets a gradient
    else:
        assert_matches_reference(scene, device)


def test_non_finite_gaussians_are_culled():
    scene = random_scene(170, n=30)
    scene["scales"][0] = math.inf
    scene["means"][1] = math.nan
    scene["quats"][2] = math.inf
    scene["t_scales"][3] = 0.0
    scene["t_means"][3] = scene["t"]  # 0 / 0
    tensors = {k: scene[k].requires_grad_(True) for k in INPUT_NAMES}
    image, alpha, meta = tomgs.rasterize(**tensors, width=scene["width"], height=scene["height"], t=scene["t"])
    assert torch.isfinite(image).all() and torch.isfinite(alpha).all()
    assert (meta["radii"][:4] == 0).all()
    grads = torch.autograd.grad(image.sum() + alpha.sum(), list(tensors.values()))
    for name, grad in zip(INPUT_NAMES, grads):
        assert torch.isfinite(grad).all(), name


def test_intersection_overflow_is_a_clear_error():
    """2^31 tile intersections would overflow int32 offsets: the renderer refuses before allocating."""
    n, width, height = 140_000, 1920, 1080  # each Gaussian covers all 8160 tiles: 1.14e9 intersections
    means = torch.tensor([[0.0, 0.0, 1.0]]).repeat(n, 1)
    K = torch.tensor([[1000.0, 0.0, 960.0], [0.0, 1000.0, 540.0], [0.0, 0.0, 1.0]])
    with pytest.raises(tomgs.RenderError, match="intersections"):
        tomgs.rasterize(means, torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.full((n, 3), 100.0),
                        torch.full((n,), 0.9), torch.rand(n, 3), torch.zeros(n), torch.ones(n),
                        torch.eye(4), K, width, height, 0.0)
