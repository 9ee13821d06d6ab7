"""Warp-lane helpers (tomgs/kernels/lanes.py) on every device: the CPU's identities and the GPU's
shuffles and votes must give the same results."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from scenes import devices
from tomgs.kernels.lanes import append_slot, lanes_count


@wp.kernel
def _append_kept(keep: wp.array(dtype=wp.int32), lists: int, capacity: int, counters: wp.array(dtype=wp.int32),
                 out: wp.array(dtype=wp.int32)):
    i = wp.tid()
    which = (i // 32) % lists  # the same for a group of 32 lanes
    slot = append_slot(keep[i] != 0, counters, which)
    if slot >= 0:
        out[which * capacity + slot] = i


@pytest.mark.parametrize("device", devices())
@pytest.mark.parametrize("share", [0.0, 0.1, 0.5, 1.0])
@pytest.mark.parametrize("lists", [1, 3])
def test_append_slot_lists_every_kept_thread_once(device, share, lists):
    """Dense, unique slots for exactly the threads that keep, in the list their group names, a
    launch's last group of lanes partial (1000 threads), none kept and all kept included; in thread
    order on the CPU."""
    rng = np.random.default_rng(int(share * 10))
    keep = (rng.random(1000) < share).astype(np.int32)
    capacity = 1000
    counters = wp.zeros(lists, dtype=wp.int32, device=device)
    out = wp.full(lists * capacity, -1, dtype=wp.int32, device=device)
    wp.launch(_append_kept, 1000, inputs=[wp.array(keep, device=device), lists, capacity, counters, out], device=device)
    counts, listed = counters.numpy(), out.numpy().reshape(lists, capacity)
    for which in range(lists):
        want = [i for i in np.flatnonzero(keep) if (i // 32) % lists == which]
        count = int(counts[which])
        assert count == len(want)
        assert (listed[which, count:] == -1).all()
        assert sorted(listed[which, :count].tolist()) == want
        if device == "cpu":
            assert listed[which, :count].tolist() == want


@wp.kernel
def _count_kept(keep: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.int32)):
    i = wp.tid()
    out[i] = lanes_count(keep[i] != 0)


@pytest.mark.parametrize("device", devices())
def test_lanes_count_counts_a_group_of_lanes(device):
    """Each thread gets the count of its group of 32 (a launch's last group partial); on the CPU,
    where every thread runs alone, its own 0 or 1."""
    keep = (np.random.default_rng(3).random(1000) < 0.4).astype(np.int32)
    out = wp.zeros(1000, dtype=wp.int32, device=device)
    wp.launch(_count_kept, 1000, inputs=[wp.array(keep, device=device), out], device=device)
    got = out.numpy()
    if device == "cpu":
        assert got.tolist() == keep.tolist()
    else:
        want = np.repeat(np.add.reduceat(keep, np.arange(0, 1000, 32)), 32)[:1000]
        assert got.tolist() == want.tolist()
