"""Warp's launches and sort go to torch's current CUDA stream (tomgs.runtime.torch_stream), ordered
with the torch work around them on that stream, whichever stream it is. A side stream is kept busy
(torch.cuda._sleep) before the frame's inputs are written on it: a kernel on any other stream would
read them unwritten, and the frame would differ from the same frame rendered on the default stream.
CUDA only (runs on a GPU machine)."""

from __future__ import annotations

import pytest
import torch

import tomgs
from tomgs import runtime
from scenes import random_scene

NAMES = ("means", "quats", "scales", "opacities", "colors", "t_means", "t_scales")

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def frame(p: dict, camera: dict):
    """image, alpha, and the gradients of a weighted loss (SH colours: the SH kernels run too)."""
    image, alpha, _ = tomgs.rasterize(**p, **camera, width=45, height=37, t=0.4)
    weights = torch.linspace(0.0, 1.0, image.numel(), device=image.device).reshape(image.shape)
    ((image * weights).sum() + alpha.sum()).backward()
    return image, alpha, {name: p[name].grad for name in NAMES}


def test_a_frame_runs_on_torchs_current_stream_cuda():
    scene = random_scene(31, n=400, sh_degree=1)
    camera = dict(viewmat=scene["viewmat"].float().cuda(), K=scene["K"].float().cuda())
    values = {name: scene[name].float().cuda() for name in NAMES}
    want = frame({name: v.clone().requires_grad_(True) for name, v in values.items()}, camera)
    torch.cuda.synchronize()

    side = torch.cuda.Stream()
    staged = {name: torch.zeros_like(v) for name, v in values.items()}
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        assert runtime.torch_stream("cuda:%d" % torch.cuda.current_device()).cuda_stream == side.cuda_stream
        torch.cuda._sleep(200_000_000)  # the side stream busy for ~0.1 s before the inputs are written
        for name, value in values.items():
            staged[name].copy_(value)
        got = frame({name: v.requires_grad_(True) for name, v in staged.items()}, camera)
    torch.cuda.synchronize()
    image, alpha, grads = got
    assert torch.equal(image, want[0]) and torch.equal(alpha, want[1])
    for name in NAMES:  # sums by atomics, in another order: equal to rounding (a kernel on another
        # stream would have read zeros: gradients wrong by their own size)
        scale = float(want[2][name].abs().max())
        assert torch.allclose(grads[name], want[2][name], rtol=1e-5, atol=1e-5 * scale), name
