"""Stage 3: per-tile compositing, front to back, and its hand-written back-to-front backward.

Threads are laid out tile by tile (256 consecutive threads = one 16x16 tile = one CUDA block), so a
block walks one tile's depth-sorted list together and the per-Gaussian loads are shared in cache.
"""

import math

import warp as wp

from tomgs import constants
from tomgs.kernels.lanes import lane_index, lanes_any, lanes_max, lanes_sum, lanes_sum_vec2, lanes_sum_vec3

# fast math: __expf and approximate division in the per-pixel loops, which are bound by instruction
# issue on the GPU; compositing needs no IEEE corner cases (projection, which checks finiteness, stays exact)
wp.set_module_options({"enable_backward": False, "fast_math": True})

TILE = wp.constant(constants.TILE_SIZE)
TILE_PIXELS = wp.constant(constants.TILE_SIZE * constants.TILE_SIZE)
ALPHA_MIN = wp.constant(constants.ALPHA_MIN)
ALPHA_MAX = wp.constant(constants.ALPHA_MAX)
T_MIN = wp.constant(constants.T_MIN)
ONE_MINUS_ALPHA_FLOOR = wp.constant(constants.ONE_MINUS_ALPHA_FLOOR)
# Past this power, o exp(-power) < ALPHA_MIN for any opacity o <= 1 (the contract), so an entry is
# skipped there without its exp: the same image, and most of a small Gaussian's entries in a tile
# (the pixels outside its ellipse) cost no exp. The margin covers fast math's approximate exp.
POWER_SKIP = wp.constant(math.log(1.0 / constants.ALPHA_MIN) + 1.0e-3)


@wp.func
def tile_origin(tile: int, tiles_x: int) -> wp.vec2i:
    """(x, y) of the top-left pixel of tile `tile` (tiles numbered row by row, tiles_x to a row)."""
    ty = tile // tiles_x
    return wp.vec2i((tile - ty * tiles_x) * TILE, ty * TILE)


@wp.func
def pixel_of(tid: int, tiles_x: int) -> wp.vec3i:
    """(tile, x, y) of the pixel handled by thread `tid`."""
    tile = tid // TILE_PIXELS
    local = tid - tile * TILE_PIXELS
    origin = tile_origin(tile, tiles_x)
    return wp.vec3i(tile, origin[0] + local % TILE, origin[1] + local // TILE)


@wp.func
def block_tile(block: int, tile_order: wp.array(dtype=wp.int32)) -> int:
    """The tile block `block` composites: tile_order[block] (the longest lists first, so that no long
    tile starts last and runs alone), or the block's own number when `tile_order` is empty."""
    if tile_order.shape[0] == 0:
        return block
    return tile_order[block]


@wp.func
def ordered(tid: int, tile_order: wp.array(dtype=wp.int32)) -> int:
    """Thread `tid` of a launch of a block per tile (`block_tile`), as the thread of its tile: the
    index `pixel_of` takes."""
    block = tid // TILE_PIXELS
    return block_tile(block, tile_order) * TILE_PIXELS + tid - block * TILE_PIXELS


@wp.func
def gaussian_power(center: wp.vec2, conic: wp.vec3, pixel: wp.vec2) -> float:
    d = center - pixel
    return 0.5 * (conic[0] * d[0] * d[0] + conic[2] * d[1] * d[1]) + conic[1] * d[0] * d[1]


@wp.func
def unblend(alpha: float, raw_alpha: float, falloff: float, trans: float, behind: wp.vec3, c: wp.vec3, dc: wp.vec3,
            dt_final: float, center: wp.vec2, conic: wp.vec3, pixel: wp.vec2):
    """One composited Gaussian of a pixel, walked back to front (the backward of one blend).

    In: its alpha (clamped) and raw_alpha = o exp(-power), falloff = exp(-power), the transmittance
    behind it, the colour composited behind it (weighted), its colour, dL/d(pixel colour), and
    dL/d(final transmittance) x final transmittance. Out: (transmittance in front of it, colour
    behind including it, dL/d colour, dL/d opacity_t, dL/d conic, dL/d mean2d)."""
    one_minus = wp.max(1.0 - alpha, ONE_MINUS_ALPHA_FLOOR)
    trans = trans / one_minus
    weight = alpha * trans
    v_alpha = trans * wp.dot(c, dc) - (wp.dot(behind, dc) + dt_final) / one_minus
    v_opac = float(0.0)
    v_conic = wp.vec3(0.0)
    v_mean = wp.vec2(0.0)
    if raw_alpha <= ALPHA_MAX:  # the 0.99 clamp passes no gradient
        v_power = -v_alpha * alpha
        d = center - pixel
        v_opac = v_alpha * falloff
        v_conic = v_power * wp.vec3(0.5 * d[0] * d[0], d[0] * d[1], 0.5 * d[1] * d[1])
        v_mean = v_power * wp.vec2(conic[0] * d[0] + conic[1] * d[1], conic[1] * d[0] + conic[2] * d[1])
    return trans, behind + c * weight, dc * weight, v_opac, v_conic, v_mean


@wp.func
def pixel_backward_state(out_trans: wp.array2d(dtype=float), out_end: wp.array2d(dtype=wp.int32),
                         v_color: wp.array2d(dtype=wp.vec3), v_trans: wp.array2d(dtype=float), x: int, y: int,
                         width: int, height: int, start: int):
    """What the backward of pixel (x, y) starts from: (one past its last composited entry, its final
    transmittance, dL/d colour, dL/d final transmittance x final transmittance). A thread outside the
    image composites nothing (end = start) but still walks with its block."""
    if x < width and y < height:
        final_trans = out_trans[y, x]
        return out_end[y, x], final_trans, v_color[y, x], v_trans[y, x] * final_trans
    return start, float(1.0), wp.vec3(0.0), float(0.0)


@wp.kernel
def raster_forward(
    ranges: wp.array2d(dtype=wp.int32),  # [tiles, 2]
    gaussian_ids: wp.array(dtype=wp.int32),  # [M] depth-sorted per tile
    means2d: wp.array(dtype=wp.vec2),  # [N]
    conics: wp.array(dtype=wp.vec3),  # [N]
    opacities_t: wp.array(dtype=float),  # [N]
    colors: wp.array(dtype=wp.vec3),  # [N]
    width: int,
    height: int,
    tiles_x: int,
    tile_order: wp.array(dtype=wp.int32),  # [tiles] the tile of each block, or empty (block b: tile b)
    out_color: wp.array2d(dtype=wp.vec3),  # out [H, W] premultiplied, no background
    out_trans: wp.array2d(dtype=float),  # out [H, W] final transmittance
    out_end: wp.array2d(dtype=wp.int32),  # out [H, W] one past the last composited list entry
):
    tile_xy = pixel_of(ordered(wp.tid(), tile_order), tiles_x)
    x = tile_xy[1]
    y = tile_xy[2]
    if x >= width or y >= height:
        return
    tile = tile_xy[0]
    pixel = wp.vec2(float(x) + 0.5, float(y) + 0.5)
    start = ranges[tile, 0]
    end = ranges[tile, 1]
    trans = float(1.0)
    color = wp.vec3(0.0)
    last = start
    for k in range(start, end):
        g = gaussian_ids[k]
        power = gaussian_power(means2d[g], conics[g], pixel)
        if power > POWER_SKIP:
            continue
        alpha = wp.min(ALPHA_MAX, opacities_t[g] * wp.exp(-power))
        if alpha < ALPHA_MIN:
            continue
        next_trans = trans * (1.0 - alpha)
        if next_trans <= T_MIN:
            break
        color += colors[g] * (alpha * trans)
        trans = next_trans
        last = k + 1
    out_color[y, x] = color
    out_trans[y, x] = trans
    out_end[y, x] = last


@wp.kernel
def raster_backward(
    ranges: wp.array2d(dtype=wp.int32),  # [tiles, 2]
    gaussian_ids: wp.array(dtype=wp.int32),  # [M]
    means2d: wp.array(dtype=wp.vec2),  # [N]
    conics: wp.array(dtype=wp.vec3),  # [N]
    opacities_t: wp.array(dtype=float),  # [N]
    colors: wp.array(dtype=wp.vec3),  # [N]
    width: int,
    height: int,
    tiles_x: int,
    tile_order: wp.array(dtype=wp.int32),  # [tiles] the tile of each block, or empty (block b: tile b)
    out_trans: wp.array2d(dtype=float),  # [H, W] from the forward
    out_end: wp.array2d(dtype=wp.int32),  # [H, W] from the forward
    v_color: wp.array2d(dtype=wp.vec3),  # [H, W] dL/d(premultiplied colour)
    v_trans: wp.array2d(dtype=float),  # [H, W] dL/d(final transmittance)
    v_means2d: wp.array(dtype=wp.vec2),  # out [N], accumulated (zeroed by the caller)
    v_conics: wp.array(dtype=wp.vec3),  # out [N], accumulated
    v_opacities_t: wp.array(dtype=float),  # out [N], accumulated
    v_colors: wp.array(dtype=wp.vec3),  # out [N], accumulated
):
    # All 32 lanes of a GPU warp lie in one tile and walk its list in lockstep, so each Gaussian's
    # gradient is summed across the lanes before a single atomic add. No lane may return early.
    tile_xy = pixel_of(ordered(wp.tid(), tile_order), tiles_x)
    tile = tile_xy[0]
    x = tile_xy[1]
    y = tile_xy[2]
    pixel = wp.vec2(float(x) + 0.5, float(y) + 0.5)
    start = ranges[tile, 0]
    end, final_trans, dc, dt_final = pixel_backward_state(out_trans, out_end, v_color, v_trans, x, y, width, height,
                                                          start)
    trans = final_trans
    behind = wp.vec3(0.0)  # colour composited behind the current Gaussian, already weighted
    lead = lane_index() == 0
    for k in range(lanes_max(end) - 1, start - 1, -1):
        g = gaussian_ids[k]
        center = means2d[g]
        conic = conics[g]
        falloff = wp.exp(-gaussian_power(center, conic, pixel))
        raw_alpha = opacities_t[g] * falloff
        alpha = wp.min(ALPHA_MAX, raw_alpha)
        used = k < end and alpha >= ALPHA_MIN
        v_col = wp.vec3(0.0)
        v_opac = float(0.0)
        v_conic = wp.vec3(0.0)
        v_mean = wp.vec2(0.0)
        if used:
            trans, behind, v_col, v_opac, v_conic, v_mean = unblend(alpha, raw_alpha, falloff, trans, behind,
                                                                    colors[g], dc, dt_final, center, conic, pixel)
        if lanes_any(used):
            v_col = lanes_sum_vec3(v_col)
            v_opac = lanes_sum(v_opac)
            v_conic = lanes_sum_vec3(v_conic)
            v_mean = lanes_sum_vec2(v_mean)
            if lead:
                wp.atomic_add(v_colors, g, v_col)
                wp.atomic_add(v_opacities_t, g, v_opac)
                wp.atomic_add(v_conics, g, v_conic)
                wp.atomic_add(v_means2d, g, v_mean)
