"""tomgs.runtime's descriptors: what a kernel reads through them is what the tensor holds."""

from __future__ import annotations

import pytest
import torch
import warp as wp

from scenes import devices
from tomgs.runtime import launch, scope, wrap, wrap_part


@wp.kernel
def _copy(src: wp.array(dtype=wp.int32), dst: wp.array(dtype=wp.int32)):
    i = wp.tid()
    dst[i] = src[i]


@pytest.mark.parametrize("device", devices())
def test_wrap_part_reads_and_writes_its_range_only(device):
    """A kernel sees elements [start, start + length) of the tensor, and writing through the part
    changes nothing outside it."""
    values = torch.arange(20, dtype=torch.int32, device=device)
    target = torch.full((20,), -1, dtype=torch.int32, device=device)
    with scope(values.device) as wp_device:
        launch(_copy, 6, device=wp_device, args=[wrap_part(values, 7, 6), wrap(target)])
        launch(_copy, 3, device=wp_device, args=[wrap(values), wrap_part(target, 15, 3)])
    expected = torch.full((20,), -1, dtype=torch.int32)
    expected[:6] = torch.arange(7, 13)
    expected[15:18] = torch.arange(3)
    assert torch.equal(target.cpu(), expected)


@pytest.mark.parametrize("start, length", [(-1, 2), (19, 2), (0, 21)])
def test_wrap_part_refuses_a_range_outside_the_tensor(start, length):
    with pytest.raises(ValueError, match="range of a contiguous 1D tensor"):
        wrap_part(torch.zeros(20, dtype=torch.int32), start, length)


def test_wrap_part_refuses_a_strided_or_2d_tensor():
    with pytest.raises(ValueError, match="contiguous 1D"):
        wrap_part(torch.zeros(20, dtype=torch.int32)[::2], 0, 2)
    with pytest.raises(ValueError, match="contiguous 1D"):
        wrap_part(torch.zeros(4, 5, dtype=torch.int32), 0, 2)
