"""tomgs.render.sequence: a ClipRenderer replaying its captured frame over its alive index's rows renders what
render_sequence renders frame by frame, keeps its index and capture between calls, and renders a
frame that overflowed its keys again."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import tomgs
from tomgs.render import alive
from tomgs.cameras import Cameras
from tomgs.constants import ALPHA_MIN
from tomgs.render.frame import render_frame
from tomgs.render.sequence import SEQUENCE_FRAMES, ClipRenderer, render_sequence
from scenes import devices, random_scene

DEVICES = devices()
COUNTS = ("n_visible", "n_alive", "n_intersections")


def short_lived_clip(device: str, frames: int = SEQUENCE_FRAMES + 8, n: int = 300):
    """(gaussians, cameras, viewmat, K): n Gaussians alive for 0.1-100% of a 40x30 clip, one only at
    the instant of frame 12."""
    scene = random_scene(11, n=n, width=40, height=30)
    g = torch.Generator().manual_seed(3)
    n = scene["means"].shape[0]
    gaussians = {k: scene[k].float().to(device) for k in ("means", "quats", "scales", "opacities", "colors")}
    gaussians["t_means"] = torch.rand(n, generator=g).to(device)
    gaussians["t_scales"] = (10.0 ** (-3 + 3 * torch.rand(n, generator=g))).to(device)
    gaussians["opacities"][0] = ALPHA_MIN
    gaussians["t_means"][0] = 12 / (frames - 1)
    viewmat = scene["viewmat"].numpy()
    cams = Cameras.create(np.repeat(np.linalg.inv(viewmat)[None], frames, 0), scene["K"].numpy(), 40, 30)
    return gaussians, cams, scene["viewmat"].float().to(device), scene["K"].float().to(device)


def assert_same_image(got: torch.Tensor, want: torch.Tensor, device: str):
    if device == "cpu":  # the same kernels on the same inputs, in one thread: bit for bit
        assert torch.equal(got, want)
    else:
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("device", DEVICES)
def test_a_clip_renderer_replays_what_rasterize_renders(device, fresh_bounds):
    """Two passes of a renderer replaying its frame (made with rows as long as its longest bucket), in
    the order a viewer scrubs: each image is rasterize's of every Gaussian, the counts its counts."""
    gaussians, cams, viewmat, K = short_lived_clip(device)
    renderer = ClipRenderer(gaussians, cams, background=(0.1, 0.2, 0.3), replay=True)
    frames = list(range(len(cams)))[::-1]
    background = torch.tensor([0.1, 0.2, 0.3], device=device)
    made = []  # (index, graph) after each pass
    for _ in range(2):
        for k, image, meta in renderer.frames(frames, to_cpu=False):
            full, _, full_meta = tomgs.rasterize(**gaussians, viewmat=viewmat, K=K, width=40, height=30,
                                                 t=float(cams.times[k]), background=background)
            assert_same_image(image, full.clamp(0, 1), device)
            assert {key: meta[key] for key in COUNTS} == {key: full_meta[key] for key in COUNTS}
            assert meta["rows"] is not None and len(meta["rows"]) < 300
        made.append((renderer.index, renderer.graph))
    (index, graph), (index_after, graph_after) = made
    assert index_after is index and graph_after is graph  # made once, kept
    assert 0 < graph.rows_capacity == index.most_rows < index.n


@pytest.mark.parametrize("device", DEVICES)
def test_a_frame_past_its_keys_is_rendered_again(device, fresh_bounds, monkeypatch):
    """The bound of this size set far below the clip's frames (~1700 intersections): the replayed frame
    lacks some, and comes out as rasterize's all the same, rendered again waiting for its counts."""
    from tomgs.render import sequence

    gaussians, cams, viewmat, K = short_lived_clip(device, n=3000)
    renderer = ClipRenderer(gaussians, cams, replay=True)
    waited = []
    monkeypatch.setattr(sequence, "render_frame", lambda **kw: waited.append(kw["defer"]) or render_frame(**kw))
    fresh_bounds.remember(_frame_of(renderer), 1)
    (k, image, got), = renderer.frames([5], to_cpu=False)
    full, _, meta = tomgs.rasterize(**gaussians, viewmat=viewmat, K=K, width=40, height=30, t=float(cams.times[5]))
    assert_same_image(image, full.clamp(0, 1), device)
    assert got["n_intersections"] == meta["n_intersections"] > 1000
    assert waited == [False]  # the frame rendered again, from Python, waiting


def _frame_of(renderer: ClipRenderer):
    """A Frame of the renderer's size (whose bound its frames share)."""
    from tomgs.render.frame import Frame
    from tomgs.runtime import scope

    with scope(renderer.device) as wp_device:
        return Frame(renderer.cameras.width, renderer.cameras.height, 0.0, 0.0, 0.01, 1e10, wp_device)


@pytest.mark.parametrize("device", DEVICES)
def test_render_sequence_indexes_and_replays_where_it_pays(device):
    """A fixed cloud's sequence of SEQUENCE_FRAMES frames renders from its index (rows fewer than N) on
    every device, and a per-frame cloud (a callable) renders the same images."""
    gaussians, cams, _, _ = short_lived_clip(device)
    fixed = list(render_sequence(gaussians, cams, to_cpu=False))
    per_frame = list(render_sequence(lambda k: gaussians, cams, to_cpu=False))
    assert alive.pays_for_sequence(device, len(cams))
    assert all(meta["rows"] is not None for _, _, meta in fixed)
    for (k, image, meta), (k2, image2, meta2) in zip(fixed, per_frame):
        assert k == k2 and meta["n_alive"] == meta2["n_alive"]
        assert_same_image(image, image2, device)


@pytest.mark.parametrize("device", DEVICES)
def test_frames_outside_the_index_render_every_gaussian(device, fresh_bounds):
    """A renderer indexed over some frames renders the others from every Gaussian (rows None), through
    its captured frame or not, as rasterize does."""
    gaussians, cams, viewmat, K = short_lived_clip(device)
    renderer = ClipRenderer(gaussians, cams, indexed=range(0, 20), alive_index=True, replay=True)
    for k, image, meta in renderer.frames([3, 30, 5, 39], to_cpu=False):
        full, _, _ = tomgs.rasterize(**gaussians, viewmat=viewmat, K=K, width=40, height=30, t=float(cams.times[k]))
        assert_same_image(image, full.clamp(0, 1), device)
        assert (meta["rows"] is None) == (k >= 20)
    assert renderer.index.n == 300 and len(renderer.index.bucket_of) == 20
