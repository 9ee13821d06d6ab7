"""The fused SH colour kernel (tomgs.kernels.sh via tomgs.render.sh.fused_sh_to_colors) against the float64
torch oracle (tomgs.render.sh.sh_to_colors), which is itself checked by finite differences.

Errors are measured against the size of what each output sums, so a float32 result is judged by
what float32 can do on that row, not by a value that happens to cancel to ~0:
  colours     |ours - ref| <= 1e-5 (0.5 + sum_k |Y_k(dir)| |sh_k|)           per row and channel
  d/d sh      |ours - ref| <= 1e-4 max_c |w_c|                               per row (|Y_k| <= 1)
  d/d means   |ours - ref| <= 1e-4 sum_{k,c} |sh_kc| |w_c| / max(|mean - centre|, DIR_EPS)
  d/d viewmat |ours - ref| <= 1e-4 (1 + max|t|) sum_i (the row's d/d means scale)
where w = dL/dcolours. Rows whose value + 0.5 lies within float32's reach of the clamp get w = 0
(float32 cannot tell which side they fall on).
"""

from __future__ import annotations

import math

import pytest
import torch

import tomgs
from tomgs.constants import SH_C0, SH_DIR_EPS as DIR_EPS
from tomgs.render.sh import eval_sh, fused_sh_to_colors, sh_to_colors
from scenes import INPUT_NAMES, SEED_BASE, devices, look_at, random_scene, rel_l2

DEVICES = devices()
DEGREES = [0, 1, 2, 3]
VALUE_TOL = 1e-5
GRAD_TOL = 1e-4


def _generator(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(SEED_BASE * 1000 + seed)


def _f32(x: torch.Tensor) -> torch.Tensor:
    """float64 holding float32-representable values: both sides see the same inputs."""
    return x.float().double()


def _camera(g: torch.Generator) -> torch.Tensor:
    eye = torch.randn(3, generator=g, dtype=torch.float64) * 0.5 + torch.tensor([0.3, -0.2, -3.0], dtype=torch.float64)
    return _f32(look_at(eye, torch.randn(3, generator=g, dtype=torch.float64) * 0.2))


def _offsets(means: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
    """[N,3] mean - camera centre in float64, non-finite mean components counted as 0 (the oracle's rule)."""
    m = torch.where(torch.isfinite(means), means, torch.zeros_like(means))
    return m + viewmat[:3, :3].T @ viewmat[:3, 3]


def _basis(means: torch.Tensor, viewmat: torch.Tensor, k: int) -> torch.Tensor:
    """[N,K] the SH basis Y_k along each row's view direction, from the oracle's own eval_sh."""
    dirs = torch.nn.functional.normalize(_offsets(means, viewmat), dim=-1, eps=DIR_EPS)
    eye = torch.eye(k, dtype=torch.float64)[None, :, :, None].expand(len(means), k, k, 3)
    return torch.stack([eval_sh(eye[:, j], dirs)[:, 0] for j in range(k)], -1)


def _run(fn, sh, means, viewmat, w, device, camera_grad=True):
    """(colours, (d/d sh, d/d means, d/d viewmat)) of sum(colours * w); None for an unused input."""
    ins = [x.detach().to(device).requires_grad_(req) for x, req in ((sh, True), (means, True), (viewmat, camera_grad))]
    colors = fn(*ins)
    wanted = [x for x in ins if x.requires_grad]
    grads = iter(torch.autograd.grad((colors * w.to(device, colors.dtype)).sum(), wanted, allow_unused=True))
    return colors, tuple(next(grads) if x.requires_grad else None for x in ins)


def check_against_oracle(sh, means, viewmat, device, seed=0, w=None) -> dict:
    """Compare the kernel with the float64 oracle on float32-representable `sh` [N,K,3], `means` [N,3],
    `viewmat` [4,4] under a random dL/dcolours; assert the bounds of the module docstring; return the
    worst normalised errors."""
    sh, means, viewmat = _f32(sh), _f32(means), _f32(viewmat)
    n, k = sh.shape[:2]
    basis = _basis(means, viewmat, k)  # [N,K]
    value_scale = 0.5 + (basis.abs()[:, :, None] * sh.abs()).sum(1)  # [N,3]
    with torch.no_grad():
        ref_values = sh_to_colors(sh, means, viewmat)
        raw = eval_sh(sh, torch.nn.functional.normalize(_offsets(means, viewmat), dim=-1, eps=DIR_EPS)) + 0.5
    if w is None:
        w = torch.randn(n, 3, generator=_generator(seed), dtype=torch.float64)
    w = torch.where(raw.abs() <= 10 * VALUE_TOL * value_scale, torch.zeros_like(w), w)  # clamp ties

    ref, ref_grads = _run(sh_to_colors, sh, means, viewmat, w, "cpu")
    ours, grads = _run(fused_sh_to_colors, sh, means, viewmat, w, device)
    assert ours.dtype == torch.float32 and ours.shape == (n, 3) and ours.device.type == device
    assert torch.equal(ref, ref_values)
    ours, ref = ours.detach().double().cpu(), ref.detach()
    assert torch.equal(torch.isnan(ours), torch.isnan(ref))
    errors = dict(values=float(((ours - ref).abs() / value_scale).nan_to_num(0.0).max()) if n else 0.0)

    v_sh, v_means, v_view = (None if x is None else x.double().cpu() for x in grads)
    ref_sh, ref_means, ref_view = ref_grads
    assert v_sh is not None and torch.isfinite(v_sh).all()
    errors["sh"] = float(((v_sh - ref_sh).abs().amax((1, 2)) / w.abs().amax(-1).clamp_min(1e-300)).max()) if n else 0.0
    if k == 1:  # degree 0 looks nowhere: no gradient for means or the camera, on either side
        assert v_means is None and v_view is None and ref_means is None and ref_view is None
    else:
        assert torch.isfinite(v_means).all() and torch.isfinite(v_view).all()
        dist = _offsets(means, viewmat).norm(dim=-1).clamp_min(DIR_EPS)
        means_scale = (sh.abs() * w.abs()[:, None, :]).sum((1, 2)) / dist  # [N]
        per_row = (v_means - ref_means).abs().amax(-1) / means_scale.clamp_min(1e-300)
        errors["means"] = float(per_row.max()) if n else 0.0
        view_scale = (1.0 + viewmat[:3, 3].abs().max()) * means_scale.sum()
        errors["viewmat"] = float((v_view - ref_view).abs().max() / view_scale.clamp_min(1e-300))
        assert (v_view[3] == 0).all()
    assert errors["values"] <= VALUE_TOL, errors
    assert max(v for key, v in errors.items() if key != "values") <= GRAD_TOL, errors
    return errors


def _random_inputs(seed: int, degree: int, n: int):
    """Gaussians 0.05 to 20 units from the camera all around it, coefficients of mixed sizes."""
    g = _generator(seed)
    viewmat = _camera(g)
    centre = -viewmat[:3, :3].T @ viewmat[:3, 3]
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    means = centre + dirs * torch.exp(torch.rand(n, 1, generator=g, dtype=torch.float64) * math.log(400.0)) * 0.05
    sh = torch.randn(n, (degree + 1) ** 2, 3, generator=g, dtype=torch.float64)
    sh = sh * torch.exp(torch.randn(n, 1, 1, generator=g, dtype=torch.float64))  # rows from ~0.05 to ~20
    return sh, means, viewmat


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("degree", DEGREES)
def test_random_inputs_match_the_oracle(degree, device):
    sh, means, viewmat = _random_inputs(degree, degree, 3000)
    check_against_oracle(sh, means, viewmat, device, seed=degree)
    # and as a whole, the plain relative error of every output
    w = torch.randn(3000, 3, generator=_generator(50 + degree), dtype=torch.float64)
    ref, ref_grads = _run(sh_to_colors, *map(_f32, (sh, means, viewmat)), w, "cpu")
    ours, grads = _run(fused_sh_to_colors, *map(_f32, (sh, means, viewmat)), w, device)
    assert rel_l2(ours, ref) <= VALUE_TOL
    for grad, ref_grad in zip(grads, ref_grads):
        assert (grad is None) == (ref_grad is None)
        if grad is not None:
            assert rel_l2(grad, ref_grad) <= VALUE_TOL


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("degree", DEGREES)
@pytest.mark.parametrize("size", [1e30, 1e-30])
def test_huge_and_tiny_coefficients(size, degree, device):
    sh, means, viewmat = _random_inputs(10 + degree, degree, 500)
    sh = sh * size
    sh[::3, 0] = torch.randn(len(sh[::3]), 3, dtype=torch.float64)  # an ordinary DC under huge or tiny rest
    check_against_oracle(sh, means, viewmat, device, seed=degree)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("degree", DEGREES)
def test_gaussians_at_and_near_the_camera_centre(degree, device):
    """A camera at the origin (its centre is exactly 0 in any precision, whatever its rotation): a
    Gaussian on it sees direction 0 (colour = the DC term, mean gradient = direction gradient /
    DIR_EPS, as torch's normalize); closer than DIR_EPS the direction shrinks linearly; far out
    |mean| is formed without squaring it (1e20^2 overflows float32)."""
    g = _generator(20 + degree)
    viewmat = _camera(g)
    viewmat[:3, 3] = 0.0
    dists = torch.tensor([0.0, 1e-30, 1e-13, 5e-13, 2e-12, 1e-11, 1e-6, 1e19, 1e20, 1e30], dtype=torch.float64)
    dirs = torch.nn.functional.normalize(torch.randn(len(dists), 3, generator=g, dtype=torch.float64), dim=-1)
    means = _f32(dirs * dists[:, None])
    sh = torch.randn(len(dists), (degree + 1) ** 2, 3, generator=g, dtype=torch.float64)
    check_against_oracle(sh, means, viewmat, device, seed=degree)
    colors = fused_sh_to_colors(sh[:1].to(device), means[:1].to(device), viewmat.to(device)).cpu()
    dc = torch.clamp_min(SH_C0 * _f32(sh[0, 0]) + 0.5, 0.0)
    assert torch.allclose(colors[0].double(), dc, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("degree", [1, 2, 3])
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_non_finite_means_count_as_zero_and_get_no_gradient(value, degree, device):
    sh, means, viewmat = _random_inputs(30 + degree, degree, 40)
    means[3, 1] = value
    means[5] = value
    sh[3, 0] = 10.0  # above the clamp in every channel, so that row has gradients to give
    check_against_oracle(sh, means, viewmat, device, seed=degree)
    ins = [_f32(x).to(device).requires_grad_(True) for x in (sh, means, viewmat)]
    fused_sh_to_colors(*ins).sum().backward()
    assert (ins[1].grad[3, 1] == 0).all() and (ins[1].grad[5] == 0).all()
    assert (ins[1].grad[3, [0, 2]] != 0).all()  # the finite components still look from where they are
    assert all(torch.isfinite(x.grad).all() for x in ins), [x.grad for x in ins]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("degree", DEGREES)
@pytest.mark.parametrize("n", [0, 1])
def test_empty_and_single(n, degree, device):
    sh, means, viewmat = _random_inputs(40 + degree, degree, n)
    check_against_oracle(sh, means, viewmat, device, seed=degree)
    ins = [_f32(x).to(device).requires_grad_(True) for x in (sh, means, viewmat)]
    fused_sh_to_colors(*ins).sum().backward()
    assert ins[0].grad.shape == sh.shape
    if degree > 0:
        assert ins[2].grad.shape == (4, 4) and (n == 1 or (ins[2].grad == 0).all())


@pytest.mark.parametrize("device", DEVICES)
def test_clamp_passes_gradient_only_above_zero_and_keeps_nan(device):
    sh = torch.zeros(4, 4, 3, dtype=torch.float64)
    # DC only: value + 0.5 = C0 dc + 0.5, negative for dc < -1.77
    sh[:, 0] = torch.tensor([[2.0, -2.0, 0.0], [-5.0, 5.0, -1.0], [0.0, 0.0, 0.0], [math.nan, 1.0, 1.0]])
    ins = [x.to(device).requires_grad_(True) for x in (sh.float(), torch.rand(4, 3), torch.eye(4))]
    colors = fused_sh_to_colors(*ins)
    ref = sh_to_colors(*(x.detach().cpu() for x in ins))
    assert torch.equal(torch.isnan(colors.cpu()), torch.isnan(ref)) and torch.isnan(colors[3, 0])
    assert torch.equal(colors.cpu().nan_to_num(-1.0), ref.nan_to_num(-1.0))
    colors.sum().backward()
    passed = (ins[0].grad[:, 0] != 0).cpu()
    assert passed.sum() == 9  # torch.clamp_min's mask, on the value before the clamp: NaN and below 0 get nothing
    assert torch.equal(passed, SH_C0 * sh[:, 0].float() + 0.5 >= 0)


@pytest.mark.parametrize("device", DEVICES)
def test_camera_gradient_is_optional_and_changes_nothing_else(device):
    sh, means, viewmat = _random_inputs(60, 3, 200)
    w = torch.randn(200, 3, generator=_generator(61), dtype=torch.float64)
    _, with_camera = _run(fused_sh_to_colors, sh, means, viewmat, w, device, camera_grad=True)
    _, without = _run(fused_sh_to_colors, sh, means, viewmat, w, device, camera_grad=False)
    assert without[2] is None and with_camera[2] is not None and with_camera[2].abs().sum() > 0
    assert torch.equal(with_camera[0], without[0]) and torch.equal(with_camera[1], without[1])


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_the_oracle_against_finite_differences(degree):
    """sh_to_colors in float64 (the oracle the kernel is held to) against central differences, in
    every input, with a non-finite mean among ordinary ones; value + 0.5 kept away from the clamp."""
    g = _generator(70 + degree)
    sh = torch.randn(12, (degree + 1) ** 2, 3, generator=g, dtype=torch.float64) * 0.05
    sh[:, 0] = torch.where(torch.rand(12, 1, generator=g, dtype=torch.float64) < 0.3, -8.0, 3.0)  # off or on
    means = torch.randn(12, 3, generator=g, dtype=torch.float64) * 2.0
    means[4, 2] = math.nan
    viewmat = _camera(g)
    assert (eval_sh(sh, torch.nn.functional.normalize(_offsets(means, viewmat), dim=-1)) + 0.5).abs().min() > 0.1
    assert torch.autograd.gradcheck(sh_to_colors, [x.requires_grad_(True) for x in (sh, means, viewmat)],
                                    eps=1e-6, atol=1e-7, rtol=1e-5)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("degree", DEGREES)
def test_rasterize_with_sh_is_the_torch_path_rendered(degree, dtype, device, monkeypatch):
    """rasterize evaluates SH with the kernel now; the image and every gradient equal what it gave
    when prepare_inputs evaluated sh_to_colors in torch, in the inputs' dtype (RGB handed in)."""
    import tomgs.render.inputs

    calls = []
    monkeypatch.setattr(tomgs.render.inputs, "fused_sh_to_colors", lambda *a: calls.append(1) or fused_sh_to_colors(*a))
    scene = random_scene(80 + degree, n=80, sh_degree=degree, dtype=dtype)
    size = dict(width=scene["width"], height=scene["height"], t=scene["t"])
    w = torch.rand(scene["height"], scene["width"], 3, generator=_generator(81)) - 0.3
    results = []
    for fused in (True, False):
        ins = {k: scene[k].detach().to(device).requires_grad_(True) for k in INPUT_NAMES}
        call = dict(ins)
        if not fused:  # the path before the kernel: RGB from the torch formula, in the inputs' dtype
            call["colors"] = sh_to_colors(ins["colors"], ins["means"], ins["viewmat"])
        image, alpha, _ = tomgs.rasterize(**call, **size)
        grads = torch.autograd.grad((image * w.to(image)).sum() + alpha.sum(), list(ins.values()))
        results.append((image, alpha, grads))
    assert calls == [1]
    (image, alpha, grads), (old_image, old_alpha, old_grads) = results
    assert (image - old_image).abs().max() <= 1e-6 and (alpha - old_alpha).abs().max() <= 1e-7
    for name, grad, old in zip(INPUT_NAMES, grads, old_grads):
        assert rel_l2(grad, old) <= 1e-5, (name, rel_l2(grad, old))
