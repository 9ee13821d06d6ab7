"""Each rasterizer stage alone against its pure-torch reference (tomgs.render.reference), on fresh random
inputs with the extremes mixed in: projection (values and gradients) and binning (the sorted
intersection list and the tile ranges). tests/render/test_raster.py checks the stages end to end."""

from __future__ import annotations

import math

import pytest
import torch

from tomgs.constants import ALPHA_MIN, TILE_SIZE, sort_low_bit
from tomgs.render.reference import bin_reference, project_reference, tile_levels, tile_rects, tiles_touched_reference
from tomgs.render.frame import bin_stage, project_stage
from scenes import SEED_BASE, devices, random_scene, rel_l2

DEVICES = devices()
PROJECT_INPUTS = ("means", "quats", "scales", "opacities", "t_means", "t_scales", "viewmat", "K")
DIFFERENTIABLE = ("means2d", "conics", "opacities_t")
GRAD_TOL = 2e-4  # relative L2 error of each input's gradient (float32 arithmetic misses by ~1e-5 here)


def camera_points(view: torch.Tensor, cam: torch.Tensor) -> torch.Tensor:
    """World positions [n,3] of camera-space points cam [n,3] for world -> camera `view`."""
    c2w = torch.linalg.inv(view)
    return cam @ c2w[:3, :3].T + c2w[:3, 3]


def extreme_scene(seed: int, n: int = 80) -> tuple[dict, dict[str, slice]]:
    """random_scene (overlap, off screen, behind the camera, at the near plane) followed by rows of
    each extreme; returns the scene and the rows of each kind."""
    scene = random_scene(seed, n=n)
    g = torch.Generator().manual_seed(SEED_BASE * 1000 + 500 + seed)
    view, t, f64 = scene["viewmat"], scene["t"], torch.float64
    rows: dict[str, torch.Tensor] = {}  # kind -> camera-space points
    extra: dict[str, dict] = {}  # kind -> per-Gaussian overrides

    def add(kind, cam, **fields):
        rows[kind], extra[kind] = torch.as_tensor(cam, dtype=f64).reshape(-1, 3), fields

    z = 1.0 + 3.0 * torch.rand(4, generator=g, dtype=f64)
    add("behind", torch.stack([torch.zeros(4, dtype=f64), torch.zeros(4, dtype=f64), -z], -1))
    add("beyond_far", [[0.0, 0.0, 2e10]])
    add("off_screen", [[40.0, 0.0, 2.0], [0.0, -40.0, 2.0], [-40.0, 30.0, 2.0]])
    add("dead_in_time", [[0.0, 0.1, 2.0], [0.1, 0.0, 2.5]], t_means=[t - 4.0, t + 40.0], t_scales=[1.0, 0.5])
    add("zero_t_scale", [[0.05, 0.05, 2.0]], t_means=[t + 0.1], t_scales=[0.0])
    add("transparent", [[0.0, 0.0, 2.0], [0.1, 0.1, 2.0]], opacities=[0.0, ALPHA_MIN * 0.99])
    add("non_finite", [[math.nan, 0.0, 2.0], [math.inf, 0.0, 2.0]])
    add("non_finite_scale", [[0.0, 0.0, 2.0]], scales=[[math.inf, 0.1, 0.1]])
    add("huge", [[0.1, -0.1, 1.5], [-0.3, 0.2, 3.0]], scales=[[30.0, 20.0, 25.0], [12.0, 9.0, 10.0]])
    add("tiny", [[0.2, 0.1, 2.0], [-0.2, 0.0, 4.0], [0.0, 0.05, 0.5]], scales=[[1e-9, 1e-9, 1e-9]] * 3)
    add("zero_quat", [[0.0, -0.2, 2.0]], quats=[[0.0, 0.0, 0.0, 0.0]])
    # a few Gaussians around each tile border crossing of the image, so their boxes straddle tiles
    fx, fy, cx, cy = (float(scene["K"][i, j]) for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)))
    px = torch.tensor([TILE_SIZE, 2 * TILE_SIZE, TILE_SIZE + 0.5, 2 * TILE_SIZE - 0.25], dtype=f64)
    py = torch.tensor([TILE_SIZE, TILE_SIZE - 0.5, 2 * TILE_SIZE, TILE_SIZE + 0.25], dtype=f64)
    depth = 2.0 + torch.rand(4, generator=g, dtype=f64)
    add("straddling", torch.stack([(px - cx) / fx * depth, (py - cy) / fy * depth, depth], -1),
        scales=[[0.02, 0.05, 0.03], [0.1, 0.01, 0.05], [0.004, 0.004, 0.004], [0.06, 0.06, 0.06]])

    kinds, start = {}, n
    for kind, cam in rows.items():
        k = len(cam)
        new = dict(means=camera_points(view, cam), quats=torch.randn(k, 4, generator=g, dtype=f64),
                   scales=torch.exp(torch.randn(k, 3, generator=g, dtype=f64) * 0.3 - 2.5),
                   opacities=0.2 + 0.75 * torch.rand(k, generator=g, dtype=f64),
                   t_means=t + 0.05 * torch.randn(k, generator=g, dtype=f64),
                   t_scales=torch.full((k,), 0.5, dtype=f64), colors=torch.rand(k, 3, generator=g, dtype=f64))
        for name, value in extra[kind].items():
            new[name] = torch.as_tensor(value, dtype=f64).reshape(new[name].shape)
        for name, value in new.items():
            scene[name] = torch.cat([scene[name], value])
        kinds[kind] = slice(start, start + k)
        start += k
    return scene, kinds


def float32_values(scene: dict) -> dict:
    """The scene's tensors rounded to float32 and back, so both sides see the same numbers."""
    out = {k: (v.float().double() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    out["t"] = float(torch.tensor(scene["t"], dtype=torch.float32))
    return out


def run_projection(scene: dict, device: str):
    """(ours, ref, our inputs, ref inputs): project_stage on `device` (float32) and
    project_reference on the CPU (float64), both on leaf tensors that require gradients."""
    ours_in = [scene[k].detach().float().to(device).requires_grad_(True) for k in PROJECT_INPUTS]
    ref_in = [scene[k].detach().clone().requires_grad_(True) for k in PROJECT_INPUTS]
    size = (scene["width"], scene["height"], scene["t"])
    return project_stage(*ours_in, *size), project_reference(*ref_in, *size), ours_in, ref_in


def radius_ties(extent: torch.Tensor) -> torch.Tensor:
    """[N,2] where float32 cannot call the rounding up of the float64 radius (it is ~an integer)."""
    return (extent - extent.round()).abs() <= 1e-5 * extent + 1e-6


def near_tile_border(means2d: torch.Tensor, radii: torch.Tensor, tol: float = 1e-3) -> torch.Tensor:
    """[N] where a box edge means2d +- radii lies within `tol` px of a tile border (float32 may
    put it on either side)."""
    edges = torch.cat([means2d - radii, means2d + radii], -1).double()
    offset = torch.remainder(edges, TILE_SIZE)
    return (torch.minimum(offset, TILE_SIZE - offset) <= tol * (1.0 + edges.abs() / TILE_SIZE)).any(-1)


def near_level(means2d, conics, opacities_t, radii, width, height, tol: float = 1e-3) -> torch.Tensor:
    """[N] where a tile of the box lies within `tol` (relative) of the ellipse's level (float32 may
    put it on either side)."""
    pairs = tile_levels(means2d, conics, opacities_t, radii, width, height)
    close = (pairs["low"] - pairs["level"]).abs() <= tol * pairs["level"]
    return torch.zeros(len(means2d), dtype=torch.bool).index_put_((pairs["ids"],), close, accumulate=True)


def assert_projection_matches(scene: dict, device: str, kinds: dict[str, slice] | None = None) -> dict:
    scene = float32_values(scene)
    ours, ref, ours_in, ref_in = run_projection(scene, device)
    n = scene["means"].shape[0]
    got = {k: v.detach().cpu() for k, v in ours.items()}
    assert got["radii"].dtype == torch.int32 and got["tiles_touched"].dtype == torch.int32
    assert {k: tuple(v.shape) for k, v in got.items()} == dict(means2d=(n, 2), conics=(n, 3), depths=(n,),
                                                              radii=(n, 2), opacities_t=(n,), tiles_touched=(n,))
    # visibility exactly; radii up to a float32 tie; culled rows zero
    visible, ref_visible = got["radii"].amax(-1) > 0, ref["radii"].amax(-1) > 0
    assert torch.equal(visible, ref_visible)
    diff = (got["radii"].long() - ref["radii"]).abs()
    assert ((diff == 0) | ((diff == 1) & radius_ties(ref["extent"]))).all(), diff.amax()
    for name in ("means2d", "conics", "tiles_touched"):
        assert (got[name][~visible] == 0).all(), name
    # values: float32 arithmetic against float64
    torch.testing.assert_close(got["depths"].double(), ref["depths"], rtol=1e-5, atol=1e-5, equal_nan=True)
    torch.testing.assert_close(got["opacities_t"].double(), ref["opacities_t"], rtol=1e-5, atol=1e-7, equal_nan=True)
    torch.testing.assert_close(got["means2d"].double(), ref["means2d"], rtol=1e-4, atol=1e-3)
    torch.testing.assert_close(got["conics"].double(), ref["conics"], rtol=1e-4, atol=1e-6)
    # tiles touched: exactly the ellipse tiles of the stage's own outputs, and the reference's wherever
    # float32 cannot put a box edge on the other side of a tile border or a tile on the other side of the level
    width, height = scene["width"], scene["height"]
    own = tiles_touched_reference(got["means2d"], got["conics"], got["opacities_t"], got["radii"], width, height)
    assert torch.equal(got["tiles_touched"].long(), own)
    ref_values = [ref[k].detach() for k in ("means2d", "conics", "opacities_t")]
    clear = ((diff == 0).all(-1) & ~near_tile_border(ref["means2d"], ref["radii"])
             & ~near_level(*ref_values, ref["radii"], width, height))
    assert torch.equal(got["tiles_touched"].long()[clear], ref["tiles_touched"][clear])

    # gradients of a random linear loss of the differentiable outputs, culled rows exactly zero
    g = torch.Generator().manual_seed(SEED_BASE + 17)
    weights = {k: torch.rand(ref[k].shape, generator=g, dtype=torch.float64) - 0.3 for k in DIFFERENTIABLE}
    weights["means2d"] /= ref["means2d"].detach().abs().clamp_min(1.0)  # every Gaussian counts, not the far off ones
    loss = sum((ours[k] * weights[k].to(ours[k])).sum() for k in DIFFERENTIABLE)
    ref_loss = sum((ref[k] * weights[k]).sum() for k in DIFFERENTIABLE)
    grads = torch.autograd.grad(loss, ours_in, allow_unused=True)
    ref_grads = torch.autograd.grad(ref_loss, ref_in, allow_unused=True)
    for name, x, grad, ref_x, ref_grad in zip(PROJECT_INPUTS, ours_in, grads, ref_in, ref_grads):
        grad = torch.zeros_like(x) if grad is None else grad
        ref_grad = torch.zeros_like(ref_x) if ref_grad is None else ref_grad
        assert torch.isfinite(grad).all(), name
        if name not in ("viewmat", "K"):
            assert (grad.cpu()[~visible] == 0).all() and (ref_grad[~ref_visible] == 0).all(), name
        assert rel_l2(grad, ref_grad) <= GRAD_TOL, (name, rel_l2(grad, ref_grad))
    if kinds is not None:
        for kind in ("behind", "beyond_far", "off_screen", "dead_in_time", "zero_t_scale", "transparent",
                     "non_finite", "non_finite_scale"):
            assert not visible[kinds[kind]].any(), kind
        for kind in ("huge", "tiny", "zero_quat", "straddling"):
            assert visible[kinds[kind]].all(), kind
        tiles = -(-width // TILE_SIZE) * -(-height // TILE_SIZE)
        assert (got["tiles_touched"][kinds["huge"]] == tiles).all()  # larger than the image: every tile
        assert (got["tiles_touched"][kinds["straddling"]] > 1).all()
    return got


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("seed", range(4))
def test_projection_matches_reference_on_random_scenes(seed, device):
    got = assert_projection_matches(random_scene(200 + seed, n=150), device)
    visible = got["radii"].amax(-1) > 0
    assert 0 < int(visible.sum()) < len(visible)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("seed", range(4))
def test_projection_matches_reference_on_extremes(seed, device):
    scene, kinds = extreme_scene(210 + seed)
    assert_projection_matches(scene, device, kinds)


@pytest.mark.parametrize("device", DEVICES)
def test_projection_radius_is_clamped_for_a_giant(device):
    """A Gaussian whose box is wider than 2^30 px: radius clamped to 2^30, every tile, values finite."""
    scene = random_scene(220, n=20)
    view = scene["viewmat"]
    scene["means"][0] = camera_points(view, torch.tensor([[0.0, 0.0, 2.0]], dtype=torch.float64))[0]
    scene["scales"][0] = 1e8
    scene["t_means"][0], scene["t_scales"][0], scene["opacities"][0] = scene["t"], 1.0, 0.9
    scene = float32_values(scene)
    ours, ref, _, _ = run_projection(scene, device)
    assert ours["radii"][0].tolist() == [2**30, 2**30] and ref["radii"][0].tolist() == [2**30, 2**30]
    tiles = -(-scene["width"] // TILE_SIZE) * -(-scene["height"] // TILE_SIZE)
    assert int(ours["tiles_touched"][0]) == int(ref["tiles_touched"][0]) == tiles
    torch.testing.assert_close(ours["means2d"][0].detach().double().cpu(), ref["means2d"][0].detach(), rtol=1e-5,
                               atol=1e-3)
    assert torch.isfinite(ours["conics"][0]).all()


@pytest.mark.parametrize("device", DEVICES)
def test_projection_of_no_gaussians(device):
    scene = random_scene(230, n=0)
    scene = float32_values(scene)
    ours, ref, ours_in, ref_in = run_projection(scene, device)
    for name in ("means2d", "conics", "depths", "radii", "opacities_t", "tiles_touched"):
        assert ours[name].shape[0] == 0 and ref[name].shape[0] == 0, name
    loss = ours["means2d"].sum() + ours["conics"].sum() + ours["opacities_t"].sum()
    grads = torch.autograd.grad(loss, ours_in, allow_unused=True)
    assert all(g is None or g.abs().sum() == 0 for g in grads)


def random_conics(g: torch.Generator, n: int, sigma_min: float = 0.5, sigma_max: float = 40.0):
    """(conics [n,3] float32, opacities [n] float32): rotated ellipses of standard deviations from
    sigma_min to sigma_max px per axis (needles of aspect up to ~80 among them), opacities from just
    above 1/255 to 1."""
    log_s = torch.rand(n, 2, generator=g, dtype=torch.float64) * math.log(sigma_max / sigma_min) + math.log(sigma_min)
    s = torch.exp(log_s)
    theta = torch.rand(n, generator=g, dtype=torch.float64) * math.pi
    c, si = torch.cos(theta), torch.sin(theta)
    a = c * c / s[:, 0] ** 2 + si * si / s[:, 1] ** 2  # conic = R diag(1 / s^2) R^T
    b = c * si * (1 / s[:, 0] ** 2 - 1 / s[:, 1] ** 2)
    d = si * si / s[:, 0] ** 2 + c * c / s[:, 1] ** 2
    opac = torch.where(torch.rand(n, generator=g) < 0.2, ALPHA_MIN * (1 + torch.rand(n, generator=g) * 1e-2),
                       torch.rand(n, generator=g)).clamp(min=ALPHA_MIN * 1.0001)
    return torch.stack([a, b, d], -1).float(), opac.float()


def random_boxes(seed: int, n: int, width: int, height: int, device: str):
    """Binning inputs of every awkward kind: (means2d [n,2] float32, conics [n,3] float32, opacities [n]
    float32, radii [n,2] int32, depths [n] float32). Centres on and around tile borders, box edges
    exactly on them, boxes off screen and partly on, radius (0, 0) (culled) and radii from 1 px to 2^30,
    random rotated ellipses (inside the box or clipped by it; huge ones in the huge boxes), and depths
    with ties."""
    g = torch.Generator().manual_seed(SEED_BASE * 1000 + 300 + seed)
    means2d = torch.stack([torch.rand(n, generator=g) * (width + 80) - 40,
                           torch.rand(n, generator=g) * (height + 80) - 40], -1)
    kind = torch.randint(0, 8, (n,), generator=g)
    on_border = torch.randint(-1, 5, (n, 2), generator=g).float() * TILE_SIZE
    means2d = torch.where((kind == 1)[:, None], on_border, means2d)  # centre on a border
    radii = torch.randint(1, 24, (n, 2), generator=g, dtype=torch.int32)
    radii[kind == 2] = 0  # culled
    radii[kind == 3] = torch.randint(200, 2**30, (int((kind == 3).sum()), 2), generator=g, dtype=torch.int32)
    radii[kind == 4] = 2**30
    edge = (kind == 5)[:, None]  # the left / top box edge exactly on a border
    means2d = torch.where(edge, on_border + radii.float(), means2d)
    edge = (kind == 6)[:, None]  # the right / bottom edge exactly on a border, and just short of it
    shift = torch.where(torch.rand(n, 1, generator=g) < 0.5, 0.0, 1e-3)
    means2d = torch.where(edge, on_border - radii.float() - shift, means2d)
    radii[kind == 7, 0] = 0  # a one-axis box: the kernel treats only (0, 0) as culled
    depths = torch.rand(n, generator=g) * 5 + 0.01
    depths[torch.rand(n, generator=g) < 0.3] = 2.5  # ties: equal keys keep Gaussian order
    conics, opacities = random_conics(g, n)
    huge = (kind == 3) | (kind == 4)
    conics[huge] = random_conics(g, int(huge.sum()), 1e3, 1e5)[0]  # every tile of the image
    return tuple(x.to(device) for x in (means2d.float(), conics, opacities, radii, depths.float()))


def assert_binning_matches(means2d, conics, opacities, radii, depths, width, height) -> dict:
    ellipses = [x.cpu() for x in (means2d, conics, opacities, radii)]
    touched = tiles_touched_reference(*ellipses, width, height).int().to(means2d.device)
    ours = bin_stage(means2d, conics, opacities, radii, depths, touched, width, height)
    ref = bin_reference(*ellipses, depths.cpu(), width, height)
    tiles = -(-width // TILE_SIZE) * -(-height // TILE_SIZE)
    assert ours["keys"].dtype == torch.int64 and ours["ids"].dtype == torch.int32
    assert ours["ranges"].dtype == torch.int32
    assert ours["ranges"].shape == (tiles, 2)
    assert torch.equal(ours["keys"].cpu(), ref["keys"])
    assert torch.equal(ours["ids"].long().cpu(), ref["ids"])
    assert torch.equal(ours["ranges"].long().cpu(), ref["ranges"])
    # the reference's list is what it says: (tile, depth, Gaussian) ascending, ranges cover it
    keys, ids = ref["keys"], ref["ids"]
    assert torch.equal(ref["tiles"], keys >> 32)
    order = torch.stack([ref["tiles"], (keys & 0xFFFFFFFF) >> sort_low_bit(width, height), ids], -1).tolist()
    assert order == sorted(order)
    assert int((ref["ranges"][:, 1] - ref["ranges"][:, 0]).sum()) == len(keys) == int(touched.sum())
    return ref


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("size", [(45, 37), (64, 48), (16, 16), (100, 7)])
def test_binning_matches_reference(seed, size, device):
    width, height = size
    inputs = random_boxes(seed, 120, width, height, device)
    ref = assert_binning_matches(*inputs, width, height)
    # the inputs do what they are for: Gaussians of many tiles, of none, and equal keys
    touched = tiles_touched_reference(*[x.cpu() for x in inputs[:4]], width, height)
    assert (touched == 0).any() and (touched == len(ref["ranges"])).any()
    if len(ref["ranges"]) > 1:
        assert ((touched > 1) & (touched < len(ref["ranges"]))).any()
    assert len(torch.unique(ref["keys"])) < len(ref["keys"])


@pytest.mark.parametrize("device", DEVICES)
def test_binning_of_projected_gaussians(device):
    """The projection stage's own outputs binned: what rasterize does between the two."""
    scene, _ = extreme_scene(240)
    ours, _, _, _ = run_projection(float32_values(scene), device)
    ours = {k: v.detach() for k, v in ours.items()}
    names = ("means2d", "conics", "opacities_t", "radii", "depths")
    out = bin_stage(*[ours[k] for k in names[:4]], ours["depths"], ours["tiles_touched"], scene["width"],
                    scene["height"])
    ref = bin_reference(*[ours[k].cpu() for k in names], scene["width"], scene["height"])
    assert torch.equal(out["keys"].cpu(), ref["keys"]) and torch.equal(out["ids"].long().cpu(), ref["ids"])
    assert torch.equal(out["ranges"].long().cpu(), ref["ranges"])


@pytest.mark.parametrize("device", DEVICES)
def test_binning_of_nothing(device):
    """N = 0, and N > 0 with every Gaussian culled or off screen: an empty list, every range (0, 0)."""
    for means2d, radii in ((torch.zeros(0, 2), torch.zeros(0, 2, dtype=torch.int32)),
                           (torch.tensor([[10.0, 10.0], [-50.0, 5.0], [5.0, 200.0]]),
                            torch.tensor([[0, 0], [3, 3], [4, 4]], dtype=torch.int32))):
        n = len(means2d)
        conics, opacities = torch.tensor([[0.1, 0.0, 0.1]]).repeat(n, 1), torch.full((n,), 0.5)
        ref = assert_binning_matches(*[x.to(device) for x in (means2d, conics, opacities, radii)],
                                     torch.ones(n, device=device), 45, 37)
        assert len(ref["keys"]) == 0 and (ref["ranges"] == 0).all()


def test_tile_rects_by_hand():
    """The reference's boxes on numbers worked by hand (tile 16 px, a 45 x 37 image: 3 x 3 tiles)."""
    means2d = torch.tensor([[16.0, 16.0], [15.5, 0.0], [44.0, 36.0], [-3.0, 8.0], [8.0, 8.0]], dtype=torch.float64)
    radii = torch.tensor([[0, 0], [0, 1], [100, 2], [2, 2], [8, 8]])
    rects = tile_rects(means2d, radii, 45, 37).tolist()
    assert rects == [[1, 1, 2, 2], [0, 0, 1, 1], [0, 2, 3, 3], [0, 0, 0, 1], [0, 0, 2, 2]]
    wide = torch.tensor([[1e-6, 0.0, 1e-6]], dtype=torch.float64).repeat(5, 1)  # an ellipse larger than any box
    opacities = torch.full((5,), 0.5, dtype=torch.float64)
    assert tiles_touched_reference(means2d, wide, opacities, radii, 45, 37).tolist() == [0, 1, 3, 0, 4]
