"""A training step replayed from a CUDA graph (tomgs.train.captured_step): the values the host writes
before each replay, and what the step decides and records on the device for the host to read later.

A captured kernel keeps the scalar arguments it was captured with, so whatever changes from step to
step (the frame, the Adam rates, whether the update counts) is written into device memory by one
launch before the replay (`set_step`) and read there by the graph's kernels. Inside the graph,
`judge_step` decides whether the step's update applies (the frame's keys held its whole list and its
inputs kept the renderer's contract) and records the frame's flags and PSNR in rings the host reads
a few steps later; `seen_rows` turns the projected radii into the rows Adam and the densifier's
statistics take.
"""

import warp as wp

from tomgs.kernels.adam import vec_slots
from tomgs.kernels.project import CONTRACT_FLAGS, FLAG_TOTAL, NUM_FLAGS

wp.set_module_options({"enable_backward": False})

# the step's integers in device memory (`ints` [STEP_INTS] int64), by position
STEP_FRAME = wp.constant(0)  # the frame trained on: its camera, time and target
STEP_SLOT = wp.constant(1)  # the rings' slot this step records in
STEP_APPLY = wp.constant(2)  # 1: the update applies; 0: a rehearsal (a capture's warm-up) that changes nothing
STEP_COLLECT = wp.constant(3)  # 1: the densifier's statistics take this step
STEP_INTS = 4
CONTRACT_MASK = wp.constant(sum(1 << k for k in CONTRACT_FLAGS))  # the flags' slots that refuse a frame


@wp.kernel
def set_step(
    frame: int,
    slot: int,
    apply: int,
    collect: int,
    lr: vec_slots,  # Adam's learning rate of each slot (tomgs.kernels.adam)
    bias1: vec_slots,  # 1 - beta1^step
    bias2_sqrt: vec_slots,  # sqrt(1 - beta2^step)
    ints: wp.array(dtype=wp.int64),  # out [STEP_INTS]
    rates: wp.array(dtype=vec_slots),  # out [3]: lr, bias1, bias2_sqrt (adam_seen_rows_read's)
):
    # one thread: everything a replay reads that changes from step to step, in one launch
    ints[STEP_FRAME] = wp.int64(frame)
    ints[STEP_SLOT] = wp.int64(slot)
    ints[STEP_APPLY] = wp.int64(apply)
    ints[STEP_COLLECT] = wp.int64(collect)
    rates[0] = lr
    rates[1] = bias1
    rates[2] = bias2_sqrt


@wp.kernel
def judge_step(
    flags: wp.array(dtype=wp.int64),  # [NUM_FLAGS] the frame's (tomgs.kernels.project)
    measured: wp.array(dtype=float),  # [1] the frame's PSNR
    ints: wp.array(dtype=wp.int64),  # [STEP_INTS] set_step's
    capacity: wp.int64,  # the tile keys the frame holds
    ok: wp.array(dtype=wp.int32),  # out [1]: 1 where the update applies
    flags_ring: wp.array2d(dtype=wp.int64),  # out [R, NUM_FLAGS]: row `slot` takes the flags
    psnr_ring: wp.array(dtype=float),  # out [R]: `slot` takes the PSNR, NaN where the update does not apply
):
    # one thread. A frame whose total passed its keys lacks entries (its image and gradients are wrong),
    # and one outside the contract is refused: neither updates anything, and the host, reading the
    # flags later, learns the larger total (and captures again) or raises the contract's error
    contract = wp.int64(0)
    for k in range(NUM_FLAGS):
        if (CONTRACT_MASK >> k) & 1 == 1:
            contract = contract | flags[k]
    good = ints[STEP_APPLY] != wp.int64(0) and flags[FLAG_TOTAL] <= capacity and contract == wp.int64(0)
    slot = int(ints[STEP_SLOT])
    for k in range(NUM_FLAGS):
        flags_ring[slot, k] = flags[k]
    if good:
        ok[0] = 1
        psnr_ring[slot] = measured[0]
    else:
        ok[0] = 0
        psnr_ring[slot] = wp.nan


@wp.kernel
def seen_rows(
    radii: wp.array(dtype=wp.vec2i),  # [N] projection's (0, 0): culled
    ok: wp.array(dtype=wp.int32),  # [1] judge_step's
    ints: wp.array(dtype=wp.int64),  # [STEP_INTS]
    in_view: wp.array(dtype=wp.bool),  # out [N]: rows the step's update takes (Adam's `seen`)
    observed: wp.array(dtype=wp.bool),  # out [N]: rows the densifier's statistics take
):
    # the eager step's (radii > 0).any(-1), for an update that applies
    i = wp.tid()
    r = radii[i]
    seen = ok[0] != 0 and (r[0] > 0 or r[1] > 0)
    in_view[i] = seen
    observed[i] = seen and ints[STEP_COLLECT] != wp.int64(0)
