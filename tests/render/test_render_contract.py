"""The contract of `rasterize`: empty frames at any call, out-of-contract inputs refused with a
RenderError naming them, times finer than float32 resolves, quaternions of any finite norm."""

from __future__ import annotations

import math
import subprocess
import sys
import textwrap

import pytest
import torch

import tomgs
from scenes import INPUT_NAMES, devices, random_scene, rel_l2, split
from tests.render.test_raster import assert_matches_reference

DEVICES = devices()


def run_fresh(code: str) -> None:
    """Run `code` in a new Python process (nothing rendered yet); fail with its stderr."""
    done = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and "ok" in done.stdout, done.stderr[-3000:]


def test_empty_first_frame_then_any():
    """N = 0 on the very first call of a process used to break every later call ('NoneType' has no
    attribute 'set_dim'): empty, full, empty, full again, forward and backward."""
    run_fresh("""
        import torch, tomgs
        K = torch.tensor([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]])
        for n in (0, 5, 0, 3, 7, 0):
            g = torch.Generator().manual_seed(n)
            means = torch.cat([torch.rand(n, 2, generator=g) - 0.5, 2 + torch.rand(n, 1, generator=g)], 1)
            inputs = [means, torch.randn(n, 4, generator=g), torch.full((n, 3), 0.1), torch.full((n,), 0.7),
                      torch.rand(n, 3, generator=g), torch.zeros(n), torch.ones(n)]
            inputs = [x.requires_grad_(True) for x in inputs]
            image, alpha, meta = tomgs.rasterize(*inputs, torch.eye(4), K, 32, 24, 0.0)
            assert int(meta["n_visible"]) == n, (n, meta["n_visible"])
            (image.sum() + alpha.sum()).backward()
            assert all(torch.isfinite(x.grad).all() for x in inputs)
        print("ok")
    """)


def test_render_sequence_whose_first_frames_are_empty():
    """What `tomgs render` does with a scene whose Gaussians appear only late in the clip."""
    run_fresh("""
        import numpy as np, torch
        from tomgs.cameras import Cameras, intrinsics
        from tomgs.render.sequence import render_sequence
        n = 20
        g = torch.Generator().manual_seed(0)
        gaussians = dict(means=torch.cat([torch.rand(n, 2, generator=g) - 0.5, 2 + torch.rand(n, 1, generator=g)], 1),
                         quats=torch.randn(n, 4, generator=g), scales=torch.full((n, 3), 0.1),
                         opacities=torch.full((n,), 0.8), colors=torch.rand(n, 3, generator=g),
                         t_means=torch.full((n,), 1.0), t_scales=torch.full((n,), 0.02))
        cams = Cameras.create(np.repeat(np.eye(4)[None], 20, 0), intrinsics(30.0, 32, 24), 32, 24)
        alive = [int(meta["n_alive"]) for k, image, meta in render_sequence(gaussians, cams)]
        assert alive[0] == 0 and alive[-1] == n, alive
        print("ok")
    """)


# ---- out-of-contract inputs: a RenderError that names them ---------------------------------------

def _scene(n: int = 30) -> dict:
    scene = random_scene(200, n=max(n, 1))
    if n == 0:
        scene = {k: (v[:0] if isinstance(v, torch.Tensor) and v.shape[:1] == (1,) and k not in ("viewmat", "K")
                     else v) for k, v in scene.items()}
    return {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}


def _call(scene: dict):
    named = {k: scene[k] for k in INPUT_NAMES}
    return tomgs.rasterize(**named, width=scene["width"], height=scene["height"], t=scene["t"],
                           **{k: scene[k] for k in ("near", "far") if k in scene})


def _set(scene: dict, name: str, index, value) -> dict:
    scene = {k: (v.clone() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    if index is None:
        scene[name] = value
    else:
        scene[name][index] = value
    return scene


BAD_GAUSSIANS = [  # (input, index, value)
    ("opacities", 3, 1.5),
    ("opacities", 3, 1.0 + 1e-6),
    ("opacities", 0, math.inf),
    ("opacities", -1, -math.inf),
    ("opacities", 7, math.nan),
    ("opacities", 7, -0.25),
    ("scales", (4, 1), -0.01),
    ("scales", (4, 2), -math.inf),
    ("t_scales", 5, -0.3),
    ("t_scales", 5, -math.inf),
]
BAD_CAMERAS = [
    ("K", (0, 0), 0.0),  # fx
    ("K", (0, 0), -40.0),
    ("K", (1, 1), 0.0),  # fy
    ("K", (1, 1), -1e-30),
    ("K", (0, 2), math.nan),
    ("K", (1, 2), math.inf),
    ("K", (0, 0), math.nan),
    ("viewmat", (0, 3), math.nan),
    ("viewmat", (2, 2), math.inf),
    ("background", 1, math.nan),
    ("background", 0, -math.inf),
]
BAD_SCALARS = [
    ("width", None, math.nan),
    ("width", None, math.inf),
    ("width", None, 2.5),
    ("width", None, 0),
    ("width", None, "32"),
    ("height", None, math.nan),
    ("height", None, -3),
    ("t", None, math.nan),
    ("t", None, math.inf),
    ("t", None, -math.inf),
    ("t", None, 1e39),  # beyond float32
    ("near", None, math.nan),
    ("near", None, 0.0),
    ("far", None, math.nan),
    ("far", None, 0.001),
]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("name,index,value", BAD_GAUSSIANS + BAD_CAMERAS + BAD_SCALARS)
def test_out_of_contract_inputs_are_refused(name, index, value, device):
    scene = {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in _set(_scene(), name, index, value).items()}
    with pytest.raises(tomgs.RenderError, match=name):
        _call(scene)


@pytest.mark.parametrize("name,index,value", BAD_CAMERAS + BAD_SCALARS)
def test_out_of_contract_cameras_are_refused_with_no_gaussians(name, index, value):
    with pytest.raises(tomgs.RenderError, match=name):
        _call(_set(_scene(0), name, index, value))


def test_the_message_says_which_gaussian():
    scene = _set(_scene(), "opacities", 17, 2.0)
    scene["opacities"][21] = math.inf
    with pytest.raises(tomgs.RenderError, match=r"opacities .*2 of 30.*index 17.*2\.0"):
        _call(scene)


@pytest.mark.parametrize("device", DEVICES)
def test_edges_of_the_contract_are_accepted(device):
    """Opacity 0 and 1, zero scales, zero temporal scale (culled), an infinite far plane."""
    scene = _scene()
    scene["opacities"][:3] = torch.tensor([0.0, 1.0, 1.0])
    scene["scales"][3] = 0.0
    scene["t_scales"][4] = 0.0
    scene["far"] = math.inf
    image, alpha, meta = _call({k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in scene.items()})
    assert torch.isfinite(image).all() and meta["radii"][0].max() == 0 and meta["radii"][4].max() == 0


# ---- time finer than float32: t is a float64 and (t - m) is formed before rounding --------------

@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("sigma", [1e-9, 1e-8, 1e-7, 1e-6])
@pytest.mark.parametrize("offset", [-2.5, -0.7, 0.0, 0.4, 1.9])
def test_time_resolves_below_float32(sigma, offset, device):
    """t = m + offset * sigma with m a float32 time and sigma below float32's resolution of t (6e-8
    near 0.5): rounding t to float32 used to move the Gaussian by up to its whole window."""
    scene = random_scene(210, n=40)
    m = float(torch.tensor(0.4375 + 1e-3 * 3 ** 0.5, dtype=torch.float32))
    t = m + offset * sigma
    scene["t_means"][:20] = m
    scene["t_scales"][:20] = sigma
    tensors, _ = split({k: (v.float().double() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()},
                       device)
    named = dict(zip(INPUT_NAMES, tensors))
    _, _, meta = tomgs.rasterize(**named, width=scene["width"], height=scene["height"], t=t)
    expected = scene["opacities"][:20].float().double() * math.exp(-0.5 * offset ** 2)
    assert torch.allclose(meta["opacities_t"][:20].double().cpu(), expected, rtol=1e-5, atol=0), \
        (meta["opacities_t"][:3], expected[:3])
    # and against the float64 reference, gradients included (t_means and t_scales carry 1/sigma)
    ref_in, _ = split({k: (v.float().double() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}, "cpu")
    ref = tomgs.rasterize_reference(**dict(zip(INPUT_NAMES, ref_in)), width=scene["width"], height=scene["height"], t=t)
    ours = tomgs.rasterize(**named, width=scene["width"], height=scene["height"], t=t)
    assert (ours[0].double().cpu() - ref[0]).abs().max() <= 1e-4
    for name, grad, ref_grad in zip(INPUT_NAMES, torch.autograd.grad(ours[0].sum(), tensors),
                                    torch.autograd.grad(ref[0].sum(), ref_in)):
        assert rel_l2(grad, ref_grad) <= 1e-3, (name, rel_l2(grad, ref_grad))


# ---- quaternions of any finite norm --------------------------------------------------------------

@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("norm", [1e-30, 1e-20, 1e19, 1e25, 1e36])
def test_quaternions_of_any_norm(norm, device):
    """|q|^2 overflowed float32 from |q| ~ 1.8e19 (and underflowed below 1e-19): such Gaussians
    rendered with the identity rotation. Now q / |q| is formed without squaring q."""
    scene = random_scene(220, n=40)
    scene["quats"][:20] *= norm / scene["quats"][:20].norm(dim=-1, keepdim=True)
    scene["t_scales"][:20] = 1e3
    assert_matches_reference(scene, device)


@pytest.mark.parametrize("device", DEVICES)
def test_the_largest_quaternions_render_like_unit_ones(device):
    scene = random_scene(221, n=40)
    unit = scene["quats"] / scene["quats"].norm(dim=-1, keepdim=True)
    big = dict(scene, quats=(unit * 3e38).float())  # float32's largest finite decade
    small = dict(scene, quats=unit)
    images = []
    for s in (big, small):
        tensors, _ = split(s, device, requires_grad=False)
        images.append(tomgs.rasterize(**dict(zip(INPUT_NAMES, tensors)), width=s["width"], height=s["height"],
                                      t=s["t"])[0])
    assert (images[0] - images[1]).abs().max() <= 1e-5
