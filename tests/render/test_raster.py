"""The Warp rasterizer against the float64 torch reference: values, gradients, meta, temporal culling."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import torch

import tomgs
from tomgs.constants import ALPHA_MIN
from tomgs.kernels import project
from scenes import INPUT_NAMES, devices, random_scene, render_both, rel_l2, split

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


def one_ulp_off(x: torch.Tensor, seed: int) -> torch.Tensor:
    """`x` (float32 values) moved by one float32 ulp up or down at random, zeros and non-finite left."""
    x32 = x.float()
    g = torch.Generator().manual_seed(seed)
    up = torch.rand(x32.shape, generator=g) < 0.5
    moved = torch.nextafter(x32, torch.where(up, torch.tensor(math.inf), torch.tensor(-math.inf)))
    return torch.where(torch.isfinite(x32) & (x32 != 0), moved, x32).double()


def render_with_yardsticks(scene: dict, device: str, t: float | None = None, **kw):
    """[(outputs, input tensors)] for: ours on `device`, the float64 reference, and two yardsticks of
    what float32 can do on this scene: the float32 reference, and the float64 reference on inputs
    one float32 ulp off (the spread a backward-stable float32 renderer may show). All on the
    float32-representable values of `scene`, at time t (a float64, not rounded; default scene["t"])."""
    scene = {k: (v.float().double() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    t = scene["t"] if t is None else t
    nudged = {k: (one_ulp_off(v, i) if isinstance(v, torch.Tensor) else v) for i, (k, v) in enumerate(scene.items())}
    out = []
    for fn, where, values, extra in ((tomgs.rasterize, device, scene, {}),
                                     (tomgs.rasterize_reference, "cpu", scene, {}),
                                     (tomgs.rasterize_reference, "cpu", scene, dict(dtype=torch.float32)),
                                     (tomgs.rasterize_reference, "cpu", nudged, {})):
        tensors = [values[k].detach().to(where).requires_grad_(True) for k in INPUT_NAMES]
        outputs = fn(**dict(zip(INPUT_NAMES, tensors)), width=scene["width"], height=scene["height"], t=t, **kw,
                     **extra)
        out.append((outputs, tensors))
    return out


def radii_match(radii: torch.Tensor, ref_radii: torch.Tensor, extent: torch.Tensor,
                rel: torch.Tensor | float = 0.0, slack: torch.Tensor | None = None) -> bool:
    """Equal, but for a difference of one where the float64 radius before rounding up lies within
    float32's reach of an integer (a tie no float32 computation can call), for a relative
    difference `rel` [N] (default none) and for an absolute `slack` [N, 2] (default none).
    Which Gaussians have a radius at all must agree exactly."""
    radii, ref_radii = radii.long().cpu(), ref_radii.long().cpu()
    tie = (extent - extent.round()).abs() <= 1e-5 * extent + 1e-6
    rel = torch.as_tensor(rel, dtype=torch.float64).reshape(-1, 1) if torch.is_tensor(rel) else rel
    allowed = torch.maximum(tie.long(), torch.ceil(rel * ref_radii).long())
    if slack is not None:
        allowed = torch.maximum(allowed, slack.long().cpu())
    return bool(((radii - ref_radii).abs() <= allowed).all() and torch.equal(radii > 0, ref_radii > 0))


def depth_condition(scene: dict) -> torch.Tensor:
    """[N] how much float32 rounding of the world coordinates is amplified in each camera depth:
    (|row 2 of viewmat| . |(mean, 1)|) / |depth|; ~1e3 for a Gaussian 1e-3 in front of a camera
    a few units from the origin (the radius, ~1/depth, inherits it)."""
    view, means = scene["viewmat"].double(), scene["means"].double()
    magnitude = means.abs() @ view[2, :3].abs() + view[2, 3].abs()
    depth = (means @ view[2, :3] + view[2, 3]).abs()
    return torch.nan_to_num(magnitude / depth, nan=0.0, posinf=0.0)


def condition_numbers(conics: torch.Tensor, radii: torch.Tensor) -> torch.Tensor:
    """[N] condition number of each visible Gaussian's 2D covariance (from its conic); 1 if culled."""
    a, b, c = conics.detach().double().cpu().unbind(-1)
    half_gap = torch.sqrt(((a - c) / 2) ** 2 + b * b)
    big, small = (a + c) / 2 + half_gap, (a * c - b * b) / ((a + c) / 2 + half_gap)
    cond = torch.nan_to_num(big / small, nan=1.0, posinf=1e300)
    return torch.where(radii.cpu().amax(-1) > 0, cond, torch.ones_like(cond))


# per-Gaussian inputs: their gradient rows belong to one Gaussian each
PER_GAUSSIAN = ("means", "quats", "scales", "opacities", "colors", "t_means", "t_scales")


def assert_matches_within_float32(scene: dict, device: str, factor: float = 3.0, t: float | None = None,
                                  thin_slack: bool = False, **kw) -> dict:
    """`assert_matches_reference` where float32 itself is the limit: image, alpha and each gradient
    within IMAGE_TOL / GRAD_TOL of the float64 reference, or, where that is larger, within `factor`
    times the larger miss of two float32 yardsticks on the same scene (`render_with_yardsticks`):
    inputs on which no float32 renderer can do better, e.g. a needle pointing at the camera or a
    Gaussian 1e-3 in front of it. Radii equal up to ties and float32's resolution; visibility exact.

    `thin_slack`: a Gaussian whose 2D covariance has condition number above 1e6 keeps only
    ~eps sqrt(cond) of relative precision on its short axis once A = J W R S is rounded to float32
    (A's entries are ~sqrt(cond) times the short axis): its own gradient rows, and the camera's,
    may then miss by 16 eps sqrt(cond) of the gradient's norm (1e-3 at cond 1e6, 1e-2 at 1e8)."""
    (ours, ours_in), (ref, ref_in), *yardsticks = render_with_yardsticks(scene, device, t, **kw)
    (image, alpha, meta), (ref_image, ref_alpha, ref_meta) = ours, ref
    assert torch.isfinite(image).all() and torch.isfinite(alpha).all()
    for k, (got, want) in enumerate(((image, ref_image), (alpha, ref_alpha))):
        got, want = got.detach().double().cpu(), want.detach()
        miss = max(float((y[0][k].detach().double() - want).abs().max()) for y in yardsticks)
        tol = max(IMAGE_TOL, factor * miss)
        assert float((got - want).abs().max()) <= tol, (("image", "alpha")[k], float((got - want).abs().max()), tol)
    # radii to 1e-4, to float32's resolution of the depth (16 eps per unit of its condition), or as
    # close as the yardsticks get (a needle near the near plane cancels in J W R S as well)
    rel = torch.clamp(depth_condition(scene) * 16 * 2.0**-24, min=1e-4)
    slack = torch.stack([(y[0][2]["radii"].long() - ref_meta["radii"]).abs() for y in yardsticks]).amax(0) * factor
    assert radii_match(meta["radii"], ref_meta["radii"], ref_meta["extent"], rel, slack)
    assert int(meta["n_visible"]) == ref_meta["n_visible"]

    g = torch.Generator().manual_seed(7)
    w_image = torch.rand(ref_image.shape, generator=g, dtype=torch.float64) - 0.3
    w_alpha = torch.rand(ref_alpha.shape, generator=g, dtype=torch.float64) - 0.3
    grads = []
    for (img, alp, _), tensors in (ours, ours_in), (ref, ref_in), *yardsticks:
        loss = (img * w_image.to(img)).sum() + (alp * w_alpha.to(alp)).sum()
        grads.append(torch.autograd.grad(loss, tensors))
    cond = condition_numbers(ref_meta["conics"], ref_meta["radii"])
    thin = (cond > 1e6) if thin_slack else torch.zeros_like(cond, dtype=torch.bool)
    thin_tol = 16 * 2.0**-24 * float(cond[thin].max().sqrt()) if thin.any() else 0.0
    for name, grad, ref_grad, *yard_grads in zip(INPUT_NAMES, *grads):
        assert torch.isfinite(grad).all(), name
        tol = max(GRAD_TOL, factor * max(rel_l2(y, ref_grad) for y in yard_grads))
        if not thin.any():
            assert rel_l2(grad, ref_grad) <= tol, (name, rel_l2(grad, ref_grad), tol)
        elif name in PER_GAUSSIAN:  # the thin Gaussians' rows apart, both against the whole norm
            miss = (grad.detach().double().cpu() - ref_grad.detach()).reshape(len(thin), -1)
            norm = float(ref_grad.detach().norm()) or 1.0
            assert float(miss[~thin].norm()) / norm <= tol, (name, float(miss[~thin].norm()) / norm, tol)
            assert float(miss[thin].norm()) / norm <= max(tol, thin_tol), \
                (name, "thin rows", float(miss[thin].norm()) / norm, max(tol, thin_tol))
        else:
            assert rel_l2(grad, ref_grad) <= max(tol, thin_tol), (name, rel_l2(grad, ref_grad), max(tol, thin_tol))
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


@pytest.mark.parametrize("batched", [False, True])
def test_alpha_at_the_skip_threshold(batched, monkeypatch):
    """One opaque Gaussian over a 256x256 image, its 1/255 level a circle ~100 px out: pixels whose
    alpha lies just above 1/255 are composited, those just below are not, as in the float64
    reference. The kernels skip an entry past POWER_SKIP without its exp; a threshold below
    ln(255), by 1e-3 or more, would drop pixels of the first ring."""
    from tomgs.render.stages import kernel_choices

    monkeypatch.setattr(kernel_choices, "batched", batched)
    one = dict(means=torch.tensor([[0.0123, 0.0071, 2.0]], dtype=torch.float64),
               quats=torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
               scales=torch.full((1, 3), 0.47, dtype=torch.float64), opacities=torch.ones(1, dtype=torch.float64),
               colors=torch.ones(1, 3, dtype=torch.float64), t_means=torch.zeros(1, dtype=torch.float64),
               t_scales=torch.ones(1, dtype=torch.float64), viewmat=torch.eye(4, dtype=torch.float64),
               K=torch.tensor([[128.0, 0, 128.0], [0, 128.0, 128.0], [0, 0, 1.0]], dtype=torch.float64),
               width=256, height=256, t=0.0)
    _, alpha, _ = tomgs.rasterize(**one)
    _, ref_alpha, meta = tomgs.rasterize_reference(**one)
    alpha = alpha.double()
    ys, xs = torch.meshgrid(torch.arange(256.0) + 0.5, torch.arange(256.0) + 0.5, indexing="ij")
    d, (a, b, c) = meta["means2d"][0] - torch.stack([xs, ys], -1).double(), meta["conics"][0]
    raw = torch.exp(-(0.5 * (a * d[..., 0] ** 2 + c * d[..., 1] ** 2) + b * d[..., 0] * d[..., 1]))[..., None]
    just_above = (raw >= ALPHA_MIN * (1 + 1e-4)) & (raw <= ALPHA_MIN * 1.1)  # o = 1: alpha = exp(-power)
    just_below = (raw < ALPHA_MIN * (1 - 1e-4)) & (raw >= ALPHA_MIN * 0.9)
    assert int(just_above.sum()) >= 20 and int(just_below.sum()) >= 20
    assert (alpha[just_above] - ref_alpha[just_above]).abs().max() <= 1e-4 * ALPHA_MIN  # float32 rounding
    assert (alpha[just_below] == 0).all()
    assert (alpha - ref_alpha).abs().max() <= IMAGE_TOL


@pytest.mark.parametrize("device", DEVICES)
def test_depths_closer_than_the_sort_reads_draw_in_index_order(device, monkeypatch):
    """Four opaque Gaussians stacked on the optical axis, float32 depths 3, 2, 1 and 0 ulps above a
    multiple of 4 ulps (the camera at the origin, so depth is exactly the stored z): the sort reads no depth bits
    that far down (tomgs.constants.sort_low_bit), so they are drawn in index order, the farthest first,
    in the image and in the gradients as the reference draws them. Ordered by exact depth instead, the
    reference's image differs: the test can tell."""
    scene = random_scene(41, n=60, width=512, height=256)  # 512 tiles: the sort leaves out 2 bits of depth
    view = scene["viewmat"]
    scene["means"] = scene["means"] @ view[:3, :3].T + view[:3, 3]  # the same scene in camera space
    scene["viewmat"] = torch.eye(4, dtype=torch.float64)
    base = torch.tensor(2.5, dtype=torch.float32).view(torch.int32) + 8  # a run of 4 ulps equal in the read bits
    stack = (base + torch.tensor([3, 2, 1, 0], dtype=torch.int32)).view(torch.float32).double()
    scene["means"][:4] = torch.stack([torch.zeros(4), torch.zeros(4), stack], -1).double()
    scene["scales"][:4], scene["opacities"][:4] = 0.3, 0.9
    scene["colors"][:4] = torch.eye(4, 3, dtype=torch.float64) + torch.tensor([0.0, 0.0, 0.5]).double()
    scene["t_means"][:4], scene["t_scales"][:4] = scene["t"], 10.0
    assert_matches_reference(scene, device)

    _, (image, _, _), _, _ = render_both(scene, device)
    monkeypatch.setattr(tomgs.render.reference, "depth_order", lambda depths, width, height: depths)
    _, (exact_image, _, _), _, _ = render_both(scene, device)
    assert (exact_image - image).abs().max() > 0.1


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
@pytest.mark.parametrize("with_rows", [False, True])
def test_long_paths_inline_or_listed_give_the_same(device, with_rows, monkeypatch):
    """The projection's long path and binning's keys written by each warp itself (inline) or from the
    work lists in full warps (tomgs/kernels/lanes.py): the same image, footprints and gradients, camera
    gradients and rendered rows (a repeated one too) included, on a scene where most Gaussians are dead;
    binning's lists serve both a frame's keys written after its sync (the first of its size) and before
    it (the next). Bit for bit on the CPU; on CUDA the image and footprints to float32 rounding (the two
    kernels may contract multiply-adds differently), the gradients to the oracle's 1e-3: the raster
    backward adds by atomics in no fixed order, which moved a per-Gaussian gradient by 1.4e-4 of itself
    between two runs and the camera gradient, a sum over every Gaussian, by 1e-2 of a small entry."""
    from tomgs.render import frame as render
    from tomgs.render import stages

    scene = random_scene(70, n=400)
    scene["t_scales"] = scene["t_scales"] * 0.2  # most dead at t
    rows = torch.tensor([*range(0, 400, 3), 5, 5], dtype=torch.int32, device=device) if with_rows else None
    results = []
    for inline_lanes in (1, 33):  # every thread inline; every warp (at most 32 lanes) listed
        monkeypatch.setattr(stages.kernel_choices, "inline_lanes", inline_lanes)
        monkeypatch.setattr(render, "key_bounds", render.KeyBounds())  # keys after the sync, then before it
        for _ in range(2):
            inputs, rest = split({k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()},
                                 device)
            named = dict(zip(INPUT_NAMES, inputs))
            image, alpha, meta = tomgs.rasterize(**named, width=rest["width"], height=rest["height"], t=rest["t"],
                                                 rows=rows)
            weights = torch.rand(image.shape, generator=torch.Generator().manual_seed(1)).to(image)
            ((image * weights).sum() + alpha.sum()).backward()
            results.append(dict(image=image, radii=meta["radii"], means2d=meta["means2d"], conics=meta["conics"],
                                depths=meta["depths"], **{name: x.grad for name, x in zip(INPUT_NAMES, inputs)
                                                          if x.requires_grad}))
    assert 0 < int((results[0]["radii"] > 0).any(-1).sum()) < len(results[0]["radii"]) // 2  # a minority visible
    for other in results[1:]:
        assert other.keys() == results[0].keys()
        for name, a in results[0].items():
            b = other[name]
            assert a is not None
            if device == "cpu" or not a.is_floating_point():
                assert torch.equal(a, b)
            elif name in INPUT_NAMES:  # a gradient: to the oracle's 1e-3, of its largest entry for sums
                torch.testing.assert_close(a, b, rtol=1e-3, atol=max(1e-5, 1e-3 * float(a.abs().max())))
            else:
                torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)


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
    """render_sequence renders each few frames from the Gaussians alive around their times (on a GPU
    too: a sequence of SEQUENCE_FRAMES or more): the images equal a render of every Gaussian, and a
    Gaussian alive only at one frame is kept."""
    from tomgs.render import alive
    from tomgs.cameras import Cameras
    from tomgs.render.sequence import render_sequence

    scene = random_scene(11, n=300, width=40, height=30)
    count = alive.SEQUENCE_FRAMES + 8
    g = torch.Generator().manual_seed(3)
    n = scene["means"].shape[0]
    gaussians = {k: scene[k].float().to(device) for k in ("means", "quats", "scales", "opacities", "colors")}
    gaussians["t_means"] = torch.rand(n, generator=g).to(device)
    gaussians["t_scales"] = (10.0 ** (-3 + 3 * torch.rand(n, generator=g))).to(device)  # 1e-3 .. 1: mostly short
    gaussians["opacities"][0] = ALPHA_MIN  # alive only at the instant t = t_mean
    gaussians["t_means"][0] = 12 / (count - 1)
    viewmat = scene["viewmat"].numpy()
    cams = Cameras.create(np.repeat(np.linalg.inv(viewmat)[None], count, 0), scene["K"].numpy(), 40, 30)
    frames = list(range(count))[::-1]
    alive_counts = []
    for k, image, meta in render_sequence(gaussians, cams, frames, device=device, to_cpu=False):
        full, _, full_meta = tomgs.rasterize(**gaussians, viewmat=scene["viewmat"].float().to(device),
                                             K=scene["K"].float().to(device), width=40, height=30,
                                             t=float(cams.times[k]))
        assert torch.equal(image, full.clamp(0, 1)), k
        assert int(meta["n_alive"]) == int(full_meta["n_alive"])
        alive_counts.append(len(meta["rows"]))
    assert alive.pays_for_sequence(device, len(frames))
    assert max(alive_counts) < n  # some frames really rendered a subset
    first, last = alive.windows(gaussians["opacities"], gaussians["t_means"], gaussians["t_scales"])
    assert first[0] <= 12 / (count - 1) <= last[0]


def test_an_unfinished_sequence_leaves_gradients_on():
    """render_sequence renders without gradients, but a caller that stops early (or between frames)
    must find autograd as it left it."""
    from tomgs.cameras import Cameras
    from tomgs.render.sequence import render_sequence

    scene = random_scene(5, n=40, width=16, height=12)
    gaussians = {k: scene[k].float() for k in ("means", "quats", "scales", "opacities", "colors")}
    gaussians["t_means"], gaussians["t_scales"] = torch.zeros(40), torch.ones(40)
    cams = Cameras.create(np.repeat(np.linalg.inv(scene["viewmat"].numpy())[None], 3, 0), scene["K"].numpy(), 16, 12)
    frames = render_sequence(gaussians, cams)
    next(frames)
    assert torch.is_grad_enabled()
    del frames
    assert torch.is_grad_enabled()


# ---- the batched kernels (tomgs.kernels.raster_batched, the CUDA default) on the CPU ----------------

@pytest.fixture(params=["one_thread_blocks", "cooperative_blocks"])
def batched_on_cpu(request, monkeypatch):
    """Composite with the batched kernel pair on the CPU, in blocks of one thread (Warp's CPU model:
    each thread stages whole batches itself) or of cooperative fibers, 256 forward and 128 backward
    (`enable_cpu_blocks`: barriers, shared batches and block reductions as on a GPU, so a missing
    barrier shows)."""
    from tomgs.render.stages import kernel_choices

    if request.param == "cooperative_blocks":
        import warp as wp

        # record the other stages' launches first, so that only the raster kernels run as fibers
        render_both(random_scene(0, n=20, width=16, height=16), "cpu")[0][0].sum().backward()
        monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    monkeypatch.setattr(kernel_choices, "batched", True)
    return request.param


def covering_scene(seed: int, n: int, width: int, height: int, opacity: tuple[float, float],
                   scale: tuple[float, float] = (0.25, 0.5), spread: float = 0.6) -> dict:
    """`n` large Gaussians 2-4 units in front of the camera, spread over `spread` z across the view,
    alive at t: most of them reach every tile of a small image, so the tile lists run to n entries."""
    scene = random_scene(seed, n=n, width=width, height=height)
    g = torch.Generator().manual_seed(seed)
    z = 2.0 + 2.0 * torch.rand(n, generator=g, dtype=torch.float64)
    means = torch.stack([(torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * spread * z,
                         (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * spread * z, z], -1)
    lo, hi = scale
    # camera at the origin looking down +z, the image centred: the coverage does not depend on the seed
    scene.update(means=means, viewmat=torch.eye(4, dtype=torch.float64),
                 K=torch.tensor([[width, 0.0, width / 2], [0.0, width, height / 2], [0.0, 0.0, 1.0]],
                                dtype=torch.float64),
                 scales=lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=torch.float64),
                 opacities=opacity[0] + (opacity[1] - opacity[0]) * torch.rand(n, generator=g, dtype=torch.float64),
                 t_means=torch.full((n,), scene["t"], dtype=torch.float64),
                 t_scales=torch.full((n,), 10.0, dtype=torch.float64))
    return scene


def assert_batched_matches(scene: dict) -> dict:
    """The batched pair against the float64 reference (values and gradients, the usual tolerances)
    and against the per-pixel pair: the same arithmetic per pixel, so the same image to 1e-6, and the
    same gradients to float32 sums taken in another order (the batched backward adds a thread's two
    pixels before its atomics): 1e-4, ten times inside the oracle's tolerance."""
    from tomgs.render.stages import kernel_choices

    meta = assert_matches_reference(scene, "cpu")
    (image, alpha, _), _, ins, _ = render_both(scene, "cpu")
    batched = kernel_choices.batched
    try:
        kernel_choices.batched = False
        (pp_image, pp_alpha, _), _, pp_ins, _ = render_both(scene, "cpu")
    finally:
        kernel_choices.batched = batched
    assert (image - pp_image).abs().max() <= 1e-6 and (alpha - pp_alpha).abs().max() <= 1e-6
    w = torch.rand(image.shape, generator=torch.Generator().manual_seed(3)) - 0.3
    grads = torch.autograd.grad((image * w).sum() + alpha.sum(), ins[:5])
    pp_grads = torch.autograd.grad((pp_image * w).sum() + pp_alpha.sum(), pp_ins[:5])
    for name, grad, pp_grad in zip(INPUT_NAMES, grads, pp_grads):
        assert rel_l2(grad, pp_grad) <= 1e-4, (name, rel_l2(grad, pp_grad))
    return meta


@pytest.mark.parametrize("seed", range(3))
def test_batched_random_scenes(seed, batched_on_cpu):
    meta = assert_batched_matches(random_scene(seed))
    assert 0 < meta["n_visible"] < meta["radii"].shape[0]


@pytest.mark.parametrize("size", [(16, 16), (33, 17), (64, 48), (7, 50)])
def test_batched_image_sizes(size, batched_on_cpu):
    assert_batched_matches(random_scene(20, n=80, width=size[0], height=size[1]))


def raster_node(out: torch.Tensor):
    """The raster stage's backward node of a render whose output `out` is still attached."""
    todo, seen = [out.grad_fn], set()
    while todo:
        node = todo.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        if type(node).__name__ == "RasterizeBackward":
            return node
        todo += [parent for parent, _ in node.next_functions]
    raise AssertionError("no raster stage in the graph")


def raster_end(out: torch.Tensor) -> torch.Tensor:
    """The raster stage's saved `end` [H, W] (one past each pixel's last composited list entry) of a
    render whose output `out` is still attached to the graph."""
    return raster_node(out).saved_tensors[-1]


@pytest.mark.parametrize("n", [300, 700])
def test_batched_deep_tiles(n, batched_on_cpu):
    """A one-tile list of more than one (300) and more than two (700) batches of 256, faint enough that
    no pixel saturates: every batch is composited forward and walked back."""
    scene = covering_scene(80 + n, n, width=16, height=16, opacity=(0.008, 0.015), scale=(0.5, 1.0))
    meta = assert_batched_matches(scene)
    assert meta["n_intersections"] == n
    (_, alpha, _), _, _, _ = render_both(scene, "cpu")
    assert alpha.max() < 1 - 1e-3  # nothing stopped on transmittance
    assert int(raster_end(alpha).max()) > 256 * (n // 256)  # the walk back starts in the last batch


def test_batched_pixels_saturate_in_different_batches(batched_on_cpu):
    """Pixels of a 700-entry tile stop on transmittance in each of its 3 batches or never: the pixels
    that are done keep staging batches for the others."""
    scene = covering_scene(92, 700, width=16, height=16, opacity=(0.04, 0.08), scale=(0.3, 0.8))
    meta = assert_batched_matches(scene)
    assert meta["n_intersections"] == 700
    (_, alpha, _), _, _, _ = render_both(scene, "cpu")
    end = raster_end(alpha)
    batch = (end - 1) // 256
    assert set(batch.flatten().tolist()) == {0, 1, 2}
    assert float(alpha.detach().max()) > 0.999 and float(alpha.detach().min()) < 0.9


def test_batched_block_stops_when_every_pixel_saturates(batched_on_cpu):
    """Dense opaque overlap: every pixel of the tile is done within the first batch, so the block
    leaves the other batches of its 600-entry list alone."""
    scene = covering_scene(100, 600, width=16, height=16, opacity=(0.9, 0.99), scale=(0.5, 1.0), spread=0.2)
    meta = assert_batched_matches(scene)
    assert meta["n_intersections"] == 600
    (_, alpha, _), _, _, _ = render_both(scene, "cpu")
    assert int(raster_end(alpha).max()) <= 256 and float(alpha.detach().min()) > 0.998


def test_batched_empty_tiles(batched_on_cpu):
    """Gaussians in one corner of a 4x3-tile image: most tiles have empty lists."""
    scene = covering_scene(110, 60, width=64, height=48, opacity=(0.2, 0.9), scale=(0.01, 0.05))
    scene["means"][:, 0] = -0.3 * scene["means"][:, 2]  # a column near the left edge
    (image, alpha, meta), _, _, _ = render_both(scene, "cpu")
    assert (alpha[:, 32:] == 0).all() and alpha.max() > 0.5
    assert_batched_matches(scene)


def test_batched_alpha_clamp(batched_on_cpu):
    """Opacities above 0.99: alpha clamps at 0.99 and passes no gradient through the clamp."""
    scene = covering_scene(120, 40, width=20, height=18, opacity=(0.992, 1.0), scale=(0.05, 0.2))
    assert_batched_matches(scene)


@pytest.mark.parametrize("batched", [False, True])
def test_tiles_taken_longest_first_give_the_same_frame(batched, monkeypatch):
    """Blocks that take the tiles in order of list length (the CUDA default) composite the same
    image as blocks in tile order, with either kernel pair, and the same gradients to float32
    rounding (the tiles add into each Gaussian's sums in another order)."""
    from tomgs.render.stages import kernel_choices

    monkeypatch.setattr(kernel_choices, "batched", batched)
    scene = random_scene(31, n=150, width=70, height=41)  # 5x3 tiles, lists of many lengths
    outs = []
    for ordered in (False, True):
        monkeypatch.setattr(kernel_choices, "ordered_tiles", ordered)
        (image, alpha, meta), _, ins, _ = render_both(scene, "cpu")
        if ordered:  # the blocks did take the tiles out of tile order
            order = raster_node(alpha).tile_order
            assert not torch.equal(order, torch.arange(len(order)))
        grads = torch.autograd.grad((image * torch.linspace(-1, 1, image.numel()).view(image.shape)).sum()
                                    + alpha.sum(), ins[:7])
        outs.append((image, alpha, grads))
    assert meta["n_intersections"] > 100
    assert torch.equal(outs[0][0], outs[1][0]) and torch.equal(outs[0][1], outs[1][1])
    for name, a, b in zip(INPUT_NAMES, outs[0][2], outs[1][2]):
        assert rel_l2(a, b) <= 1e-4, name


@pytest.mark.parametrize("cooperative", [False, True])
def test_frame_counts_come_with_the_sync(cooperative, monkeypatch):
    """meta's n_visible and n_alive are summed per block on the device and read with the intersection
    count (Python ints): equal to counting the per-Gaussian outputs, over several blocks whose threads
    each count rows a launch apart (project.STATS_ROWS) and a partial one, also in 256-fiber blocks on
    the CPU (block sums as on a GPU)."""
    import warp as wp

    from tomgs import runtime
    from tomgs.render import frame as render

    if cooperative:  # fresh recorded launches, so that every kernel runs in blocks of 256 fibers
        monkeypatch.setattr(render, "launch", runtime.Launches())
        monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    n = 2 * 256 * project.STATS_ROWS + 700  # three blocks, the last one's threads counting fewer rows
    scene = random_scene(1, n=n)
    names = ("means", "quats", "scales", "opacities", "colors", "t_means", "t_scales", "viewmat", "K")
    _, _, meta = tomgs.rasterize(*(scene[k].float() for k in names), scene["width"], scene["height"], scene["t"])
    assert isinstance(meta["n_visible"], int) and isinstance(meta["n_alive"], int)
    assert meta["n_visible"] == int((meta["radii"] > 0).any(-1).sum()) > 256 * project.STATS_ROWS
    assert meta["n_alive"] == int((meta["opacities_t"] >= ALPHA_MIN).sum())
    assert 0 < meta["n_visible"] < meta["n_alive"] < n


# ---- tile keys written before the host sync, into buffers of a bound kept between frames ----------

@pytest.fixture
def write_capacities(monkeypatch):
    """Fresh bounds (tomgs.render.frame.key_bounds) for the test, and the list of the capacities that
    rasterize's calls of render.write_keys ask for, in order."""
    from tomgs.render import frame as render

    monkeypatch.setattr(render, "key_bounds", render.KeyBounds())
    asked = []
    write = render.write_keys

    def spy(wrapped, n, ends, frame, capacity, lists=None):
        asked.append(capacity)
        return write(wrapped, n, ends, frame, capacity, lists)

    monkeypatch.setattr(render, "write_keys", spy)
    return asked


def test_the_kept_bound_follows_how_much_the_totals_move():
    """Frames that repeat keep almost no headroom (memory: 24 bytes a slot); frames whose totals
    move keep twice their spread, at most an eighth; the bound holds the last 16 frames' largest."""
    from tomgs.render.frame import MAX_INTERSECTIONS, KeyBounds, Frame

    frame = Frame(64, 48, 0.0, 0.0, 0.01, 1e10, "cpu")
    other = Frame(48, 64, 0.0, 0.0, 0.01, 1e10, "cpu")
    bounds = KeyBounds()
    assert bounds.capacity(frame) == 0  # a size not seen yet: keys after the sync
    for _ in range(3):
        bounds.remember(frame, 1_000_000)
    assert bounds.capacity(frame) == 1_000_000 + 1_000_000 // 256 + 256
    bounds.remember(frame, 990_000)  # spread 10,000: twice it
    assert bounds.capacity(frame) == 1_000_000 + 20_000 + 1_000_000 // 256 + 256
    bounds.remember(frame, 500_000)  # spread 500,000: an eighth at most
    assert bounds.capacity(frame) == 1_000_000 + 125_000 + 1_000_000 // 256 + 256
    assert bounds.capacity(other) == 0  # per frame size
    for _ in range(KeyBounds.FRAMES):
        bounds.remember(frame, 2_000)  # the large totals leave the window
    assert bounds.capacity(frame) == 2_000 + 2_000 // 256 + 256
    bounds.remember(frame, MAX_INTERSECTIONS)
    assert bounds.capacity(frame) == MAX_INTERSECTIONS


def weighted_loss(image: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    g = torch.Generator().manual_seed(11)
    w_image = torch.rand(image.shape, generator=g, dtype=torch.float64) - 0.3
    w_alpha = torch.rand(alpha.shape, generator=g, dtype=torch.float64) - 0.3
    return (image * w_image.to(image)).sum() + (alpha * w_alpha.to(alpha)).sum()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("inline_lanes", [None, 33])
def test_frames_past_the_kept_bound_write_their_keys_again(write_capacities, device, inline_lanes, monkeypatch):
    """Each frame of a growing sequence needs more intersections than the bound kept from the frames
    before it (none for the first): its keys, written before the sync up to the bound, are written
    again at the right size after it. The image matches the reference, and equals bit for bit the
    same frame rendered again within the bound (keys written once, before the sync). With every warp
    listing its Gaussians (inline_lanes 33), the keys written again run inline: binning's lists have
    served the first write."""
    from tomgs.render import stages

    monkeypatch.setattr(stages.kernel_choices, "inline_lanes", inline_lanes)
    width, height = 96, 80
    # (1500 left two pixels of a float32 render 8e-4 from the float64 reference on the H100, the same
    # before tile keys moved before the sync: a scene at the float32 edge, not this path)
    for n in (40, 250, 700):
        scene = random_scene(90 + n, n=n, width=width, height=height)
        write_capacities.clear()
        (image, alpha, meta), (ref_image, ref_alpha, _), ours_in, _ = render_both(scene, device)
        total = meta["n_intersections"]
        assert len(write_capacities) == 2 and write_capacities[0] < write_capacities[1] == total
        assert (image.detach().double().cpu() - ref_image).abs().max() <= IMAGE_TOL
        assert (alpha.detach().double().cpu() - ref_alpha).abs().max() <= IMAGE_TOL

        write_capacities.clear()
        named = dict(zip(INPUT_NAMES, ours_in))
        again, again_alpha, _ = tomgs.rasterize(**named, width=width, height=height,
                                                t=float(torch.tensor(scene["t"], dtype=torch.float32)))
        assert len(write_capacities) == 1 and write_capacities[0] >= total
        assert torch.equal(again, image) and torch.equal(again_alpha, alpha)


@pytest.mark.parametrize("device", DEVICES)
def test_two_frames_forward_before_either_backward(write_capacities, device):
    """Two views per training step: both forwards run before either backward, each with its keys
    written before the sync. Each frame's list (its ids, which its backward reads) is its own: the
    gradients match the reference and, on the CPU, equal bit for bit those of each frame run alone."""
    scenes = [random_scene(140 + k, n=300, width=64, height=48) for k in range(2)]
    alone = []
    for scene in scenes:  # each alone, which also leaves a bound that holds both frames
        (image, alpha, _), _, ours_in, _ = render_both(scene, device)
        alone.append(torch.autograd.grad(weighted_loss(image, alpha), ours_in))
    write_capacities.clear()
    frames = [render_both(scene, device) for scene in scenes]
    assert len(write_capacities) == 2 and write_capacities[0] == write_capacities[1] > 0  # before the sync only
    assert frames[0][0][2]["n_intersections"] != frames[1][0][2]["n_intersections"]
    for k in (1, 0):  # the backwards, the later frame's first
        (image, alpha, _), (ref_image, ref_alpha, _), ours_in, ref_in = frames[k]
        grads = torch.autograd.grad(weighted_loss(image, alpha), ours_in)
        ref_grads = torch.autograd.grad(weighted_loss(ref_image, ref_alpha), ref_in)
        for name, grad, ref_grad, grad_alone in zip(INPUT_NAMES, grads, ref_grads, alone[k]):
            assert rel_l2(grad, ref_grad) <= GRAD_TOL, (k, name, rel_l2(grad, ref_grad))
            assert device != "cpu" or torch.equal(grad, grad_alone), (k, name)
