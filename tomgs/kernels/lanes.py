"""Warp-lane (32-thread SIMT group) collectives for CUDA kernels, identities on the CPU.

On the GPU a group of 32 threads reduces its values with register shuffles before one lane does
the atomic add: this turns 32 contended atomics into one. On the CPU every thread runs alone,
so each helper is the identity and every thread is lane 0. Callers must reach these helpers with
all 32 lanes converged (no lane-dependent branch around the call), hence no early returns.
"""

import warp as wp

_FULL = "0xffffffffu"


def _shuffle_sum(fields: list[str]) -> str:
    adds = "\n".join(f"        r{f} += __shfl_xor_sync({_FULL}, r{f}, o);" for f in fields)
    return f"""
#if defined(__CUDA_ARCH__)
    auto r = v;
    for (int o = 16; o > 0; o >>= 1) {{
{adds}
    }}
    return r;
#else
    return v;
#endif
"""


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    return static_cast<wp::int32>(threadIdx.x & 31u);
#else
    return 0;
#endif
""")
def lane_index() -> int: ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    return __any_sync(0xffffffffu, pred) != 0;
#else
    return pred;
#endif
""")
def lanes_any(pred: bool) -> bool: ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    return __popc(__ballot_sync(__activemask(), pred));
#else
    return pred ? 1 : 0;
#endif
""")
def lanes_count(pred: bool) -> int:
    """How many running lanes of this group hold `pred` (the same for all of them): 0 or 1 on the CPU."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    wp::int32 r = x;
    for (int o = 16; o > 0; o >>= 1) {
        const wp::int32 other = __shfl_xor_sync(0xffffffffu, r, o);
        r = other > r ? other : r;
    }
    return r;
#else
    return x;
#endif
""")
def lanes_max(x: int) -> int: ...


@wp.func_native(_shuffle_sum([""]).replace("auto r = v;", "float r = v;"))
def lanes_sum(v: float) -> float: ...


@wp.func_native(_shuffle_sum([".c[0]", ".c[1]"]))
def lanes_sum_vec2(v: wp.vec2) -> wp.vec2: ...


@wp.func_native(_shuffle_sum([".c[0]", ".c[1]", ".c[2]"]))
def lanes_sum_vec3(v: wp.vec3) -> wp.vec3: ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    // one atomic per group of lanes: the lanes still running (a launch's last, partial group has
    // fewer) vote, the lowest voter reserves the group's slots, each keeper takes its rank among them
    const unsigned int active = __activemask();
    const unsigned int votes = __ballot_sync(active, keep);
    if (votes == 0u) return -1;
    const int lane = static_cast<int>(threadIdx.x & 31u);
    const int leader = __ffs(votes) - 1;
    int base = 0;
    if (lane == leader) base = atomicAdd(counters.data + which, __popc(votes));
    base = __shfl_sync(active, base, leader);
    return keep ? base + __popc(votes & ((1u << lane) - 1u)) : -1;
#else
    if (!keep) return -1;
    const wp::int32 slot = counters.data[which];
    counters.data[which] = slot + 1;
    return slot;
#endif
""")
def append_slot(keep: bool, counters: wp.array(dtype=wp.int32), which: int) -> int:
    """A slot of list `which` for a thread that `keep`s something (-1 for one that does not):
    counters[which] slots of it are taken so far, reserved with one atomic per group of lanes on the
    GPU, in thread order on the CPU. Slots are unique and dense; on the GPU their order across groups
    is not fixed. Every lane of a group must name the same list and reach the call (no lane-dependent
    branch around it)."""
    ...


# ---- work lists: a stage's long path run in full warps -------------------------------------------
# A warp takes as long as its slowest lane, so a pass over every Gaussian where ~15% hold work costs
# what running all of them costs. A dense pass settles what every row needs; a warp holding at least
# INLINE_LANES rows with work runs their long path itself, the others append those rows to work lists
# (`list_row`) that a listed pass runs in full warps (`work_item`).
# WORK_LISTS lists, warp w appending to list w % WORK_LISTS, so that the warps running at once add to
# different counters (one counter took ~150k contended atomics a frame), each counter on its own
# 128-byte line (COUNTER_STRIDE int32s apart): atomics to one line serialise where it is cached
# (on the H100, 5M rows at 10% listed: a dense pass 0.117 -> 0.066 ms). A listed pass runs one slot a
# thread: looping over 8 slots a thread made passes over full lists up to twice as slow.
WORK_LISTS = wp.constant(64)
COUNTER_STRIDE = wp.constant(32)
INLINE_LANES = 16  # on CUDA; on a CPU every thread runs alone, so each runs its own (inline lanes 1)
# Registers of a stage's dense pass over all N (`cuda_max_registers`; most rows dead at a frame): at 64,
# 4 blocks of 256 fit a multiprocessor where the projection's 74 (forward) and 109 (backward) registers
# fitted 3 and 2, and these passes are latency bound. H100 (docs/notes/rasterizer.md), 1080p 5M temporal:
# forward 0.203 -> 0.170 ms, backward 0.143 -> 0.122, keys 0.066 -> 0.053.
# The listed passes keep theirs: at 64 their long path lost 10-30%.
DENSE_REGISTERS = 64


def work_capacity(m: int) -> int:
    """Slots of each work list for a pass over M rows: the rows of the warps that append to it."""
    warps = -(-m // 32)
    return -(-warps // int(WORK_LISTS)) * 32


def work_counters(passes: int) -> int:
    """int32 elements of the counts of `passes` passes, zeroed by the caller."""
    return passes * int(WORK_LISTS) * int(COUNTER_STRIDE)


@wp.func
def list_row(keep: bool, row: int, capacity: int, work: wp.array(dtype=wp.int32),
             work_counts: wp.array(dtype=wp.int32)):
    """Append `row` (the thread's index) to its warp's list where `keep`. Every lane of the warp must
    reach it (no lane-dependent branch or return before it), as for `append_slot`."""
    which = (row // 32) % WORK_LISTS
    slot = append_slot(keep, work_counts, which * COUNTER_STRIDE)
    if slot >= 0:
        work[which * capacity + slot] = row


@wp.func
def work_item(w: int, capacity: int, work: wp.array(dtype=wp.int32), work_counts: wp.array(dtype=wp.int32)) -> int:
    """The row listed at slot w of the work lists laid end to end (`capacity` slots each), -1 past
    its list's count."""
    which = w // capacity
    if w - which * capacity >= work_counts[which * COUNTER_STRIDE]:
        return -1
    return work[w]
