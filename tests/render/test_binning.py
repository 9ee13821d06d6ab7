"""Ellipse binning: a Gaussian's keys are the tiles of its box that its alpha >= 1/255 ellipse reaches.

The key list against the torch reference (tomgs.render.reference.ellipse_tiles, a dense minimum of the
quadratic over every tile of the box) on awkward ellipses; a thin diagonal Gaussian's list shrinks to
about its ellipse's tiles; and no tile holding a pixel that the raster draws (alpha >= 1/255) is
ever dropped, checked pixel by pixel."""

from __future__ import annotations

import math

import pytest
import torch

from tomgs.constants import ALPHA_MIN, DEPTH_SORT_BITS, RADIUS_SIGMAS, TILE_SIZE, sort_low_bit
from tomgs.render.reference import bin_reference, tile_rects, tiles_touched_reference
from tomgs.render.frame import bin_stage, project_stage
from scenes import SEED_BASE, devices, random_scene
from tests.render.test_stages import camera_points, float32_values

DEVICES = devices()


def extent_of(opacities: torch.Tensor) -> torch.Tensor:
    """Standard deviations out to which alpha >= 1/255, as projection bounds the radius."""
    return torch.sqrt((2.0 * torch.log(opacities.double() / ALPHA_MIN)).clamp_min(0)).clamp(max=RADIUS_SIGMAS)


def ellipses(sigmas: torch.Tensor, theta: torch.Tensor, opacities: torch.Tensor):
    """(conics [n,3] float32, radii [n,2] int32) of Gaussians with standard deviations sigmas [n,2]
    (px) along axes rotated by theta [n], the radii as projection rounds them (ceil(extent sqrt(cov)))."""
    c, s = torch.cos(theta.double()), torch.sin(theta.double())
    rot = torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], -2)
    cov = rot @ torch.diag_embed(sigmas.double() ** 2) @ rot.transpose(-1, -2)
    conic = torch.linalg.inv(cov)
    radii = torch.ceil(extent_of(opacities)[:, None] * torch.diagonal(cov, dim1=-2, dim2=-1).sqrt())
    return torch.stack([conic[:, 0, 0], conic[:, 0, 1], conic[:, 1, 1]], -1).float(), radii.int()


def awkward_ellipses(seed: int, n: int, width: int, height: int):
    """(means2d, conics, opacities, radii, depths) with every awkward kind mixed: needles of aspect up
    to 1000 at any angle, huge ones, centres off screen with the ellipse partly on, centres on tile
    borders, near-degenerate conics (det ~ 0 and below in float32), an underflowed conic, opacities a
    hair above 1/255 and near 1."""
    g = torch.Generator().manual_seed(SEED_BASE * 1000 + 700 + seed)
    u = lambda *shape: torch.rand(*shape, generator=g, dtype=torch.float64)  # noqa: E731
    kind = torch.randint(0, 7, (n,), generator=g)
    means2d = torch.stack([u(n) * (width + 200) - 100, u(n) * (height + 200) - 100], -1)
    on_border = torch.randint(-1, 6, (n, 2), generator=g).double() * TILE_SIZE
    means2d = torch.where((kind == 1)[:, None], on_border, means2d)
    sigmas = torch.exp(u(n, 2) * math.log(60.0 / 0.55)) * 0.55
    needle = kind == 2
    sigmas[needle, 0] = 0.55 + u(int(needle.sum())) * 0.3
    sigmas[needle, 1] = 50.0 + u(int(needle.sum())) * 500.0
    sigmas[kind == 3] = 1e3 + u(int((kind == 3).sum()), 2) * 1e4  # huge
    theta = u(n) * math.pi
    theta[kind == 4] = math.pi / 4 + (u(int((kind == 4).sum())) - 0.5) * 1e-3
    opacities = u(n)
    pick = u(n)
    opacities = torch.where(pick < 0.2, ALPHA_MIN * (1.0 + u(n) * 1e-3), opacities)
    opacities = torch.where(pick > 0.85, 1.0 - u(n) * 1e-3, opacities).clamp(ALPHA_MIN * 1.00001, 1.0)
    conics, radii = ellipses(sigmas, theta, opacities)
    degenerate = torch.nonzero(kind == 5).squeeze(-1)  # B^2 = AC to a few float32 ulps, both signs of det
    a, c = conics[degenerate, 0].double(), conics[degenerate, 2].double()
    ulps = torch.randint(-3, 4, (len(degenerate),), generator=g).double()
    conics[degenerate, 1] = (torch.sqrt(a * c) * (1.0 + ulps * 2.0**-23)).float()
    underflow = torch.nonzero(kind == 6).squeeze(-1)[:2]
    conics[underflow, 0] = 0.0  # A underflowed in float32: the whole box
    radii = torch.where((radii == 0).all(-1, keepdim=True), torch.ones_like(radii), radii).clamp(max=2**30)
    depths = (u(n) * 5 + 0.01).float()
    return means2d.float(), conics, opacities.float(), radii, depths


def drawn_tiles(means2d, conics, opacities, width, height) -> list[set[int]]:
    """Per Gaussian, the tiles with a pixel whose alpha = opacity exp(-power) >= 1/255, power taken both
    exactly (float64 of the float32 inputs) and in the raster's float32 order."""
    ys, xs = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    tile = (ys.long() // TILE_SIZE) * -(-width // TILE_SIZE) + xs.long() // TILE_SIZE
    out = []
    for center, conic, opac in zip(means2d, conics, opacities):
        drawn = torch.zeros(height, width, dtype=torch.bool)
        for dtype in (torch.float64, torch.float32):
            dx, dy = center[0].to(dtype) - xs.to(dtype), center[1].to(dtype) - ys.to(dtype)
            a, b, c = conic.to(dtype)
            power = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
            drawn |= opac.to(dtype) * torch.exp(-power) >= torch.tensor(ALPHA_MIN, dtype=torch.float32).to(dtype)
        out.append(set(tile[drawn].tolist()))
    return out


def listed_tiles(keys, ids, n) -> list[set[int]]:
    tiles = [set() for _ in range(n)]
    for key, i in zip((keys.cpu() >> 32).tolist(), ids.cpu().tolist()):
        tiles[i].add(key)
    return tiles


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("size", [(640, 360), (45, 37), (200, 16)])
def test_keys_match_reference_on_awkward_ellipses(seed, size, device):
    width, height = size
    inputs = awkward_ellipses(seed, 300, width, height)
    touched = tiles_touched_reference(*inputs[:4], width, height)
    ours = bin_stage(*[x.to(device) for x in inputs], touched.int().to(device), width, height)
    ref = bin_reference(*inputs, width, height)
    assert torch.equal(ours["keys"].cpu(), ref["keys"]) and torch.equal(ours["ids"].long().cpu(), ref["ids"])
    assert torch.equal(ours["ranges"].long().cpu(), ref["ranges"])
    # never more than the box, at least one tile of a box on screen, and fewer than the boxes in all
    rect = tile_rects(inputs[0], inputs[3], width, height)
    box = (rect[:, 2] - rect[:, 0]) * (rect[:, 3] - rect[:, 1])
    assert (touched <= box).all() and ((touched >= 1) | (box == 0)).all()
    assert touched.sum() < box.sum()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("angle", [45.0, -45.0, 30.0])
def test_thin_diagonal_gaussian_keeps_about_its_ellipse(angle, device):
    """A needle across a 512 x 512 image: its box holds ~30 x 30 tiles, its list about the tiles along
    the diagonal (those holding a drawn pixel, and a few its ellipse grazes between pixel centres)."""
    width = height = 512
    conics, radii = ellipses(torch.tensor([[100.0, 0.6]]), torch.tensor([math.radians(angle)]), torch.tensor([1.0]))
    means2d = torch.tensor([[256.3, 255.7]])
    opacities, depths = torch.ones(1), torch.ones(1)
    touched = tiles_touched_reference(means2d, conics, opacities, radii, width, height)
    out = bin_stage(*[x.to(device) for x in (means2d, conics, opacities, radii, depths)], touched.int().to(device),
                    width, height)
    rect = tile_rects(means2d, radii, width, height)[0]
    box = int((rect[2] - rect[0]) * (rect[3] - rect[1]))
    n = int(rect[2] - rect[0])
    drawn = drawn_tiles(means2d, conics, opacities, width, height)[0]
    listed = listed_tiles(out["keys"], out["ids"], 1)[0]
    assert drawn <= listed
    assert box >= 500 and len(listed) <= 3 * n + 4 and len(listed) <= 1.25 * len(drawn) + 4, (box, len(listed),
                                                                                               len(drawn))


def scene_with_extreme_opacities(seed: int, width: int, height: int) -> dict:
    """random_scene at `width` x `height`, half of its opacities a hair above 1/255 or near 1, and a few
    needles, at t with the temporal windows wide open, so the opacities are what the raster sees."""
    scene = random_scene(seed, n=120, width=width, height=height)
    g = torch.Generator().manual_seed(SEED_BASE * 1000 + 800 + seed)
    n = len(scene["opacities"])
    pick = torch.rand(n, generator=g, dtype=torch.float64)
    low = ALPHA_MIN * (1.0 + torch.rand(n, generator=g, dtype=torch.float64) * 1e-2)
    high = 1.0 - torch.rand(n, generator=g, dtype=torch.float64) * 1e-3
    scene["opacities"] = torch.where(pick < 0.25, low, torch.where(pick > 0.75, high, scene["opacities"]))
    scene["t_scales"] = torch.full((n,), 1e3, dtype=torch.float64)
    needles = slice(0, 12)
    scene["scales"][needles] = torch.tensor([0.4, 1e-4, 1e-3], dtype=torch.float64)
    cam = torch.stack([torch.rand(12, generator=g, dtype=torch.float64) - 0.5,
                       torch.rand(12, generator=g, dtype=torch.float64) - 0.5, torch.full((12,), 2.5)], -1)
    scene["means"][needles] = camera_points(scene["viewmat"], cam.double())
    return float32_values(scene)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("size", [(45, 37), (160, 120)])
def test_no_tile_with_a_drawn_pixel_is_dropped(seed, size, device):
    """Projected Gaussians (opacities near 1/255 and near 1, needles, off screen, huge) and awkward
    ellipses: every tile holding a pixel of alpha >= 1/255 is in the Gaussian's list."""
    width, height = size
    scene = scene_with_extreme_opacities(900 + seed, width, height)
    names = ("means", "quats", "scales", "opacities", "t_means", "t_scales", "viewmat", "K")
    proj = project_stage(*[scene[k].float().to(device) for k in names], width, height, scene["t"])
    proj = {k: v.detach() for k, v in proj.items()}
    fields = ("means2d", "conics", "opacities_t", "radii", "depths")
    cases = [tuple(proj[k] for k in fields) + (proj["tiles_touched"],)]
    awkward = awkward_ellipses(seed, 60, width, height)
    cases.append(tuple(x.to(device) for x in awkward) + (tiles_touched_reference(*awkward[:4], width, height).int()
                                                         .to(device),))
    for means2d, conics, opacities, radii, depths, touched in cases:
        visible = (radii != 0).any(-1).cpu()
        out = bin_stage(means2d, conics, opacities, radii, depths, touched, width, height)
        listed = listed_tiles(out["keys"], out["ids"], len(means2d))
        drawn = drawn_tiles(means2d.cpu()[visible], conics.cpu()[visible], opacities.cpu()[visible], width, height)
        rect = tile_rects(means2d.cpu(), radii.cpu(), width, height)
        tiles_x = -(-width // TILE_SIZE)
        for i, tiles in zip(torch.nonzero(visible).squeeze(-1).tolist(), drawn):
            x0, y0, x1, y1 = rect[i].tolist()
            box = {ty * tiles_x + tx for ty in range(y0, y1) for tx in range(x0, x1)}
            assert tiles & box <= listed[i], (i, sorted(tiles & box - listed[i]))
        assert sum(len(d) for d in drawn) > 0


# ---- keys written before the frame's host sync: the capacity guard, and the sort on tensors --------

def write_keys(inputs, touched: torch.Tensor, width: int, height: int, capacity: int, size: int,
               ends: torch.Tensor | None = None, sentinel: int = -7, inline_lanes: int = 1):
    """binning.write_tile_keys launched as rasterize launches it, with `capacity`, into keys and ids of
    `size` slots filled with `sentinel`: (keys, ids). `inline_lanes` 33: every warp lists its visible
    Gaussians, which write_tile_keys_listed writes."""
    from tomgs.kernels import binning
    from tomgs.render.stages import Frame, WorkLists, pass_args
    from tomgs.runtime import launch, scope, wrap
    import warp as wp

    means2d, conics, opacities, radii, depths = (x.contiguous() for x in inputs)
    ends = torch.cumsum(touched, 0, dtype=torch.int64) if ends is None else ends
    keys = torch.full((size,), sentinel, dtype=torch.int64, device=means2d.device)
    ids = torch.full((size,), sentinel, dtype=torch.int32, device=means2d.device)
    frame = Frame(width, height, 0.0, 0.0, 0.01, 1e10, "cpu")
    lists = WorkLists(len(means2d), 1, inline_lanes, means2d.device) if inline_lanes > 1 else None
    assert inline_lanes in (1, 33)
    with scope(means2d.device) as device:
        shared = [wrap(means2d, wp.vec2), wrap(conics, wp.vec3), wrap(opacities), wrap(radii, wp.vec2i), wrap(depths),
                  wrap(ends), frame.tiles_x, frame.tiles_y, capacity, wrap(keys), wrap(ids)]
        work = pass_args(lists, 0)
        launch(binning.write_tile_keys, len(means2d), device=device, args=[*shared, *work])
        if lists:
            launch(binning.write_tile_keys_listed, lists.slots, device=device, args=[*shared, *work[1:]])
            assert int(lists.counts.sum()) == int((radii != 0).any(-1).sum())  # every visible one listed
    return keys.cpu(), ids.cpu()


def test_a_pass_of_the_work_lists_serves_one_launch():
    """A pass's counters are zeroed once: the pass runs listed the first time its arguments are taken,
    and inline after (a frame's keys written again past their bound append to no used list)."""
    from tomgs.render.stages import WorkLists, pass_args

    lists = WorkLists(100, 2, 33, torch.device("cpu"))
    first = pass_args(lists, 1)
    assert first[:2] == [33, lists.capacity] and lists.capacity > 0
    assert pass_args(lists, 1)[:2] == [1, 0]  # taken: inline, no list
    assert pass_args(lists, 0)[:2] == [33, lists.capacity]  # the other pass is its own
    assert pass_args(None, 0)[:2] == [1, 0]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("share", [0.0, 0.37, 0.999, 1.0])
@pytest.mark.parametrize("inline_lanes", [1, 33])
def test_keys_stop_at_the_capacity(share, inline_lanes, device):
    """Launched before the intersection count is known, write_tile_keys writes only the slots below its
    capacity: those exactly as with room for all, and nothing past them (the sentinel after stays),
    whether each warp writes its Gaussians' keys itself or lists them for write_tile_keys_listed.
    Every third Gaussian is culled (radii 0, no tiles): no keys, not listed."""
    width, height = 200, 96
    inputs = [x.to(device) for x in awkward_ellipses(11, 200, width, height)]
    inputs[3][::3] = 0
    touched = tiles_touched_reference(*[x.cpu() for x in inputs[:4]], width, height).int().to(device)
    touched[::3] = 0
    total = int(touched.sum())
    full_keys, full_ids = write_keys(inputs, touched, width, height, total, total)
    assert (full_keys != -7).all() and total > 100
    capacity = int(share * total)
    keys, ids = write_keys(inputs, touched, width, height, capacity, total + 64, inline_lanes=inline_lanes)
    assert torch.equal(keys[:capacity], full_keys[:capacity]) and torch.equal(ids[:capacity], full_ids[:capacity])
    assert (keys[capacity:] == -7).all() and (ids[capacity:] == -7).all()


def test_keys_stop_at_the_capacity_when_the_count_passes_int32():
    """A frame counted past int32 (refused after the sync, but its keys are written before it): the
    int64 slot offsets are clipped to the capacity before any narrowing, so nothing lands outside."""
    width, height = 200, 96
    inputs = awkward_ellipses(12, 100, width, height)
    touched = tiles_touched_reference(*inputs[:4], width, height).int()
    ends = torch.cumsum(touched, 0, dtype=torch.int64)
    jump = int(torch.nonzero(touched > 1)[20, 0])  # a Gaussian of several tiles, made to span 2^32 slots
    capacity = int(ends[jump - 1]) + 1  # room for its first key, as without the jump
    ends[jump:] += 2**32 - ends[jump]  # from 2^32 on: narrowed to int32 first, they would wrap to slot 0
    keys, ids = write_keys(inputs, touched, width, height, capacity, capacity + 64, ends=ends)
    full_keys, full_ids = write_keys(inputs, touched, width, height, capacity, capacity)
    assert torch.equal(keys[:capacity], full_keys) and torch.equal(ids[:capacity], full_ids)
    assert (keys[capacity:] == -7).all() and (ids[capacity:] == -7).all()


@pytest.mark.parametrize("begin_bit", [0, 3])
@pytest.mark.parametrize("count", [0, 1, 7, 5000])
def test_sort_pairs_sorts_stably_on_tensors(count, begin_bit):
    """tomgs.runtime.sort_pairs (Warp's native radix sort, called without building wp.arrays) on the
    CPU: keys[:count] ascending in bits [begin_bit, end_bit), ties in their first order, values carried
    along; storage past 2 * count untouched."""
    from tomgs.runtime import scope, sort_pairs

    g = torch.Generator().manual_seed(SEED_BASE * 1000 + 731 + count)
    tiles = torch.randint(0, 300, (count,), generator=g)
    depths = torch.randint(0, 40, (count,), generator=g)  # few depths: many equal keys
    keys = torch.full((2 * count + 5,), -3, dtype=torch.int64)
    values = torch.full((2 * count + 5,), -3, dtype=torch.int32)
    keys[:count] = tiles << 32 | depths
    values[:count] = torch.arange(count, dtype=torch.int32)
    order = torch.sort(keys[:count] >> begin_bit, stable=True)[1]
    expected_keys = keys[:count][order]
    with scope(keys.device):
        sort_pairs(keys, values, count, 32 + 9, begin_bit)
    assert torch.equal(keys[:count], expected_keys) and torch.equal(values[:count], order.int())
    assert (keys[2 * count:] == -3).all() and (values[2 * count:] == -3).all()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("size", [(854, 480), (640, 360)])
def test_depths_closer_than_the_sort_reads_are_drawn_in_gaussian_order(size, device):
    """The sort reads a key's depth from bit `sort_low_bit` up (5 radix passes at 854x480, not 6):
    Gaussians whose float32 depths differ only below it tie and keep Gaussian order, the others
    keep depth order. Six Gaussians on one tile: 2 + 3, 2, 1 and 0 ulps (one run of equal high bits,
    listed in reverse depth order), 1.9 and 3."""
    width, height = size
    depths = torch.tensor([2.0, 2.0, 2.0, 2.0, 1.9, 3.0]).view(torch.int32)
    depths[:4] += torch.tensor([3, 2, 1, 0], dtype=torch.int32)
    depths = depths.view(torch.float32)
    n = len(depths)
    means2d = torch.tensor([[8.0, 8.0]]).repeat(n, 1)
    conics, radii = torch.tensor([[0.5, 0.0, 0.5]]).repeat(n, 1), torch.tensor([[2, 2]], dtype=torch.int32).repeat(n, 1)
    opacities = torch.full((n,), 0.5)
    inputs = (means2d, conics, opacities, radii, depths)
    touched = tiles_touched_reference(*inputs[:4], width, height)
    ours = bin_stage(*[x.to(device) for x in inputs], touched.int().to(device), width, height)
    assert sort_low_bit(width, height) >= 2  # 3 ulps fall below it
    assert ours["ids"].tolist() == [4, 0, 1, 2, 3, 5]
    ref = bin_reference(*inputs, width, height)
    assert torch.equal(ours["keys"].cpu(), ref["keys"]) and torch.equal(ours["ids"].long().cpu(), ref["ids"])


@pytest.mark.parametrize("size, read", [((854, 480), 40), ((640, 360), 40), ((1920, 1080), 45), ((45, 37), 36),
                                        ((16, 16), 32)])
def test_the_sort_reads_whole_passes_and_enough_depth(size, read):
    """Bits the tile sort reads: the tile's, and at least DEPTH_SORT_BITS of depth, in whole 8-bit passes
    (or every bit of the key, where those passes would hold more)."""
    tiles = -(-size[0] // TILE_SIZE) * -(-size[1] // TILE_SIZE)
    low = sort_low_bit(*size)
    assert 32 + tiles.bit_length() - low == read and (read % 8 == 0 or low == 0) and 32 - low >= DEPTH_SORT_BITS


def test_sort_pairs_refuses_too_little_storage():
    from tomgs.runtime import sort_pairs

    with pytest.raises(ValueError, match="scratch"):
        sort_pairs(torch.zeros(9, dtype=torch.int64), torch.zeros(10, dtype=torch.int32), 5, 40)
    with pytest.raises(ValueError, match="int64 keys"):
        sort_pairs(torch.zeros(10, dtype=torch.int32), torch.zeros(10, dtype=torch.int32), 5, 40)
