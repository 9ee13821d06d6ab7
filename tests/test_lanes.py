"""Warp-lane helpers (tomgs/kernels/lanes.py) on every device: the CPU's identities and the GPU's
shuffles and votes must give the same results."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from scenes import devices
from tomgs.kernels.lanes import append_slot


@wp.kernel
def _append_kept(keep: wp.array(dtype=wp.int32), counter: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.int32)):
    i = wp.tid()
    slot = append_slot(keep[i] != 0, counter)
    if slot >= 0:
        out[slot] = i


@pytest.mark.parametrize("device", devices())
@pytest.mark.parametrize("share", [0.0, 0.1, 0.5, 1.0])
def test_append_slot_lists_every_kept_thread_once(device, share):
    """Dense, unique slots for exactly the threads that keep, a launch's last group of lanes partial
    (1000 threads), none kept and all kept included; in thread order on the CPU."""
    rng = np.random.default_rng(int(share * 10))
    keep = (rng.random(1000) < share).astype(np.int32)
    counter = wp.zeros(1, dtype=wp.int32, device=device)
    out = wp.full(1000, -1, dtype=wp.int32, device=device)
    wp.launch(_append_kept, 1000, inputs=[wp.array(keep, device=device), counter, out], device=device)
    count, listed = int(counter.numpy()[0]), out.numpy()
    want = np.flatnonzero(keep)
    assert count == len(want)
    assert (listed[count:] == -1).all()
    assert sorted(listed[:count].tolist()) == want.tolist()
    if device == "cpu":
        assert listed[:count].tolist() == want.tolist()
