"""Block (CUDA thread block) collectives shared by the kernels.

A block is 256 threads on CUDA; on the CPU Warp runs blocks of width 1 (every thread alone), or of
256 cooperative fibers with `wp.config.enable_cpu_blocks` (real block semantics, for tests). Every
thread of a block must reach a collective (no early return before it), so kernels that use one are
launched over whole blocks (`tomgs.render.whole_blocks`) and guard their last, partial block.
"""

import warp as wp

MAX_BLOCK = wp.constant(256)  # the widest block a kernel of this package is launched with


@wp.func_native("return WP_TILE_BLOCK_DIM;")
def block_width() -> int:
    """Threads per block, as the module was compiled for it (256 on CUDA; 1, or 256 with
    wp.config.enable_cpu_blocks, on the CPU): a constant to the compiler, unlike wp.block_dim()."""
    ...


@wp.func
def packed_work(live: bool, tid: int) -> int:
    """Which thread's work this thread does (a tid of its block), or -1 for none: its own when it is
    live and most of its block is; else the block's live threads are packed, in order, into its first
    lanes. A block with few live threads then runs their long path in one or two warps instead of
    every warp it has, each mostly idle (divergence: a warp takes as long as its slowest lane).
    Called by every thread of the block; `tid` is wp.tid() of a launch over whole blocks."""
    flags = wp.tile(int(live))
    count = wp.tile_extract(wp.tile_sum(flags), 0)  # the same in every thread: a uniform branch
    if 2 * count > block_width():
        if live:
            return tid
        return -1
    lane = tid % block_width()
    slots = wp.tile_empty(shape=MAX_BLOCK, dtype=int, storage="shared")
    wp.tile_scatter_masked(slots, wp.tile_extract(wp.tile_scan_exclusive(flags), lane), tid, live)
    if lane < count:
        return wp.tile_extract(slots, lane)
    return -1
