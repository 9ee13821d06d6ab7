"""tomgs.render.captured.FrameGraph: frames replayed from CUDA graphs (issued from Python on a CPU) render and
differentiate what `rasterize` does, one frame at a time, and never hand out memory a later frame
overwrites without saying so."""

from __future__ import annotations

import gc
import math
import weakref

import pytest
import torch

import tomgs
from tomgs.render import frame as render
from tomgs.render.captured import FrameGraph
from tomgs.render.inputs import RenderError
from scenes import devices, random_scene

DEVICES = devices()
NAMES = ("means", "quats", "scales", "opacities", "colors", "t_means", "t_scales")
COUNTS = ("n_visible", "n_alive", "n_intersections")


def cloud_on(device: str, seed: int = 4, n: int = 400, width: int = 45, height: int = 37, sh_degree=None,
             dtype=torch.float32):
    """(leaf tensors of `dtype` requiring grad, another copy of them, cameras [(viewmat, K, t)], background)."""
    scene = random_scene(seed, n=n, width=width, height=height, sh_degree=sh_degree)
    cloud = {name: scene[name].float().to(device, dtype).requires_grad_() for name in NAMES}
    twin = {name: tensor.detach().clone().requires_grad_() for name, tensor in cloud.items()}
    viewmat, K = scene["viewmat"].float().to(device), scene["K"].float().to(device)
    turned = viewmat.clone()
    turned[0, 3] += 0.05  # a second camera: the graph reads each call's
    # the second time is not a float32: its low part (t_lo) must reach the kernels too
    frames = [(viewmat, K, 0.5), (turned, K * 1.02, 0.3 + 1e-9), (viewmat, K, 0.7)]
    return cloud, twin, frames, scene["background"].float().to(device)


def weights(device: str, width: int = 45, height: int = 37, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(height, width, 3, generator=g).to(device), torch.rand(height, width, 1, generator=g).to(device))


def assert_close(got: torch.Tensor, want: torch.Tensor, device: str, gradient: bool = False):
    if device == "cpu":  # the same kernels on the same inputs, in one thread: bit for bit
        assert torch.equal(got, want)
    elif gradient:  # atomics add in no fixed order: the oracle's gradient tolerance
        torch.testing.assert_close(got, want, rtol=1e-3, atol=1e-3 * float(want.abs().max()))
    else:
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)


def assert_kept_or_refused(next_frame, held: torch.Tensor, message: str, device: str):
    """`next_frame()` leaves `held` as it was, or refuses with `message` (a captured graph, which writes
    its frames in its own memory): never overwrites it."""
    kept = held.clone()
    try:
        next_frame()
    except RenderError as error:
        assert device != "cpu" and message in str(error)
    assert torch.equal(held, kept)


@pytest.mark.parametrize("sh_degree, dtype", [(None, torch.float32), (1, torch.float32), (None, torch.float64)])
@pytest.mark.parametrize("device", DEVICES)
def test_replayed_frames_render_and_differentiate_as_rasterize(device, sh_degree, dtype, fresh_bounds):
    """float64 clouds are rendered in float32 (cast inside the graph), their gradients float64."""
    cloud, twin, frames, background = cloud_on(device, sh_degree=sh_degree, dtype=dtype)
    w_image, w_alpha = weights(device)
    graph = FrameGraph(**cloud, width=45, height=37, background=background)
    for viewmat, K, t in frames:
        image, alpha, counts = graph(viewmat, K, t)
        (image * w_image).sum().add((alpha * w_alpha).sum()).backward()
        want, want_alpha, meta = tomgs.rasterize(**twin, viewmat=viewmat, K=K, width=45, height=37, t=t,
                                                 background=background)
        (want * w_image).sum().add((want_alpha * w_alpha).sum()).backward()
        assert not counts.overflowed
        assert counts.read() == {k: meta[k] for k in COUNTS} and meta["n_intersections"] > 0
        assert_close(image, want, device)
        assert_close(alpha, want_alpha, device)
        for name in NAMES:  # summed over the frames on both sides: a later frame adds, never overwrites
            assert_close(cloud[name].grad, twin[name].grad, device, gradient=True)


@pytest.mark.parametrize("device", DEVICES)
def test_images_are_the_callers(device, fresh_bounds):
    cloud, twin, frames, _ = cloud_on(device)
    graph = FrameGraph(**{k: v.detach() for k, v in cloud.items()}, width=45, height=37)
    kept = [graph(*frame)[0] for frame in frames]  # no gradients: frames follow one another freely
    for image, (viewmat, K, t) in zip(kept, frames):
        want = tomgs.rasterize(**twin, viewmat=viewmat, K=K, width=45, height=37, t=t)[0]
        assert_close(image, want, device)
    assert not torch.equal(kept[0], kept[1])


@pytest.mark.parametrize("device", DEVICES)
def test_a_view_of_a_held_image_is_refused_not_overwritten(device, fresh_bounds):
    cloud, _, frames, _ = cloud_on(device)
    graph = FrameGraph(**{k: v.detach() for k, v in cloud.items()}, width=45, height=37)
    corner = graph(*frames[0])[0][:5, :5]  # a view, not the image handed out
    assert_kept_or_refused(lambda: graph(*frames[1]), corner, "a view of the last frame's image is still held",
                           device)


@pytest.mark.parametrize("device", DEVICES)
def test_one_frame_at_a_time(device, fresh_bounds):
    cloud, _, frames, _ = cloud_on(device)
    graph = FrameGraph(**cloud, width=45, height=37)
    image, alpha, _ = graph(*frames[0])
    with pytest.raises(RenderError, match="one frame at a time"):
        graph(*frames[1])  # the first frame's backward would read what this one writes
    del image, alpha  # dropped without a backward: the next frame may come
    image, _, _ = graph(*frames[1])
    image.sum().backward()
    with torch.no_grad():
        graph(*frames[2])


@pytest.mark.parametrize("device", DEVICES)
def test_a_held_gradient_is_refused_not_overwritten(device, fresh_bounds):
    cloud, _, frames, _ = cloud_on(device)
    graph = FrameGraph(**cloud, width=45, height=37)
    graph(*frames[0])[0].sum().backward()
    held = cloud["means"].grad
    for tensor in cloud.values():
        tensor.grad = None
    assert_kept_or_refused(lambda: graph(*frames[1])[0].sum().backward(), held, "gradient of means is still held",
                           device)


def graph_at_bound(device: str, bounds, total: int):
    """(cloud, twin, its FrameGraph, a frame) with the bound of the graph's size set by one frame of `total`
    intersections (the cloud's frames have ~1000)."""
    cloud, twin, frames, _ = cloud_on(device)
    graph = FrameGraph(**cloud, width=45, height=37)
    bounds.remember(graph._frame, total)
    return cloud, twin, graph, frames[0]


@pytest.mark.parametrize("device", DEVICES)
def test_a_frame_past_its_keys_renders_again_at_a_grown_bound(device, fresh_bounds):
    _, twin, graph, (viewmat, K, t) = graph_at_bound(device, fresh_bounds, 1)  # far below its ~1000
    image, alpha, counts = graph(viewmat, K, t)
    assert counts.overflowed and graph.capacity < counts.read()["n_intersections"]
    del image, alpha
    image, _, counts = graph(viewmat, K, t)
    assert not counts.overflowed and graph.capacity > counts.read()["n_intersections"]
    assert_close(image, tomgs.rasterize(**twin, viewmat=viewmat, K=K, width=45, height=37, t=t)[0], device)


@pytest.mark.parametrize("device", DEVICES)
def test_keys_grow_after_any_frame_read_past_them(device, fresh_bounds):
    """A caller that reads a frame's counts after issuing the next (a pipeline) finds the next call
    grown, though the frame before it was not read."""
    cloud, twin, frames, _ = cloud_on(device)
    still = {name: tensor.detach() for name, tensor in cloud.items()}  # no backward owed between frames
    graph = FrameGraph(**still, width=45, height=37)
    fresh_bounds.remember(graph._frame, 1)  # far below the frames' ~1000
    image, _, first = graph(*frames[0])
    del image
    image, _, second = graph(*frames[1])
    assert first.overflowed and second.known() is None
    del image
    image, _, again = graph(*frames[0])
    assert not again.overflowed and graph.capacity > first.read()["n_intersections"]
    viewmat, K, t = frames[0]
    assert_close(image, tomgs.rasterize(**twin, viewmat=viewmat, K=K, width=45, height=37, t=t)[0], device)


@pytest.mark.parametrize("device", DEVICES)
def test_keys_every_frame_fits_are_not_captured_again(device, fresh_bounds):
    """Totals that spread raise the bound by its headroom; while no frame is past the keys, the graph
    keeps them (each capture costs two eager frames and the capture itself)."""
    cloud, twin, graph, (viewmat, K, t) = graph_at_bound(device, fresh_bounds, 5_000)  # above its ~1000
    for _ in range(2):
        image, alpha, counts = graph(viewmat, K, t)
        (image.sum() + alpha.sum()).backward()
        held = graph.capacity
        assert counts.read()["n_intersections"] < 2_000 < 5_000 < held
        for tensor in cloud.values():
            tensor.grad = None
    # [5000, ~1000, ~1000] spread the bound past the keys; none of the frames was past them
    assert fresh_bounds.capacity(graph._frame) > held and graph.capacity == held
    assert_close(image, tomgs.rasterize(**twin, viewmat=viewmat, K=K, width=45, height=37, t=t)[0], device)


@pytest.mark.parametrize("device", DEVICES)
def test_the_keys_shrink_with_the_bound(device, fresh_bounds):
    cloud, twin, graph, (viewmat, K, t) = graph_at_bound(device, fresh_bounds, 100_000)  # far above its ~1000
    for _ in range(render.KeyBounds.FRAMES + 1):  # until the large total has left the bound's frames
        first = graph.capacity
        image, alpha, counts = graph(viewmat, K, t)
        (image.sum() + alpha.sum()).backward()
        counts.read()
    assert first > 100_000 and graph.capacity < 2_000  # the padded sort sorts what the capacity holds
    for tensor in cloud.values():
        tensor.grad = None
    image, _, counts = graph(viewmat, K, t)
    image.sum().backward()
    want = tomgs.rasterize(**twin, viewmat=viewmat, K=K, width=45, height=37, t=t)[0]
    want.sum().backward()
    assert not counts.overflowed and graph.capacity == fresh_bounds.capacity(graph._frame)
    assert_close(image, want, device)
    for name in NAMES:
        assert_close(cloud[name].grad, twin[name].grad, device, gradient=True)


@pytest.mark.parametrize("device", DEVICES)
def test_keys_made_not_to_shrink_only_grow(device, fresh_bounds):
    """shrink_keys False (a clip renderer's): the capacity of a frame far above the others is kept once
    the bound has fallen, and grows past a larger frame; it captures at those two changes only."""
    cloud, _, frames, _ = cloud_on(device)
    still = {name: tensor.detach() for name, tensor in cloud.items()}
    graph = FrameGraph(**still, width=45, height=37, shrink_keys=False)
    fresh_bounds.remember(graph._frame, 5_000)  # far above the frames' ~1000
    for _ in range(render.KeyBounds.FRAMES + 1):
        image, _, counts = graph(*frames[0])
        assert not counts.overflowed
    assert graph.capacity > 5_000 and fresh_bounds.capacity(graph._frame) < 2_000 and graph.captures == 1
    fresh_bounds.remember(graph._frame, 20_000)
    graph(*frames[0])
    assert graph.capacity > 20_000 and graph.captures == 2


@pytest.mark.parametrize("device", DEVICES)
def test_a_graph_goes_with_its_last_reference(device, fresh_bounds):
    """A FrameGraph (its CUDA graphs and their memory) is freed when the last reference to it goes, not
    at a later garbage collection: one that destroys a graph while another is being captured spoils
    that capture."""
    cloud, _, frames, _ = cloud_on(device)
    graph = FrameGraph(**cloud, width=45, height=37)
    image, alpha, counts = graph(*frames[0])
    (image.sum() + alpha.sum()).backward()
    counts.read()
    gone = weakref.ref(graph)
    gc.disable()
    try:
        del graph, image, alpha, counts
        assert gone() is None
    finally:
        gc.enable()


@pytest.mark.parametrize("device", DEVICES)
def test_a_cloud_given_new_memory_is_refused_not_rendered_stale(device, fresh_bounds):
    cloud, twin, frames, _ = cloud_on(device)
    graph = FrameGraph(**cloud, width=45, height=37)
    graph(*frames[0])[0].sum().backward()
    with torch.no_grad():
        for tensor in (cloud["means"], twin["means"]):
            tensor.add_(0.01)  # in place: the graph reads it
    viewmat, K, t = frames[1]
    image = graph(viewmat, K, t)[0]
    assert_close(image, tomgs.rasterize(**twin, viewmat=viewmat, K=K, width=45, height=37, t=t)[0], device)
    image.sum().backward()
    cloud["scales"].data = cloud["scales"].data * 2  # new memory: the graph would read the old
    with pytest.raises(RenderError, match="scales changed memory or shape"):
        graph(*frames[2])


@pytest.mark.parametrize("device", DEVICES)
def test_bad_input_is_refused(device, fresh_bounds):
    cloud, _, frames, _ = cloud_on(device)
    viewmat, K, t = frames[0]
    with pytest.raises(RenderError, match="means must have shape"):
        FrameGraph(**dict(cloud, means=cloud["means"][:, :2]), width=45, height=37)
    with pytest.raises(RenderError, match="width must be a positive integer"):
        FrameGraph(**cloud, width=0, height=37)
    graph = FrameGraph(**cloud, width=45, height=37)
    with pytest.raises(RenderError, match="viewmat must be a floating-point tensor of shape"):
        graph(viewmat[:3], K, t)
    with pytest.raises(RenderError, match="K must be a floating-point tensor"):
        graph(viewmat, K.int(), t)
    with pytest.raises(RenderError, match="t must be a finite time"):
        graph(viewmat, K, math.nan)
    graph(viewmat, K, t)[0].sum().backward()  # a good frame first: the graph is captured
    bad = K.clone()
    bad[0, 0] = math.inf
    image, alpha, counts = graph(viewmat, bad, t)
    with pytest.raises(RenderError, match="K must be finite"):
        counts.read()
    del image, alpha
    image, _, counts = graph(viewmat, K, t)  # and it goes on rendering good frames
    assert counts.read()["n_intersections"] > 0 and image.abs().sum() > 0


@pytest.mark.skipif(not torch.cuda.is_available() or torch.cuda.device_count() < 2, reason="needs two GPUs")
def test_a_graph_on_a_second_gpu_captures_and_renders_there(fresh_bounds):
    assert torch.cuda.current_device() == 0  # the cloud is elsewhere: the graph must not follow the current device
    cloud, twin, frames, _ = cloud_on("cuda:1")
    graph = FrameGraph(**cloud, width=45, height=37)
    for viewmat, K, t in frames:
        image, alpha, counts = graph(viewmat, K, t)
        (image.sum() + alpha.sum()).backward()
        want, want_alpha, _ = tomgs.rasterize(**twin, viewmat=viewmat, K=K, width=45, height=37, t=t)
        (want.sum() + want_alpha.sum()).backward()
        assert image.device == torch.device("cuda:1") and not counts.overflowed
        assert_close(image, want, "cuda:1")
        for name in NAMES:
            assert_close(cloud[name].grad, twin[name].grad, "cuda:1", gradient=True)


def rows_of(n: int, share: float, seed: int) -> torch.Tensor:
    """Ascending int64 rows, about `share` of n, as an alive index lists them."""
    g = torch.Generator().manual_seed(seed)
    return torch.nonzero(torch.rand(n, generator=g) < share)[:, 0]


@pytest.mark.parametrize("device", DEVICES)
def test_frames_of_rows_render_as_rasterize_of_those_rows(device, fresh_bounds):
    """A graph made with rows_capacity renders each call's rows as `rasterize(rows=)` does: fewer rows
    than the last call (the buffer's tail then holds the last call's, which must not be drawn), and
    more than it holds (it captures again with room for them)."""
    cloud, _, frames, background = cloud_on(device)
    cloud = {name: tensor.detach() for name, tensor in cloud.items()}
    n = cloud["means"].shape[0]
    calls = [(frames[0], rows_of(n, 0.5, 1)), (frames[1], rows_of(n, 0.2, 2)), (frames[2], rows_of(n, 0.9, 3)),
             (frames[0], rows_of(n, 0.05, 4))]
    graph = FrameGraph(**cloud, width=45, height=37, background=background, rows_capacity=len(calls[0][1]))
    for (viewmat, K, t), rows in calls:
        image, alpha, counts = graph(viewmat, K, t, rows=rows.to(device))
        want, want_alpha, meta = tomgs.rasterize(**cloud, viewmat=viewmat, K=K, width=45, height=37, t=t,
                                                 background=background, rows=rows.to(device))
        assert not counts.overflowed
        assert counts.read() == {k: meta[k] for k in COUNTS} and meta["n_intersections"] > 0
        assert_close(image, want, device)
        assert_close(alpha, want_alpha, device)
    assert graph.rows_capacity == len(calls[2][1])
    # every row, and a row of its own: both as rasterize gives them
    for rows in (torch.arange(n), torch.tensor([7])):
        image, _, _ = graph(*frames[1], rows=rows.to(device))
        want, _, _ = tomgs.rasterize(**cloud, viewmat=frames[1][0], K=frames[1][1], width=45, height=37,
                                     t=frames[1][2], background=background, rows=rows.to(device))
        assert_close(image, want, device)


@pytest.mark.parametrize("device", DEVICES)
def test_rows_a_graph_cannot_render_are_refused(device, fresh_bounds):
    cloud, _, frames, _ = cloud_on(device)
    with pytest.raises(RenderError, match="renders only"):
        FrameGraph(**cloud, width=45, height=37, rows_capacity=10)  # the cloud requires grad
    cloud = {name: tensor.detach() for name, tensor in cloud.items()}
    with pytest.raises(RenderError, match="rows_capacity to pass rows"):
        FrameGraph(**cloud, width=45, height=37)(*frames[0], rows=torch.arange(5, device=device))
    graph = FrameGraph(**cloud, width=45, height=37, rows_capacity=10)
    with pytest.raises(RenderError, match="pass the rows"):
        graph(*frames[0])
    with pytest.raises(RenderError, match="rows must be an integer tensor"):
        graph(*frames[0], rows=torch.ones(3, device=device))
    with pytest.raises(RenderError, match=r"rows must index the 400 Gaussians .*: 1 of 2 do not.* \(400\)"):
        graph(*frames[0], rows=torch.tensor([3, 400], device=device))[2].read()  # N = 400
    image, _, counts = graph(*frames[0], rows=torch.tensor([3, 5], device=device))  # and it renders on
    want, _, _ = tomgs.rasterize(**cloud, viewmat=frames[0][0], K=frames[0][1], width=45, height=37, t=frames[0][2],
                                 rows=torch.tensor([3, 5], device=device))
    assert counts.read()["n_alive"] <= 2
    assert_close(image, want, device)
