"""Stage 3 for CUDA: the per-tile compositing of tomgs.kernels.raster, with each tile's list staged
through shared memory in batches (the scheme of gsplat and INRIA 3DGS).

One 16x16 tile is one block of 256 threads, thread = pixel as in raster.py. The block walks its
tile's depth-sorted list in batches of 256 entries: each thread gathers ONE entry's record (mean,
opacity, conic, colour; the backward also its id) from global memory into shared tiles (coalesced,
all gathers in flight at once), the block synchronises, then every thread composites its pixel against the batch
with broadcast reads from shared memory. The per-pixel kernels instead load every entry in every
thread (through L1), which made them issue bound. Per pixel the arithmetic and its order are those
of raster.py, so both pairs give the same image to rounding.

The backward runs a thread per two pixels of a tile, one above the other (`paired_pixels`): a block of
128, each warp a 16x4 patch, so the nine gradient terms of an entry are summed in the thread over its
two pixels, then over the warp's lanes once for 64 pixels (the lane sums and the per-entry work shared
by two pixels were most of its issued instructions in ncu; docs/notes/rasterizer.md).

Block width: 256 (forward) and 128 (backward) on CUDA; on the CPU Warp runs a block of width 1 (every
thread alone: it stages the whole batch itself, which gives exactly the per-pixel result), or of 256 /
128 cooperative fibers with `wp.config.enable_cpu_blocks` (real block semantics: barriers and
reductions, for tests). The forward launches 1D over num_tiles * 256 threads, the backward over
num_tiles * 128, so block b is tile b, or tile_order[b] when the caller orders the tiles
(`raster.ordered`: on CUDA the longest lists first).
"""

import warp as wp

from tomgs.kernels.lanes import lane_index, lanes_any, lanes_max, lanes_sum, lanes_sum_vec2, lanes_sum_vec3
from tomgs.kernels.raster import (ALPHA_MAX, ALPHA_MIN, POWER_SKIP, T_MIN, TILE, TILE_PIXELS, block_tile,
                                  gaussian_power, ordered, pixel_backward_state, pixel_of, tile_origin, unblend)

# fast math as in raster.py (the same per-pixel arithmetic, issue bound on the GPU)
wp.set_module_options({"enable_backward": False, "fast_math": True})


@wp.func_native("return WP_TILE_BLOCK_DIM;")
def block_width() -> int:
    """Threads per block, as the module was compiled for it (256 on CUDA; 1, or 256 with
    wp.config.enable_cpu_blocks, on the CPU): a constant to the compiler, unlike wp.block_dim()."""
    ...


@wp.func
def list_record(gaussian_ids: wp.array(dtype=wp.int32), means2d: wp.array(dtype=wp.vec2),
                conics: wp.array(dtype=wp.vec3), opacities_t: wp.array(dtype=float), colors: wp.array(dtype=wp.vec3),
                k: int, has: bool):
    """What a thread stages for list entry k: (Gaussian id, (mean x, mean y, opacity), conic, colour);
    zeros when it has no entry to stage (`has` false: k is past the list)."""
    if has:
        g = gaussian_ids[k]
        center = means2d[g]
        return g, wp.vec3(center[0], center[1], opacities_t[g]), conics[g], colors[g]
    return int(0), wp.vec3(0.0), wp.vec3(0.0), wp.vec3(0.0)


@wp.kernel
def raster_forward_batched(
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
    tid = wp.tid()
    tile_xy = pixel_of(ordered(tid, tile_order), tiles_x)
    tile = tile_xy[0]
    x = tile_xy[1]
    y = tile_xy[2]
    inside = x < width and y < height
    pixel = wp.vec2(float(x) + 0.5, float(y) + 0.5)
    rank = tid % block_width()  # this thread's place in its block
    start = ranges[tile, 0]
    end = ranges[tile, 1]
    # one batch of records: (mean x, mean y, opacity), conic, colour; 9 KB
    xy_opacity = wp.tile_empty(shape=TILE_PIXELS, dtype=wp.vec3, storage="shared")
    conic_batch = wp.tile_empty(shape=TILE_PIXELS, dtype=wp.vec3, storage="shared")
    color_batch = wp.tile_empty(shape=TILE_PIXELS, dtype=wp.vec3, storage="shared")
    trans = float(1.0)
    color = wp.vec3(0.0)
    last = start
    done = not inside  # threads outside the image only help stage batches
    for batch in range(start, end, TILE_PIXELS):
        # the block stops once every pixel is done; this reduction is also the barrier that keeps
        # the staging below from overwriting records other threads are still reading
        if wp.tile_extract(wp.tile_sum(wp.tile(int(done))), 0) == block_width():
            break
        count = wp.min(TILE_PIXELS, end - batch)
        for slot in range(rank, TILE_PIXELS, block_width()):  # one pass on CUDA, 256 on a 1-wide block
            has = slot < count
            _, record, conic, c = list_record(gaussian_ids, means2d, conics, opacities_t, colors, batch + slot, has)
            wp.tile_scatter_masked(xy_opacity, slot, record, has)
            wp.tile_scatter_masked(conic_batch, slot, conic, has)
            wp.tile_scatter_masked(color_batch, slot, c, has)
        if not done:
            for j in range(count):
                record = wp.tile_extract(xy_opacity, j)
                power = gaussian_power(wp.vec2(record[0], record[1]), wp.tile_extract(conic_batch, j), pixel)
                if power > POWER_SKIP:
                    continue
                alpha = wp.min(ALPHA_MAX, record[2] * wp.exp(-power))
                if alpha < ALPHA_MIN:
                    continue
                next_trans = trans * (1.0 - alpha)
                if next_trans <= T_MIN:
                    done = True
                    break
                color += wp.tile_extract(color_batch, j) * (alpha * trans)
                trans = next_trans
                last = batch + j + 1
    if inside:
        out_color[y, x] = color
        out_trans[y, x] = trans
        out_end[y, x] = last


# the backward's block: a thread per two pixels of its tile, one above the other, so that a warp (a 16x4
# patch) sums the nine gradient terms of an entry over 64 pixels with one set of lane sums
PAIR_THREADS = wp.constant(TILE_PIXELS // 2)


@wp.func
def paired_pixels(tid: int, tiles_x: int, tile_order: wp.array(dtype=wp.int32)) -> wp.vec4i:
    """(tile, x, y, y + 1): the pixels of thread `tid` of raster_backward_batched. Block b composites tile
    tile_order[b] (b when `tile_order` is empty); its thread l takes column l % TILE, rows 2 (l // TILE)
    and the one below."""
    block = tid // PAIR_THREADS
    local = tid - block * PAIR_THREADS
    tile = block_tile(block, tile_order)
    origin = tile_origin(tile, tiles_x)
    y = origin[1] + 2 * (local // TILE)
    return wp.vec4i(tile, origin[0] + local % TILE, y, y + 1)


@wp.func
def entry_alpha(record: wp.vec3, conic: wp.vec3, pixel: wp.vec2) -> wp.vec3:
    """(alpha clamped, raw alpha o exp(-power), falloff exp(-power)) of a staged entry at `pixel`."""
    falloff = wp.exp(-gaussian_power(wp.vec2(record[0], record[1]), conic, pixel))
    raw_alpha = record[2] * falloff
    return wp.vec3(wp.min(ALPHA_MAX, raw_alpha), raw_alpha, falloff)


@wp.kernel
def raster_backward_batched(
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
    # Launched over num_tiles * PAIR_THREADS threads: a thread walks two pixels (`paired_pixels`), each
    # with the arithmetic of raster.py's per-pixel backward, and adds their terms before the lane sums.
    # The block walks back from its largest `end` in batches, every thread through every batch (no
    # early return: barriers and the warp-lane sums before the atomics need all threads).
    tid = wp.tid()
    pixels = paired_pixels(tid, tiles_x, tile_order)
    tile = pixels[0]
    x = pixels[1]
    pixel0 = wp.vec2(float(x) + 0.5, float(pixels[2]) + 0.5)
    pixel1 = wp.vec2(float(x) + 0.5, float(pixels[3]) + 0.5)
    rank = tid % block_width()
    start = ranges[tile, 0]
    end0, trans0, dc0, dt_final0 = pixel_backward_state(out_trans, out_end, v_color, v_trans, x, pixels[2], width,
                                                        height, start)
    end1, trans1, dc1, dt_final1 = pixel_backward_state(out_trans, out_end, v_color, v_trans, x, pixels[3], width,
                                                        height, start)
    end = wp.max(end0, end1)
    block_end = wp.tile_extract(wp.tile_max(wp.tile(end)), 0)
    # two batches of records, used in turn: a thread staging batch b + 1 into one half has passed
    # the barrier of batch b's staging, which every thread reaches only after it has read batch
    # b - 1 from the other half, so no extra barrier is needed before overwriting; 20 KB
    id_batch = wp.tile_empty(shape=(2, TILE_PIXELS), dtype=wp.int32, storage="shared")
    xy_opacity = wp.tile_empty(shape=(2, TILE_PIXELS), dtype=wp.vec3, storage="shared")
    conic_batch = wp.tile_empty(shape=(2, TILE_PIXELS), dtype=wp.vec3, storage="shared")
    color_batch = wp.tile_empty(shape=(2, TILE_PIXELS), dtype=wp.vec3, storage="shared")
    behind0 = wp.vec3(0.0)  # colour composited behind the current Gaussian, already weighted
    behind1 = wp.vec3(0.0)
    lead = lane_index() == 0
    warp_end = lanes_max(end)  # no pixel of this warp composited an entry at or past it
    half = int(0)
    for batch_end in range(block_end, start, -TILE_PIXELS):
        count = wp.min(TILE_PIXELS, batch_end - start)
        # slot s holds list entry batch_end - 1 - s: the batch is stored back to front
        for slot in range(rank, TILE_PIXELS, block_width()):  # two passes on CUDA
            has = slot < count
            g, record, conic, c = list_record(gaussian_ids, means2d, conics, opacities_t, colors, batch_end - 1 - slot,
                                              has)
            wp.tile_scatter_masked(id_batch, half, slot, g, has)
            wp.tile_scatter_masked(xy_opacity, half, slot, record, has)
            wp.tile_scatter_masked(conic_batch, half, slot, conic, has)
            wp.tile_scatter_masked(color_batch, half, slot, c, has)
        # entries past the warp's pixels are skipped by all its 32 lanes alike (converged for the shuffles)
        for j in range(wp.max(0, batch_end - warp_end), count):
            k = batch_end - 1 - j
            record = wp.tile_extract(xy_opacity, half, j)
            conic = wp.tile_extract(conic_batch, half, j)
            a0 = entry_alpha(record, conic, pixel0)
            a1 = entry_alpha(record, conic, pixel1)
            used0 = k < end0 and a0[0] >= ALPHA_MIN
            used1 = k < end1 and a1[0] >= ALPHA_MIN
            v_col = wp.vec3(0.0)
            v_opac = float(0.0)
            v_conic = wp.vec3(0.0)
            v_mean = wp.vec2(0.0)
            if used0 or used1:
                center = wp.vec2(record[0], record[1])
                c = wp.tile_extract(color_batch, half, j)
                if used0:
                    trans0, behind0, v_col, v_opac, v_conic, v_mean = unblend(
                        a0[0], a0[1], a0[2], trans0, behind0, c, dc0, dt_final0, center, conic, pixel0)
                if used1:
                    trans1, behind1, col1, opac1, conic1, mean1 = unblend(
                        a1[0], a1[1], a1[2], trans1, behind1, c, dc1, dt_final1, center, conic, pixel1)
                    v_col += col1
                    v_opac += opac1
                    v_conic += conic1
                    v_mean += mean1
            if lanes_any(used0 or used1):
                v_col = lanes_sum_vec3(v_col)
                v_opac = lanes_sum(v_opac)
                v_conic = lanes_sum_vec3(v_conic)
                v_mean = lanes_sum_vec2(v_mean)
                if lead:
                    g = wp.tile_extract(id_batch, half, j)
                    wp.atomic_add(v_colors, g, v_col)
                    wp.atomic_add(v_opacities_t, g, v_opac)
                    wp.atomic_add(v_conics, g, v_conic)
                    wp.atomic_add(v_means2d, g, v_mean)
        half = 1 - half
