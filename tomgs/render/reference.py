"""Pure-torch references with the semantics of the Warp rasterizer: the oracles for every test.

    project_reference   stage 1 alone, per Gaussian, with the projection kernel's outputs
    bin_reference       stage 2 alone: the sorted (tile, depth) intersection list and tile ranges
    depth_order         what a tile's Gaussians are drawn in the order of
    rasterize_reference the whole renderer, dense

Same projection (EWA with 0.3 px dilation, clamped Jacobian, opacity-aware radius), same culls
(near/far, non-finite, temporal opacity < 1/255, off screen), same binning (the tiles of the box
centre +- radius clamped to the image that the Gaussian's alpha >= 1/255 ellipse reaches, keys
ordered by tile, then the high bits of float32 depth that the sort reads, then Gaussian),
same compositing (alpha clamp 0.99, skip alpha < 1/255, stop before T <= 1e-4), but every pixel
meets every visible Gaussian and autograd provides the gradients. Run them in float64 on small
scenes; the dense renderer's memory is O(pixels x N).
"""

from __future__ import annotations

import dataclasses

import torch

from tomgs.constants import ALPHA_MAX, ALPHA_MIN, EPS2D, FOV_CLAMP, RADIUS_SIGMAS, T_MIN, TILE_SIZE, sort_low_bit
from tomgs.geometry import quat_to_rotmat
from tomgs.render.inputs import RasterInputs, prepare_inputs
from tomgs.temporal import opacity_at

_PER_GAUSSIAN = ("means", "quats", "scales", "opacities", "colors", "t_means", "t_scales")


def _project(p: RasterInputs) -> dict[str, torch.Tensor]:
    """Per-Gaussian 2D quantities for all N (culled ones are garbage, see `valid`)."""
    rot_view, trans_view = p.viewmat[:3, :3], p.viewmat[:3, 3]
    cam = p.means @ rot_view.T + trans_view  # [N,3]
    x, y, depth = cam.unbind(-1)
    depth_ok = (depth > p.near) & (depth < p.far)
    z = torch.where(depth_ok, depth, torch.ones_like(depth))  # keep culled lanes NaN-free for autograd

    opac_t = opacity_at(p.opacities, p.t_means, p.t_scales, p.t)

    fx, fy, cx, cy = p.K[0, 0], p.K[1, 1], p.K[0, 2], p.K[1, 2]
    lim_x = FOV_CLAMP * 0.5 * p.width / fx
    lim_y = FOV_CLAMP * 0.5 * p.height / fy
    u = torch.clamp(x / z, -lim_x, lim_x)
    v = torch.clamp(y / z, -lim_y, lim_y)
    zero = torch.zeros_like(z)
    jac = torch.stack([fx / z, zero, -fx * u / z, zero, fy / z, -fy * v / z], -1).reshape(-1, 2, 3)

    m = quat_to_rotmat(p.quats) * p.scales[:, None, :]  # R diag(s): Sigma = m m^T
    a_mat = jac @ rot_view @ m  # [N,2,3]; 2D covariance = a a^T + eps I
    a0 = (a_mat[:, 0] ** 2).sum(-1)
    c0 = (a_mat[:, 1] ** 2).sum(-1)
    b = (a_mat[:, 0] * a_mat[:, 1]).sum(-1)
    a, c = a0 + EPS2D, c0 + EPS2D
    # det(a a^T) by Cauchy-Binet (sum of squared 2x2 minors): no cancellation for thin Gaussians
    r0, r1 = a_mat[:, 0], a_mat[:, 1]
    minors = torch.stack([r0[:, 0] * r1[:, 1] - r0[:, 1] * r1[:, 0], r0[:, 0] * r1[:, 2] - r0[:, 2] * r1[:, 0],
                          r0[:, 1] * r1[:, 2] - r0[:, 2] * r1[:, 1]], -1)
    det = (minors ** 2).sum(-1) + EPS2D * (a0 + c0) + EPS2D * EPS2D
    conics = torch.stack([c / det, -b / det, a / det], -1)
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], -1)
    return dict(means2d=means2d, conics=conics, opac_t=opac_t, depth=depth, depth_ok=depth_ok, cov_a=a, cov_c=c)


def _radii_and_valid(proj: dict[str, torch.Tensor], width: int, height: int
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Integer radii [N,2], the visibility mask [N] and the radii before rounding up [N,2] (no gradients)."""
    finite = torch.stack([proj[k].isfinite().all(-1) if proj[k].dim() == 2 else proj[k].isfinite()
                          for k in ("means2d", "conics", "opac_t", "depth")]).all(0)
    alive = proj["opac_t"] >= ALPHA_MIN
    valid = proj["depth_ok"] & finite & alive
    opac = torch.where(valid, proj["opac_t"], torch.ones_like(proj["opac_t"]))
    extend = torch.clamp(torch.sqrt(2.0 * torch.log(opac / ALPHA_MIN).clamp_min(0)), max=RADIUS_SIGMAS)
    extent = torch.stack([extend * proj["cov_a"].sqrt(), extend * proj["cov_c"].sqrt()], -1)
    rx, ry = torch.ceil(extent).unbind(-1)
    mx, my = proj["means2d"].unbind(-1)
    on_screen = (mx + rx > 0) & (mx - rx < width) & (my + ry > 0) & (my - ry < height) & ((rx > 0) | (ry > 0))
    valid = valid & on_screen & rx.isfinite() & ry.isfinite()
    radii = torch.where(valid[:, None], torch.stack([rx, ry], -1), torch.zeros_like(proj["means2d"]))
    extent = torch.where(valid[:, None], extent, torch.zeros_like(extent))
    return radii.clamp(max=2**30).long(), valid, extent


def _visible(p: RasterInputs):
    """(every Gaussian's projection, no gradients; radii [N,2] int64; visible [N] bool; extent [N,2])."""
    with torch.no_grad():
        full = _project(p)
        radii, valid, extent = _radii_and_valid(full, p.width, p.height)
    return full, radii, valid, extent


def _subset(p: RasterInputs, idx: torch.Tensor) -> RasterInputs:
    return dataclasses.replace(p, **{k: getattr(p, k)[idx] for k in _PER_GAUSSIAN})


def tile_rects(means2d: torch.Tensor, radii: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """[N,4] int64 (x0, y0, x1, y1): the tiles [x0, x1) x [y0, y1) that the box means2d +- radii [N,2]
    overlaps, clamped to the image's tiles; computed in means2d's dtype (float32 for the kernel's)."""
    tiles_x, tiles_y = -(-int(width) // TILE_SIZE), -(-int(height) // TILE_SIZE)
    c, r = means2d.detach(), radii.to(means2d.dtype)
    lo = torch.floor((c - r) / TILE_SIZE)
    hi = torch.floor((c + r) / TILE_SIZE) + 1.0
    limit = torch.tensor([tiles_x, tiles_y], dtype=c.dtype, device=c.device)
    lo, hi = torch.minimum(lo.clamp_min(0.0), limit), torch.minimum(hi.clamp_min(0.0), limit)
    return torch.cat([lo, hi], -1).long()


def tile_levels(means2d: torch.Tensor, conics: torch.Tensor, opacities_t: torch.Tensor, radii: torch.Tensor,
                width: int, height: int) -> dict[str, torch.Tensor]:
    """Every (Gaussian, tile of its box) pair, Gaussian by Gaussian, tiles row by row: ids [P] and tiles [P]
    int64, `low` [P] the minimum of q(d) = d^T conic d over the tile's rectangle of pixel centres (d =
    pixel - means2d; exact, float64) and `level` [P] the bound on q where the raster may draw (alpha >= 1/255
    at q <= extent^2, extent as for the radius, in opacities_t's dtype), with the kernel's slack: 2^-10
    relative and absolute, and 2^-20 (A X^2 + C Y^2) for the raster's float32 power, X, Y = radii + 16."""
    tiles_x = -(-int(width) // TILE_SIZE)
    rect = tile_rects(means2d, radii, width, height)
    span = (rect[:, 2] - rect[:, 0]).clamp_min(0)
    count = torch.where((radii != 0).any(-1), span * (rect[:, 3] - rect[:, 1]).clamp_min(0), 0)
    ids = torch.repeat_interleave(torch.arange(len(count), device=means2d.device), count)
    slot = torch.arange(len(ids), device=means2d.device) - (torch.cumsum(count, 0) - count)[ids]
    tx = rect[ids, 0] + slot % span[ids].clamp_min(1)
    ty = rect[ids, 1] + slot // span[ids].clamp_min(1)

    f64 = torch.float64
    A, B, C = conics.detach().to(f64)[ids].unbind(-1)
    x0 = TILE_SIZE * tx.to(f64) + 0.5 - means2d.detach().to(f64)[ids, 0]  # the rectangle, relative to the centre
    y0 = TILE_SIZE * ty.to(f64) + 0.5 - means2d.detach().to(f64)[ids, 1]
    x1, y1 = x0 + TILE_SIZE - 1, y0 + TILE_SIZE - 1

    def q(x, y):
        return A * x * x + 2.0 * B * x * y + C * y * y

    # with the centre outside, the minimum lies on an edge (no interior minimum but at d = 0), at a
    # corner or where the edge's own parabola bottoms out
    safe_a, safe_c = torch.where(A > 0, A, 1.0), torch.where(C > 0, C, 1.0)
    lows = [q(x, y) for x in (x0, x1) for y in (y0, y1)]
    for y in (y0, y1):
        lows.append(torch.where(A > 0, q(torch.clamp(-B * y / safe_a, x0, x1), y), torch.inf))
    for x in (x0, x1):
        lows.append(torch.where(C > 0, q(x, torch.clamp(-B * x / safe_c, y0, y1)), torch.inf))
    inside = (x0 <= 0) & (0 <= x1) & (y0 <= 0) & (0 <= y1)
    low = torch.where(inside, torch.zeros_like(A), torch.stack(lows).amin(0))

    opac = opacities_t.detach()
    extend = torch.clamp(torch.sqrt((2.0 * torch.log(opac / ALPHA_MIN)).clamp_min(0)), max=RADIUS_SIGMAS).to(f64)
    far_x, far_y = (radii.to(f64) + TILE_SIZE).unbind(-1)
    noise = conics.detach().to(f64)[:, 0] * far_x ** 2 + conics.detach().to(f64)[:, 2] * far_y ** 2
    level = extend * extend * (1.0 + 2.0 ** -10) + 2.0 ** -10 + 2.0 ** -20 * noise
    return dict(ids=ids, tiles=ty * tiles_x + tx, low=low, level=level[ids], underflow=~(A > 0))


def ellipse_tiles(means2d: torch.Tensor, conics: torch.Tensor, opacities_t: torch.Tensor, radii: torch.Tensor,
                  width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(ids [M], tiles [M]) int64: the tiles of each Gaussian's box (`tile_rects`; radii (0, 0) = culled)
    whose pixel centres its ellipse q(d) <= level reaches (`tile_levels`), every tile of the box where the
    float32 conic's A underflowed to 0, and the box's first tile where none is reached, so that a
    Gaussian whose box is on screen holds one; Gaussian by Gaussian, tiles row by row."""
    pairs = tile_levels(means2d, conics, opacities_t, radii, width, height)
    ids = pairs["ids"]
    keep = pairs["underflow"] | (pairs["low"] <= pairs["level"])
    kept = torch.zeros(len(means2d), dtype=torch.long, device=ids.device).index_add_(0, ids, keep.long())
    first = torch.ones_like(keep)
    first[1:] = ids[1:] != ids[:-1]
    keep |= first & (kept[ids] == 0)
    return ids[keep], pairs["tiles"][keep]


def tiles_touched_reference(means2d: torch.Tensor, conics: torch.Tensor, opacities_t: torch.Tensor,
                            radii: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """[N] int64: how many tiles each Gaussian holds (`ellipse_tiles`), 0 where radii are (0, 0) (culled)."""
    ids, _ = ellipse_tiles(means2d, conics, opacities_t, radii, width, height)
    return torch.bincount(ids, minlength=len(means2d))


def project_reference(
    means, quats, scales, opacities, t_means, t_scales, viewmat, K, width, height, t, *,
    near=0.01, far=1e10, dtype=torch.float64,
) -> dict[str, torch.Tensor]:
    """Stage 1 alone, per Gaussian, with `tomgs.render.frame.project_stage`'s outputs and conventions, in
    `dtype`: means2d [N,2], conics [N,3], depths [N], radii [N,2] int64, opacities_t [N], tiles_touched
    [N] int64, plus extent [N,2] (the radii before rounding up: a test can tell a tie). A culled
    Gaussian has zero means2d, conics, radii and tiles touched and gets zero gradient; depths and
    opacities_t are given for all. means2d, conics and opacities_t are differentiable (autograd)."""
    colors = torch.zeros_like(means) if isinstance(means, torch.Tensor) else means  # projection reads no colour
    p = prepare_inputs(means, quats, scales, opacities, colors, t_means, t_scales, viewmat, K, width, height, t,
                       None, near, far, dtype)
    full, radii, valid, extent = _visible(p)
    idx = torch.nonzero(valid).squeeze(-1)
    proj = _project(_subset(p, idx))  # differentiate only the visible: culled rows get exactly zero, never NaN
    n = p.means.shape[0]
    means2d = torch.zeros(n, 2, dtype=dtype, device=p.means.device).index_copy(0, idx, proj["means2d"])
    conics = torch.zeros(n, 3, dtype=dtype, device=p.means.device).index_copy(0, idx, proj["conics"])
    opacities_t = full["opac_t"].index_copy(0, idx, proj["opac_t"])
    return dict(means2d=means2d, conics=conics, depths=full["depth"], radii=radii, opacities_t=opacities_t,
                tiles_touched=tiles_touched_reference(means2d, conics, opacities_t, radii, p.width, p.height),
                extent=extent)


def _depth_bits(depths: torch.Tensor) -> torch.Tensor:
    """int64 [N]: the bits of float32 depths [N], the low half of a tile key (a positive float's bits
    order as it does)."""
    return depths.detach().to(torch.float32).view(torch.int32).long()


def depth_order(depths: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """int64 [N]: what a tile's list orders its Gaussians by, for their depths [N] (> 0 where visible)
    in a width x height frame: `_depth_bits` from `sort_low_bit` up. Gaussians equal in it are drawn
    in Gaussian order."""
    return _depth_bits(depths) >> sort_low_bit(width, height)


def bin_reference(means2d: torch.Tensor, conics: torch.Tensor, opacities_t: torch.Tensor, radii: torch.Tensor,
                  depths: torch.Tensor, width: int, height: int) -> dict[str, torch.Tensor]:
    """Stage 2 alone, with `tomgs.render.frame.bin_stage`'s outputs: every (tile, Gaussian) pair of
    `ellipse_tiles` (the tiles of the box means2d +- radii [N,2] that the ellipse of conics [N,3] at
    opacities_t [N] reaches) as keys [M] int64 `tile << 32 | bits of float32 depth` (depths [N] > 0 where
    visible), sorted by tile, then `depth_order`, then Gaussian; ids [M] int64 the Gaussian of each;
    tiles [M] int64; ranges [tiles, 2] int64 each tile's [start, end) in them, (0, 0) for a tile nobody
    touches."""
    tiles_x, tiles_y = -(-int(width) // TILE_SIZE), -(-int(height) // TILE_SIZE)
    ids, tiles = ellipse_tiles(means2d, conics, opacities_t, radii, width, height)
    keys = (tiles << 32) | _depth_bits(depths)[ids]
    # keys equal in the bits the sort reads (tile, depth_order) keep Gaussian order, as the radix sort does
    order = torch.sort(keys >> sort_low_bit(width, height), stable=True)[1]
    keys, ids, tiles = keys[order], ids[order], tiles[order]
    per_tile = torch.bincount(tiles, minlength=tiles_x * tiles_y)
    end = torch.cumsum(per_tile, 0)
    ranges = torch.stack([end - per_tile, end], -1) * (per_tile > 0)[:, None]
    return dict(keys=keys, ids=ids, tiles=tiles, ranges=ranges)


def rasterize_reference(
    means, quats, scales, opacities, colors, t_means, t_scales, viewmat, K, width, height, t, *,
    background=None, near=0.01, far=1e10, dtype=torch.float64,
):
    """Same signature and outputs as `tomgs.rasterize`; `dtype` is the compute precision."""
    p = prepare_inputs(means, quats, scales, opacities, colors, t_means, t_scales, viewmat, K, width, height, t,
                          background, near, far, dtype)
    full, radii, valid, extent = _visible(p)
    # differentiate only the visible subset: culled Gaussians get exactly zero gradient, never NaN
    idx = torch.nonzero(valid).squeeze(-1)
    idx = idx[torch.argsort(depth_order(full["depth"][idx], p.width, p.height), stable=True)]
    sub = _subset(p, idx)
    proj = _project(sub)

    ys, xs = torch.meshgrid(torch.arange(p.height, dtype=dtype, device=p.means.device) + 0.5,
                            torch.arange(p.width, dtype=dtype, device=p.means.device) + 0.5, indexing="ij")
    pix = torch.stack([xs, ys], -1).reshape(-1, 1, 2)  # [P,1,2]
    delta = proj["means2d"][None] - pix  # [P,M,2]
    con = proj["conics"]
    power = 0.5 * (con[:, 0] * delta[..., 0] ** 2 + con[:, 2] * delta[..., 1] ** 2) + con[:, 1] * delta[..., 0] * delta[..., 1]
    alpha = torch.clamp(proj["opac_t"] * torch.exp(-power), max=ALPHA_MAX)
    alpha = alpha * (alpha >= ALPHA_MIN).detach()
    with torch.no_grad():
        stopped = torch.cumprod(1.0 - alpha, dim=1) <= T_MIN
        keep = torch.cumsum(stopped.to(torch.int32), dim=1) == 0
    alpha = alpha * keep
    trans = torch.cumprod(1.0 - alpha, dim=1)  # [P,M] transmittance after each Gaussian
    trans_before = torch.cat([torch.ones_like(trans[:, :1]), trans[:, :-1]], dim=1)
    color = torch.einsum("pm,mc->pc", alpha * trans_before, sub.colors)
    t_final = trans[:, -1:] if trans.shape[1] else torch.ones_like(pix[:, 0, :1])
    if p.background is not None:
        color = color + t_final * p.background
    image = color.reshape(p.height, p.width, 3)
    alpha_out = (1.0 - t_final).reshape(p.height, p.width, 1)
    # extent: the radii before rounding up, so that a test can tell a float32 tie at an integer
    meta = dict(radii=radii, means2d=full["means2d"], depths=full["depth"], conics=full["conics"],
                opacities_t=full["opac_t"], n_visible=int(valid.sum()), extent=extent)
    return image, alpha_out, meta


__all__ = ["rasterize_reference", "project_reference", "bin_reference", "depth_order", "tile_rects", "tile_levels",
           "ellipse_tiles", "tiles_touched_reference", "quat_to_rotmat"]
