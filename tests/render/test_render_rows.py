"""`rasterize(..., rows=...)`: render some Gaussians of a cloud without gathering its inputs (the
alive index's frames). The kernels read the rows' inputs and write their gradients in place; the
result must be what rendering the gathered inputs gives, images and gradients, and bad rows must be
refused before anything is read out of range."""

from __future__ import annotations

import pytest
import torch

import tomgs
from tomgs.render.inputs import RenderError
from tomgs.render.frame import render_frame
from scenes import devices, random_scene

DEVICES = devices()
NAMES = ("means", "quats", "scales", "opacities", "colors", "t_means", "t_scales")


def leaves(scene: dict, device: str) -> dict:
    return {name: scene[name].float().to(device).requires_grad_(True) for name in NAMES}


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("sh_degree", [None, 0, 2])
@pytest.mark.parametrize("camera_grads", [False, True])
@pytest.mark.parametrize("repeated", [False, True])
def test_rows_render_what_their_gathered_inputs_render(device, sh_degree, camera_grads, repeated):
    """A subset, ascending; or with rows listed twice (rendered twice, gradients summed)."""
    scene = random_scene(21, n=300, sh_degree=sh_degree)
    g = torch.Generator().manual_seed(5)
    rows = torch.sort(torch.randperm(300, generator=g)[:170]).values
    if repeated:
        rows = torch.sort(torch.cat([rows, rows[::7]])).values
    rows = rows.to(device)
    weights = torch.rand(37, 45, 3, generator=g).to(device)
    results = []
    for gathered in (False, True):
        p = leaves(scene, device)
        viewmat = scene["viewmat"].float().to(device).requires_grad_(camera_grads)
        K = scene["K"].float().to(device).requires_grad_(camera_grads)
        inputs = {name: value.index_select(0, rows) for name, value in p.items()} if gathered else p
        image, alpha, meta = tomgs.rasterize(**inputs, viewmat=viewmat, K=K, width=45, height=37, t=0.4,
                                             rows=None if gathered else rows)
        ((image * weights).sum() + alpha.sum()).backward()
        grads = {name: value.grad for name, value in p.items()}
        if camera_grads:
            grads.update(viewmat=viewmat.grad, K=K.grad)
        results.append((image, alpha, meta, grads))
    (image, alpha, meta, grads), (want, want_alpha, want_meta, want_grads) = results
    assert meta["n_alive"] > 20 and meta["n_intersections"] > 0
    assert torch.equal(image, want) and torch.equal(alpha, want_alpha)
    for key in ("radii", "means2d", "conics", "depths", "opacities_t", "n_visible", "n_alive", "n_intersections"):
        assert (torch.equal(meta[key], want_meta[key]) if torch.is_tensor(meta[key]) else meta[key] == want_meta[key]), key
    unrendered = torch.ones(300, dtype=torch.bool)
    unrendered[rows.cpu()] = False
    for name, grad in grads.items():
        # float32 sums of the same terms in another order: a repeated row's by atomics; on a GPU every
        # Gaussian's by atomics across tiles, in an order that changes from run to run (H100: the same
        # gathered inputs rendered twice differ by up to 1.2e-6 of the largest means gradient, and by
        # 1.4e-5 of the viewmat's, a sum over every Gaussian whose terms cancel far below their size)
        tolerance = 1e-6 if device == "cpu" else 1e-5 * (1 if name in NAMES else 10)
        scale = float(want_grads[name].abs().max())
        assert torch.allclose(grad, want_grads[name], rtol=tolerance, atol=tolerance * scale), name
        if name in NAMES:
            assert not grad[unrendered.to(device)].any(), name  # the rest keep exactly zero


@pytest.mark.parametrize("device", DEVICES)
def test_rows_do_not_wait_either(device):
    scene = random_scene(22, n=200)
    p = {name: scene[name].float().to(device) for name in NAMES}
    camera = dict(viewmat=scene["viewmat"].float().to(device), K=scene["K"].float().to(device), width=45, height=37)
    rows = torch.arange(0, 200, 3, device=device)
    want, _, _ = tomgs.rasterize(**p, **camera, t=0.3, rows=rows)
    image, _, _, counts = render_frame(**p, **camera, t=0.3, rows=rows, defer=True)
    assert counts is not None and not counts.overflowed and torch.equal(image, want)


@pytest.mark.parametrize("device", DEVICES)
def test_bad_rows_are_refused(device):
    scene = random_scene(23, n=50)
    p = {name: scene[name].float().to(device) for name in NAMES}
    camera = dict(viewmat=scene["viewmat"].float().to(device), K=scene["K"].float().to(device), width=45, height=37)
    for rows in (torch.tensor([3, 50], device=device), torch.tensor([-1, 4], device=device)):
        with pytest.raises(RenderError, match=r"rows must index the 50 Gaussians.*1 of 2 do not"):
            tomgs.rasterize(**p, **camera, t=0.5, rows=rows)
    with pytest.raises(RenderError, match="rows must be an integer tensor"):
        tomgs.rasterize(**p, **camera, t=0.5, rows=torch.tensor([0.0, 1.0], device=device))
    with pytest.raises(RenderError, match="rows must be an integer tensor"):
        tomgs.rasterize(**p, **camera, t=0.5, rows=[0, 1])
    empty = {name: value[:0] for name, value in p.items()}  # no Gaussians: every row is outside
    with pytest.raises(RenderError, match="rows must index the 0 Gaussians"):
        tomgs.rasterize(**empty, **camera, t=0.5, rows=torch.tensor([0], device=device))
    image, alpha, meta = tomgs.rasterize(**p, **camera, t=0.5, rows=torch.zeros(0, dtype=torch.int64, device=device))
    assert not image.any() and not alpha.any() and meta["radii"].shape == (0, 2)
