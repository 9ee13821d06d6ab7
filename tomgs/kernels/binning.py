"""Stage 2: binning. Each visible Gaussian writes one 64-bit key per tile it touches,
`tile << 32 | depth bits`, so that one radix sort orders by tile, then front to back.
The exclusive scan of tiles touched and the sort itself are library primitives run by the caller.
"""

import warp as wp

from tomgs import constants

wp.set_module_options({"enable_backward": False})

TILE = wp.constant(constants.TILE_SIZE)


@wp.func
def tile_rect(center: wp.vec2, radius: wp.vec2i, tiles_x: int, tiles_y: int) -> wp.vec4i:
    """Tiles [x0, x1) x [y0, y1) overlapped by the box center +- radius, clamped to the image."""
    tile = float(TILE)
    x0 = wp.clamp(wp.floor((center[0] - float(radius[0])) / tile), 0.0, float(tiles_x))
    x1 = wp.clamp(wp.floor((center[0] + float(radius[0])) / tile) + 1.0, 0.0, float(tiles_x))
    y0 = wp.clamp(wp.floor((center[1] - float(radius[1])) / tile), 0.0, float(tiles_y))
    y1 = wp.clamp(wp.floor((center[1] + float(radius[1])) / tile) + 1.0, 0.0, float(tiles_y))
    return wp.vec4i(int(x0), int(y0), int(x1), int(y1))


@wp.kernel
def write_tile_keys(
    means2d: wp.array(dtype=wp.vec2),  # [N]
    radii: wp.array(dtype=wp.vec2i),  # [N]
    depths: wp.array(dtype=float),  # [N] > 0 for every visible Gaussian
    ends: wp.array(dtype=wp.int64),  # [N] inclusive scan of tiles touched
    tiles_x: int,
    tiles_y: int,
    keys: wp.array(dtype=wp.int64),  # out [>= total] tile << 32 | depth bits
    gaussian_ids: wp.array(dtype=wp.int32),  # out [>= total]
):
    i = wp.tid()
    r = radii[i]
    if r[0] == 0 and r[1] == 0:
        return
    rect = tile_rect(means2d[i], r, tiles_x, tiles_y)
    # a positive float's bit pattern orders like its value
    depth_bits = wp.int64(wp.cast(depths[i], wp.int32))
    k = int(ends[i]) - (rect[2] - rect[0]) * (rect[3] - rect[1])
    for ty in range(rect[1], rect[3]):
        for tx in range(rect[0], rect[2]):
            keys[k] = (wp.int64(ty * tiles_x + tx) << wp.int64(32)) | depth_bits
            gaussian_ids[k] = i
            k += 1


@wp.kernel
def tile_ranges(
    sorted_keys: wp.array(dtype=wp.int64),  # [M] sorted
    count: int,  # M
    ranges: wp.array2d(dtype=wp.int32),  # out [tiles, 2] [start, end) into the sorted list; zeroed by the caller
):
    k = wp.tid()
    tile = int(sorted_keys[k] >> wp.int64(32))
    if k == 0:
        ranges[tile, 0] = 0
    else:
        prev = int(sorted_keys[k - 1] >> wp.int64(32))
        if prev != tile:
            ranges[prev, 1] = k
            ranges[tile, 0] = k
    if k == count - 1:
        ranges[tile, 1] = count
