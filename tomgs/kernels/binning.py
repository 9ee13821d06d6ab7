"""Stage 2: binning. Each visible Gaussian writes one 64-bit key per tile it touches,
`tile << 32 | depth bits`, so that one radix sort orders by tile, then front to back.
The exclusive scan of tiles touched and the sort itself are library primitives run by the caller.

A Gaussian touches the tiles of its box (`tile_rect`) whose pixel centres its ellipse reaches:
{d : d^T conic d <= level}, the pixels where alpha = o exp(-d^T conic d / 2) can reach 1/255
(`ellipse_level`). Projection counts them and `write_tile_keys` writes them with the same
function, `row_tiles`, one tile row at a time, so that the two agree exactly.

With ~10-25% of the Gaussians visible at a frame, nearly every warp of a pass over all of them holds
a few: a warp holding at least `inline_lanes` visible ones writes their keys itself, the others list
theirs for `write_tile_keys_listed`, which writes them in full warps (tomgs/kernels/lanes.py).
"""

import warp as wp

from tomgs import constants
from tomgs.kernels.lanes import DENSE_REGISTERS, lanes_count, list_row, work_item

wp.set_module_options({"enable_backward": False})

TILE = wp.constant(constants.TILE_SIZE)
ALPHA_MIN = wp.constant(constants.ALPHA_MIN)
RADIUS_SIGMAS = wp.constant(constants.RADIUS_SIGMAS)
# slack on the level: relative and absolute for the float32 log and the raster's fast exp, and 8
# float32 ulps of the largest terms of the raster's float32 power, which a needle's power cancels
# down from
LEVEL_REL = wp.constant(wp.float64(2.0**-10))
LEVEL_NOISE = wp.constant(wp.float64(2.0**-20))


@wp.func
def opacity_extent(opac: float) -> float:
    """Standard deviations out to which alpha = opac exp(-x^2 / 2) stays >= 1/255, at most RADIUS_SIGMAS."""
    return wp.min(RADIUS_SIGMAS, wp.sqrt(wp.max(2.0 * wp.log(opac / ALPHA_MIN), 0.0)))


@wp.func
def tile_rect(center: wp.vec2, radius: wp.vec2i, tiles_x: int, tiles_y: int) -> wp.vec4i:
    """Tiles [x0, x1) x [y0, y1) overlapped by the box center +- radius, clamped to the image."""
    tile = float(TILE)
    x0 = wp.clamp(wp.floor((center[0] - float(radius[0])) / tile), 0.0, float(tiles_x))
    x1 = wp.clamp(wp.floor((center[0] + float(radius[0])) / tile) + 1.0, 0.0, float(tiles_x))
    y0 = wp.clamp(wp.floor((center[1] - float(radius[1])) / tile), 0.0, float(tiles_y))
    y1 = wp.clamp(wp.floor((center[1] + float(radius[1])) / tile) + 1.0, 0.0, float(tiles_y))
    return wp.vec4i(int(x0), int(y0), int(x1), int(y1))


@wp.func
def ellipse_level(conic: wp.vec3, radius: wp.vec2i, opac: float) -> wp.float64:
    """Bound on 2 x power = d^T conic d over every pixel of the box's tiles that the raster may draw
    (alpha >= 1/255): extent^2 plus slack (LEVEL_REL, LEVEL_NOISE), so no drawn pixel is dropped."""
    extend = wp.float64(opacity_extent(opac))
    x = wp.float64(radius[0] + TILE)  # the farthest pixel centre of a box tile from the centre
    y = wp.float64(radius[1] + TILE)
    terms = wp.float64(conic[0]) * x * x + wp.float64(conic[2]) * y * y
    return extend * extend * (wp.float64(1.0) + LEVEL_REL) + LEVEL_REL + LEVEL_NOISE * terms


@wp.func
def widen_at(span: wp.vec2d, A: wp.float64, B: wp.float64, D: wp.float64, level: wp.float64,
             y: wp.float64) -> wp.vec2d:
    """`span` [lo, hi] widened by the ellipse's x-interval at height y, -B y / A +- sqrt(level A - D y^2) / A
    (relative to the centre), left as it is where the ellipse does not reach y."""
    disc = level * A - D * y * y
    if disc < wp.float64(0.0):
        return span
    h = wp.sqrt(disc) / A
    m = -B * y / A
    return wp.vec2d(wp.min(span[0], m - h), wp.max(span[1], m + h))


@wp.func
def row_tiles(center: wp.vec2, conic: wp.vec3, level: wp.float64, rect: wp.vec4i, ty: int) -> wp.vec2i:
    """Tiles [x0, x1) of tile row ty, inside the box's tiles `rect`, whose rectangle of pixel centres
    meets the ellipse d^T conic d <= level (d = pixel - center); x0 = x1 when none does."""
    A = wp.float64(conic[0])
    B = wp.float64(conic[1])
    C = wp.float64(conic[2])
    if not (A > wp.float64(0.0)):  # an underflowed conic: keep the box's row
        return wp.vec2i(rect[0], rect[2])
    D = A * C - B * B  # products of float32s are exact in float64: the float32 conic's own ellipse
    tile = wp.float64(TILE)
    ya = tile * wp.float64(ty) + wp.float64(0.5) - wp.float64(center[1])  # the row's pixel centres, y - cy
    yb = ya + tile - wp.float64(1.0)
    # x-range of the ellipse over ya <= y <= yb: the left (right) edge is convex (concave) in y, so its
    # extreme lies at a band end, unless the ellipse's leftmost (rightmost) point lies inside the band;
    # with D <= 0 (a float32 conic degenerate to a strip or worse) there is no such point
    inf = wp.float64(wp.inf)
    span = widen_at(widen_at(wp.vec2d(inf, -inf), A, B, D, level, ya), A, B, D, level, yb)
    lo = span[0]
    hi = span[1]
    if D > wp.float64(0.0):
        xe = wp.sqrt(level * C / D)  # half width; the rightmost point is (xe, -B xe / C)
        ye = B * xe / C
        if -ye >= ya and -ye <= yb:
            hi = xe
        if ye >= ya and ye <= yb:
            lo = -xe
    # tile tx holds pixel centres 16 tx + 0.5 .. 16 tx + 15.5
    cx = wp.float64(center[0])
    first = wp.ceil((cx + lo - tile + wp.float64(0.5)) / tile)
    last = wp.floor((cx + hi - wp.float64(0.5)) / tile) + wp.float64(1.0)
    x0 = int(wp.clamp(first, wp.float64(rect[0]), wp.float64(rect[2])))
    x1 = int(wp.clamp(last, wp.float64(x0), wp.float64(rect[2])))
    return wp.vec2i(x0, x1)


@wp.func
def tiles_of(center: wp.vec2, conic: wp.vec3, radius: wp.vec2i, opac: float, tiles_x: int, tiles_y: int) -> int:
    """How many tiles `write_tile_keys` writes for this Gaussian: its ellipse's tiles, or the box's
    first tile when the ellipse reaches none (a Gaussian whose box is on screen always holds one, so
    that counting the Gaussians that hold tiles counts the visible ones)."""
    rect = tile_rect(center, radius, tiles_x, tiles_y)
    level = ellipse_level(conic, radius, opac)
    count = int(0)
    for ty in range(rect[1], rect[3]):
        span = row_tiles(center, conic, level, rect, ty)
        count += span[1] - span[0]
    if count == 0 and rect[2] > rect[0] and rect[3] > rect[1]:
        count = 1
    return count


@wp.func
def write_keys_of(
    i: int,  # a visible Gaussian
    r: wp.vec2i,  # its radii
    means2d: wp.array(dtype=wp.vec2),
    conics: wp.array(dtype=wp.vec3),
    opacities_t: wp.array(dtype=float),
    depths: wp.array(dtype=float),
    ends: wp.array(dtype=wp.int64),
    tiles_x: int,
    tiles_y: int,
    capacity: int,
    keys: wp.array(dtype=wp.int64),
    gaussian_ids: wp.array(dtype=wp.int32),
):
    """Gaussian i's keys and ids, in its slots [ends[i-1], ends[i]) below `capacity` (as write_tile_keys)."""
    # its slots, clipped to the capacity in int64 (launched before the total is known, when ends may
    # exceed int32): a frame past the capacity writes a prefix and nothing beyond
    k = int(0)
    if i > 0:
        k = int(wp.min(ends[i - 1], wp.int64(capacity)))
    end = int(wp.min(ends[i], wp.int64(capacity)))
    if k >= end:
        return
    center = means2d[i]
    conic = conics[i]
    rect = tile_rect(center, r, tiles_x, tiles_y)
    level = ellipse_level(conic, r, opacities_t[i])
    # a positive float's bit pattern orders like its value
    depth_bits = wp.int64(wp.cast(depths[i], wp.int32))
    # writes stay in this Gaussian's slots even where the counts came from elsewhere
    for ty in range(rect[1], rect[3]):
        span = row_tiles(center, conic, level, rect, ty)
        for tx in range(span[0], wp.min(span[1], span[0] + end - k)):
            keys[k] = (wp.int64(ty * tiles_x + tx) << wp.int64(32)) | depth_bits
            gaussian_ids[k] = i
            k += 1
    if k < end:  # the ellipse reached no tile: the box's first one, as `tiles_of` counts
        keys[k] = (wp.int64(rect[1] * tiles_x + rect[0]) << wp.int64(32)) | depth_bits
        gaussian_ids[k] = i


@wp.kernel(cuda_max_registers=DENSE_REGISTERS)
def write_tile_keys(
    means2d: wp.array(dtype=wp.vec2),  # [N]
    conics: wp.array(dtype=wp.vec3),  # [N]
    opacities_t: wp.array(dtype=float),  # [N]
    radii: wp.array(dtype=wp.vec2i),  # [N] (0, 0): culled
    depths: wp.array(dtype=float),  # [N] > 0 for every visible Gaussian
    ends: wp.array(dtype=wp.int64),  # [N] inclusive scan of tiles touched (`tiles_of`)
    tiles_x: int,
    tiles_y: int,
    capacity: int,  # slots of keys and ids that may be written: [0, capacity); total may exceed it
    keys: wp.array(dtype=wp.int64),  # out [>= capacity] tile << 32 | depth bits
    gaussian_ids: wp.array(dtype=wp.int32),  # out [>= capacity]
    inline_lanes: int,  # a warp holding this many visible lanes writes their keys (INLINE_LANES; 1 on a CPU)
    list_capacity: int,  # slots of each work list (lanes.work_capacity(N))
    work: wp.array(dtype=wp.int32),  # out [WORK_LISTS x list_capacity]: Gaussians left to write_tile_keys_listed
    work_counts: wp.array(dtype=wp.int32),  # [lanes.work_counters(1)] zeroed by the caller
):
    # the visible Gaussians of a warp holding at least inline_lanes of them write their keys here, the
    # others' are listed for write_tile_keys_listed, which writes them in full warps (with ~10-25% of
    # the Gaussians visible at a frame nearly every warp holds a few, and takes as long as its slowest)
    i = wp.tid()
    r = radii[i]
    visible = r[0] != 0 or r[1] != 0  # else culled (most rows of a frame, the dead): its scan entries are not read
    inline = lanes_count(visible) >= inline_lanes  # the same for the warp's lanes
    list_row(visible and not inline, i, list_capacity, work, work_counts)  # every lane reaches it: no return above
    if visible and inline:
        write_keys_of(i, r, means2d, conics, opacities_t, depths, ends, tiles_x, tiles_y, capacity, keys,
                      gaussian_ids)


@wp.kernel
def write_tile_keys_listed(
    means2d: wp.array(dtype=wp.vec2),  # [N] (as write_tile_keys)
    conics: wp.array(dtype=wp.vec3),
    opacities_t: wp.array(dtype=float),
    radii: wp.array(dtype=wp.vec2i),
    depths: wp.array(dtype=float),
    ends: wp.array(dtype=wp.int64),
    tiles_x: int,
    tiles_y: int,
    capacity: int,
    keys: wp.array(dtype=wp.int64),
    gaussian_ids: wp.array(dtype=wp.int32),
    list_capacity: int,  # write_tile_keys's work lists: the visible Gaussians it left
    work: wp.array(dtype=wp.int32),
    work_counts: wp.array(dtype=wp.int32),
):
    # launched over the work lists' slots, run where one lists a row
    i = work_item(wp.tid(), list_capacity, work, work_counts)
    if i < 0:
        return
    write_keys_of(i, radii[i], means2d, conics, opacities_t, depths, ends, tiles_x, tiles_y, capacity, keys,
                  gaussian_ids)


@wp.kernel
def pad_tile_keys(
    ends: wp.array(dtype=wp.int64),  # [N] inclusive scan of tiles touched; ends[N-1] is the total
    n: int,  # N
    padding: wp.int64,  # a key past every tile of the frame, sorted last
    keys: wp.array(dtype=wp.int64),  # in/out [>= capacity]: slots from the total on get `padding`
):
    """Launched over a buffer's capacity when the total is not known on the host (a frame that does
    not wait for its counts): the slots `write_tile_keys` leaves unwritten become padding, so that
    sorting the whole capacity puts the list first and `tile_ranges` skips the rest."""
    k = wp.tid()
    total = wp.int64(0)
    if n > 0:
        total = ends[n - 1]
    if wp.int64(k) >= total:
        keys[k] = padding


@wp.kernel
def tile_ranges(
    sorted_keys: wp.array(dtype=wp.int64),  # [M] sorted; entries of tile >= num_tiles are padding, last
    count: int,  # M
    num_tiles: int,
    ranges: wp.array2d(dtype=wp.int32),  # out [tiles, 2] [start, end) into the sorted list; zeroed by the caller
):
    k = wp.tid()
    tile = int(sorted_keys[k] >> wp.int64(32))
    prev = int(-1)
    if k > 0:
        prev = int(sorted_keys[k - 1] >> wp.int64(32))
    if prev != tile:
        if prev >= 0 and prev < num_tiles:
            ranges[prev, 1] = k
        if tile < num_tiles:
            ranges[tile, 0] = k
    if k == count - 1 and tile < num_tiles:
        ranges[tile, 1] = count
