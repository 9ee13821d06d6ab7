"""A clip's frames, rendered: `render_sequence` (the frames of a cloud, or of a cloud per frame) and
`ClipRenderer`, which keeps what makes a fixed cloud's frames cheap from one call to the next.

A fixed cloud's frame on a GPU costs the host more than its kernels take on a light clip (~20 torch
ops and ~10 launches issued from Python, ~1 ms a frame): a `ClipRenderer` renders each frame from its
alive index's rows (tomgs.render.alive: the Gaussians that may be alive then) through one captured frame
(tomgs.render.captured.FrameGraph), so the host only writes the camera, the time and the rows and replays.
The index costs ~7 ms to build and pays from SEQUENCE_FRAMES frames of a call; the capture costs
~10 ms and saves what the host adds to a frame (0.13 ms on a light fitted clip, 0.02 ms on a heavy
one, whose frames the kernels pace), so a renderer captures once it has rendered REPLAY_FRAMES frames
in all: a long call's, or those of a `ClipRenderer` the caller keeps and renders from again.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Callable, Iterator

import torch

from tomgs.render import alive
from tomgs.render.frame import FrameCounts, render_frame

NAMES = ("means", "quats", "scales", "opacities", "colors", "t_means", "t_scales")
COUNT_KEYS = ("n_visible", "n_alive", "n_intersections")
# frames of a call from which the alive index pays for its build (tomgs.render.alive.pays_for_sequence)
SEQUENCE_FRAMES = alive.SEQUENCE_FRAMES
# frames a renderer renders, over all its calls, from which it captures its frame. Measured on the H100
# (benchmarks/render_speed.py, 1-minute fits): a capture made within a call of kite-surf's 50
# frames took it from 923 to 828 fps and camel's 90 from 698 to 583, while captured frames ran 0.13 ms
# (kite-surf: 1179 against 1022 fps) and 0.03 ms (camel: 752 against 733) quicker than frames issued from
# Python: the capture pays on a light clip from ~100 frames, on a heavy one from several hundred.
REPLAY_FRAMES = 128


def render_sequence(gaussians, cameras, indices=None, *, background=None, device=None, to_cpu: bool = True,
                    pipelined: bool | None = None, alive_index: bool | None = None):
    """Yield (frame k, image [H,W,3] float32 in [0,1], meta) for frames `indices` of `cameras`.

    `gaussians`: mapping with means, quats, scales, opacities, colors (RGB or SH), t_means,
    t_scales; or a callable k -> such a mapping, a per-frame cloud (an edit over time, a simulated
    shot). `cameras`: a `tomgs.Cameras`; frame k renders at t = cameras.times[k]. No gradients.
    A fixed cloud renders through a `ClipRenderer` made for this call (see there: its alive index,
    and on a GPU its captured frame, from REPLAY_FRAMES frames); keep one yourself to render a clip
    more than once. With `alive_index` (None: where it pays, tomgs.render.alive.pays_for_sequence) only the
    Gaussians that may be alive at a frame's time are rendered. `meta`: the frame's counts
    (n_visible, n_alive, n_intersections) and meta['rows'], the Gaussians rendered (int [M]; None:
    all). Images come back on the CPU unless `to_cpu` is False.

    `pipelined` (None: on a GPU): a frame does not wait for its counts (`render_frame(defer=True)`); they
    are read after the next frame has been issued, so the device renders while the host prepares
    (a callable `gaussians` is then called for frame k+1 before frame k is yielded). A frame that
    needed more intersections than recent ones is rendered again, waiting, before it is yielded.
    """
    order = list(range(len(cameras)) if indices is None else indices)
    if not callable(gaussians):
        if order:
            renderer = ClipRenderer(gaussians, cameras, background=background, device=device,
                                    alive_index=alive_index, indexed=order)
            yield from renderer.frames(order, to_cpu=to_cpu, pipelined=pipelined)
        return
    views = {}  # cameras and background on each device a frame lands on (one, in practice)

    @torch.no_grad()  # inside a helper: a no_grad block around `yield` would leak into the caller
    def issue(position: int, k: int, wait: bool) -> IssuedFrame:
        g = gaussians(k)
        dev = torch.device(device) if device is not None else g["means"].device
        g = {name: g[name].detach().to(dev) for name in NAMES}
        t = float(cameras.times[k])
        use = alive.pays_for_sequence(dev, 1) if alive_index is None else alive_index
        rows = alive.index_of(g["opacities"], g["t_means"], g["t_scales"], [t]).rows(0) if use else None
        if dev not in views:
            views[dev] = _views(cameras, background, dev)
        viewmats, Ks, bg = views[dev]
        defer = not wait and (dev.type == "cuda" if pipelined is None else pipelined)
        image, _, meta, counts = render_frame(**g, viewmat=viewmats[k], K=Ks[k], width=cameras.width,
                                              height=cameras.height, t=t, background=bg, rows=rows, defer=defer)
        return IssuedFrame.of(position, k, image, _sequence_meta(meta, rows), counts, to_cpu)

    yield from issue_in_order(order, issue)


class ClipRenderer:
    """A fixed cloud's frames along a clip's cameras, as often as asked (`frames`), keeping what makes
    them cheap between calls: its alive index over the clip's frames (tomgs.render.alive; `indexed`: over those
    frames only, the others then render every Gaussian), built at the first call of enough frames to pay
    for it, and on a GPU its frame captured (tomgs.render.captured.FrameGraph,
    rendering each frame's index rows through a buffer as long as the longest), made at the pipelined
    call that takes the frames it has rendered to REPLAY_FRAMES (`replay` True: at the first call, on a
    CPU too, where the frames are issued from Python all the same; False: never).

    The cloud is read in place, and what the index lists depends on it: after changing the cloud
    (opacities, t_means or t_scales above all), make a new ClipRenderer.

        renderer = ClipRenderer(scene.model.render_inputs(), scene.cameras)
        for k, image, meta in renderer.frames(range(0, 80)): ...
    """

    def __init__(self, gaussians, cameras, *, background=None, device=None, alive_index: bool | None = None,
                 replay: bool | None = None, indexed=None):
        dev = torch.device(device) if device is not None else gaussians["means"].device
        self.gaussians = {name: gaussians[name].detach().to(dev) for name in NAMES}
        self.cameras, self.device = cameras, dev
        self.viewmats, self.Ks, self.background = _views(cameras, background, dev)
        self._alive_index, self._replay = alive_index, replay
        self.index: alive.AliveIndex | None = None  # over the frames `indexed`, once built
        self._indexed = list(range(len(cameras)) if indexed is None else indexed)
        self._position = {k: position for position, k in enumerate(self._indexed)}  # a frame's in the index
        self.graph = None  # the captured frame (tomgs.render.captured.FrameGraph), once made
        self.rendered = 0  # frames asked of it so far, this call's included

    def frames(self, indices=None, *, to_cpu: bool = True, pipelined: bool | None = None) -> Iterator[tuple]:
        """Yield (k, image, meta) for frames `indices` (None: all), as `render_sequence` does."""
        order = list(range(len(self.cameras)) if indices is None else indices)
        if not order:
            return iter(())
        pipelined = self.device.type == "cuda" if pipelined is None else pipelined
        self.rendered += len(order)
        index = self._index_for(len(order))
        graph = self._graph_for(pipelined, index)
        g, cams = self.gaussians, self.cameras

        @torch.no_grad()  # inside a helper: a no_grad block around `yield` would leak into the caller
        def issue(position: int, k: int, wait: bool) -> IssuedFrame:
            t = float(cams.times[k])
            rows = None if index is None or k not in self._position else index.rows(self._position[k])
            if graph is not None and not wait and (rows is not None or not graph.rows_capacity):
                image, _, counts = graph(self.viewmats[k], self.Ks[k], t, rows=rows if graph.rows_capacity else None)
                meta = {"rows": rows}
            else:  # issued from Python (a frame rendered again, waiting for its counts, included)
                image, _, meta, counts = render_frame(**g, viewmat=self.viewmats[k], K=self.Ks[k], width=cams.width,
                                                      height=cams.height, t=t, background=self.background,
                                                      rows=rows, defer=pipelined and not wait)
                meta = _sequence_meta(meta, rows)
            return IssuedFrame.of(position, k, image, meta, counts, to_cpu)

        return issue_in_order(order, issue)

    def _index_for(self, frames: int) -> alive.AliveIndex | None:
        """The index this call renders from (built now where it pays), or None: every Gaussian."""
        if self._alive_index is False:
            return None
        if self.index is None and (self._alive_index or alive.pays_for_sequence(self.device, frames)):
            g = self.gaussians
            times = [float(self.cameras.times[k]) for k in self._indexed]
            self.index = alive.index_of(g["opacities"], g["t_means"], g["t_scales"], times)
        return self.index

    def _graph_for(self, pipelined: bool, index: alive.AliveIndex | None):
        """The captured frame for this call (made now where it pays), or None: frames issued from Python.
        It renders the index's rows where the index has one (no bucket lists every Gaussian)."""
        if self.graph is None:
            wanted = self._replay if self._replay is not None else (
                self.device.type == "cuda" and pipelined and self.rendered >= REPLAY_FRAMES)
            if not wanted:
                return None
            from tomgs.render.captured import FrameGraph  # it imports tomgs.render, as this module does

            rows = 0 if index is None or index.most_rows >= index.n else index.most_rows
            self.graph = FrameGraph(**self.gaussians, width=self.cameras.width, height=self.cameras.height,
                                    background=self.background, rows_capacity=rows, shrink_keys=False)
        return self.graph if pipelined or self._replay else None


# ------------------------------------------------------------------------------------------ frame by frame

@dataclass
class IssuedFrame:
    """A frame queued on its device: what `_finish` needs to hand it over."""

    position: int
    k: int
    image: torch.Tensor  # `of` clamps it to [0, 1]; on the CPU once `copied` has passed, where asked
    meta: dict
    counts: FrameCounts | None  # None: the counts are in meta already
    copied: object  # a torch.cuda.Event after the image's copy to the host, or None

    @staticmethod
    def of(position: int, k: int, image: torch.Tensor, meta: dict, counts, to_cpu: bool) -> IssuedFrame:
        image = image.clamp(0.0, 1.0)
        copied = None
        if to_cpu and image.is_cuda and counts is not None:  # queued behind the frame; waited for in `_finish`
            image = image.to("cpu", non_blocking=True)
            copied = torch.cuda.Event()
            copied.record()
        elif to_cpu:
            image = image.cpu()
        return IssuedFrame(position, k, image, meta, counts, copied)


def issue_in_order(order: list, issue: Callable[[int, int, bool], IssuedFrame], ahead: int = 1) -> Iterator[tuple]:
    """(k, image, meta) of frames `order`, issued by issue(position, k, wait) without waiting; a frame whose
    counts are pending is yielded once `ahead` more frames have been issued (the device renders while the
    host waits), and one that overflowed its keys is issued again, waiting. Each frame in flight holds what
    it was issued with until then: `ahead` bounds that."""
    pending = deque()
    for position, k in enumerate(order):
        pending.append(issue(position, k, False))
        while len(pending) > ahead or (pending and pending[0].counts is None):
            yield _finish(pending.popleft(), issue)
    while pending:
        yield _finish(pending.popleft(), issue)


def _finish(issued: IssuedFrame, issue: Callable[[int, int, bool], IssuedFrame]) -> tuple:
    if issued.counts is not None:
        if issued.counts.overflowed:  # it lacked intersections: rendered again, waiting for its counts
            return _finish(issue(issued.position, issued.k, True), issue)
        issued.meta.update(issued.counts.read())
    if issued.copied is not None:
        issued.copied.synchronize()
    return issued.k, issued.image, issued.meta


def _sequence_meta(meta: dict, rows) -> dict:
    """What a sequence's frame tells: its counts (where known) and the rows it rendered."""
    return {"rows": rows, **{key: meta[key] for key in COUNT_KEYS if key in meta}}


def _views(cameras, background, device: torch.device) -> tuple:
    """(viewmats [T,4,4], Ks [T,3,3], background [3] or None) on `device`."""
    bg = None if background is None else torch.as_tensor(background, dtype=torch.float32, device=device)
    return cameras.viewmats(device), cameras.Ks(device), bg
