"""Frames replayed from CUDA graphs: `rasterize`'s forward and backward for one cloud and one image
size, captured once and replayed for any camera and time.

A frame issued from Python costs a GPU machine's CPU ~1 ms (~20 torch ops and ~10 launches at 10-60 us
each), more than the kernels of a 1M-Gaussian frame take, so such a frame is host bound. A captured
frame is one replay for the forward and one for the backward; the device runs the kernels back to back.

    graph = FrameGraph(means=..., quats=..., scales=..., opacities=..., colors=..., t_means=...,
                       t_scales=..., width=854, height=480)
    image, alpha, counts = graph(viewmat, K, t)    # differentiable in the cloud's tensors
    loss(image, alpha).backward()
    if counts.overflowed: ...                       # its image lacked entries: call again (recaptured)

Fixed at capture: the cloud's tensors, read in place at every replay (update them in place, as an
optimiser does; new tensors, a new N or other requires_grad flags need a new FrameGraph, and a tensor
given new memory, `.data =`, is refused at the next call), the image size, background, near and far,
and the capacity of the tile keys (tomgs.render's bound of recent frames of this size). Per call: the
camera and the time, written into device memory the graph reads (`project.set_frame`). The kernels are
`rasterize`'s: the same image and gradients (bit for bit on a CPU).

With `rows_capacity`, frames render the rows each call names (`rasterize(rows=)`: tomgs.render.alive's index
rows), copied into a buffer of that many the graph reads, past their count padding it culls; a call
naming more captures again with room for them. Such a graph renders only: its cloud takes no gradients.
With `shrink_keys` False the keys' capacity only grows (see `_fit_capacity`).

One frame at a time: a frame's backward runs before the next frame is rendered (a frame whose image
takes gradients and is still held raises RenderError at the next call). A frame's image, alpha and
gradients lie in the graph's memory (an eager frame's memory, without copies), so the next call
writes them again: before it does, an image or alpha the caller still holds, and a `.grad` still
holding the gradients, get copies of their own (gradients summed over frames stay right); a view
of them, or a gradient held elsewhere, raises RenderError rather than being overwritten.

On a CPU nothing is captured: each call issues the same frame from Python, with the same results.
"""

from __future__ import annotations

import contextlib
import gc
import weakref
from dataclasses import replace

import torch
import warp as wp

from tomgs.errors import RenderError
from tomgs.kernels import project
from tomgs.render import frame as frame_layer
from tomgs.render.frame import FrameCounts, check_scalars, check_time, issue_frame
from tomgs.render.stages import Frame
from tomgs.render.inputs import check_rows, prepare_inputs
from tomgs.runtime import NO_ARRAY, launch, scope, torch_stream, warp_device, wrap


def _storage_of(tensor: torch.Tensor) -> int:
    """The address of `tensor`'s storage, for `_use_count`: read once, when the tensor is captured (a
    storage object costs a GPU machine's host microseconds to build, at every check of every frame)."""
    return tensor.untyped_storage()._cdata


def _use_count(storage: int) -> int | None:
    """References to the storage at `storage` (`_storage_of` a tensor that keeps it alive: tensors viewing
    it), or None where torch does not say."""
    count = getattr(torch._C, "_storage_Use_Count", None)  # private to torch: checked, not relied on
    return None if count is None else count(storage)


class FrameGraph:
    """`rasterize` of one cloud at one image size, for any camera and time: captured as CUDA graphs
    (forward, and backward where a cloud tensor requires grad) on a GPU, issued from Python on a CPU.
    See the module docstring for what is fixed and what is shared."""

    def __init__(self, means, quats, scales, opacities, colors, t_means, t_scales, width: int, height: int, *,
                 background: torch.Tensor | None = None, near: float = 0.01, far: float = 1e10, rows_capacity: int = 0,
                 shrink_keys: bool = True):
        self.cloud = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
                          t_means=t_means, t_scales=t_scales)
        check_scalars(width, height, 0.0, near, far)
        device = means.device if isinstance(means, torch.Tensor) else torch.device("cpu")
        f32 = dict(device=device, dtype=torch.float32)
        if rows_capacity and any(isinstance(x, torch.Tensor) and x.requires_grad for x in self.cloud.values()):
            raise RenderError("a FrameGraph that renders rows (rows_capacity) renders only: pass the cloud detached")
        # the rows a frame renders (read in place by its kernels) and their count, set with its camera; the
        # buffer's tail keeps rows of [0, N) (zeros, or an earlier frame's), which the kernels never read
        self._rows = torch.zeros(int(rows_capacity), device=device, dtype=torch.int32) if rows_capacity > 0 else None
        self._row_count = torch.zeros(1 if rows_capacity > 0 else 0, device=device, dtype=torch.int32)
        # where each call writes its camera and time (set_frame) and the frame reads them; a camera
        # to check the cloud against until the first call's is written
        self._viewmat, self._K, self._times = torch.eye(4, **f32), torch.eye(3, **f32), torch.zeros(2, **f32)
        self._own_leaves()  # what a frame reads: leaves of its own, sharing the cloud's memory
        # what `_prepare` passes besides the leaves (kept apart from self: a graph holding a function of
        # itself would be freed by the garbage collector, at any time, not when its last reference goes)
        self._scalars = dict(width=width, height=height, t=0.0, background=background, near=near, far=far,
                             dtype=torch.float32, fused_sh=True, rows=self._rows)
        p = self._prepare()  # RenderError now for a cloud outside the contract's shapes and types
        self.width, self.height, self.device = p.width, p.height, device
        self.near, self.far = p.near, p.far
        self._frame = timed_frame(p.width, p.height, p.near, p.far, device, self._times, wrap(self._row_count))
        self._set_args = [wrap(self._viewmat, wp.mat44), wrap(self._K, wp.mat33), wrap(self._times)]
        self._params = [(name, tensor) for name, tensor in self.cloud.items() if tensor.requires_grad]
        self._param_tensors = tuple(tensor for _, tensor in self._params)
        self._storage = self._storage_of_cloud()  # what the frames read: checked at every call
        self._captured = device.type == "cuda"
        self.capacity = 0  # the tile keys a frame holds (0: none captured yet)
        self.captures = 0  # how many times it has taken a new capacity of keys or rows (captured, on a GPU)
        self._shrink_keys = shrink_keys
        self._graphs = None  # (forward, backward or None) once captured
        self._outputs = None  # (image, alpha, flags) of the captured forward, or of the last frame on a CPU
        # (storage, references to it while nothing else holds it) of the captured image and alpha
        self._output_refs = ()
        self._grads = None  # the captured backward's gradients, one per param (None: unused)
        self._handed_out = False  # a backward handed them out since `_release_grads` last found them free
        self._v = None  # (v_image, v_alpha): where the backward reads its incoming gradients
        self._in_flight = None  # a weak reference to the last frame's backward node until its backward ran
        self._handed = ()  # weak references to the last frame's image and alpha, as handed out

    # ---------------------------------------------------------------------------------------------- a frame

    @property
    def rows_capacity(self) -> int:
        """The rows a frame may render without a new capture (0: frames render the whole cloud)."""
        return 0 if self._rows is None else len(self._rows)

    def __call__(self, viewmat: torch.Tensor, K: torch.Tensor, t: float, rows: torch.Tensor | None = None):
        """(image [H,W,3], alpha [H,W,1], counts) of the cloud seen by `viewmat` [4,4] and `K` [3,3] at
        time t, as `rasterize` gives them (differentiable in the cloud's tensors that require grad);
        counts a tomgs.render.FrameCounts: read it (after the backward) before trusting the image.
        `rows` (int [M], made with rows_capacity, and then required): render those Gaussians only."""
        t_hi, t_lo = check_time(t)  # the size and planes were checked when it was made
        viewmat, K = self._camera(viewmat, "viewmat", (4, 4)), self._camera(K, "K", (3, 3))
        count = self._take_rows(rows)
        storage = self._storage_of_cloud()
        if storage != self._storage:
            changed = ", ".join(name for name, now, then in zip(self.cloud, storage, self._storage) if now != then)
            raise RenderError(f"the cloud's {changed} changed memory or shape since this FrameGraph was made (a "
                              "`.data =` or resize): frames read the memory it had; make a new FrameGraph")
        node = self._in_flight() if self._in_flight is not None else None
        if node is not None:
            raise RenderError("FrameGraph renders one frame at a time: run the last frame's backward (or drop its "
                              "image) before rendering the next")
        self._release_outputs()
        self._release_grads()
        with scope(self.device) as wp_device:
            frame = [wrap(viewmat, wp.mat44), wrap(K, wp.mat33), t_hi, t_lo, *self._set_args, count,
                     self._frame.row_count]  # set_frame's
            self._fit_capacity(wp_device, frame, count)
            image, alpha = _Replayed.apply(self, wp_device, frame, *self._param_tensors)
        if image.grad_fn is not None:
            self._in_flight = weakref.ref(image.grad_fn)
        if self._captured:
            self._handed = (weakref.ref(image), weakref.ref(alpha))
        p = self._p if self._rows is None else replace(self._p, rows=self._rows[:count])  # its errors name these
        counts = FrameCounts(self._outputs[2], p, self._frame, self.capacity)
        return image, alpha, counts

    def _storage_of_cloud(self) -> list[tuple]:
        """(address, shape, dtype) of each cloud tensor: in-place updates keep them, `.data =` does not."""
        return [(tensor.data_ptr(), tensor.shape, tensor.dtype) for tensor in self.cloud.values()]

    def _take_rows(self, rows) -> int:
        """`rows` copied into the buffer the frames read (grown, and captured again, to hold them): their count."""
        if self._rows is None:
            if rows is not None:
                raise RenderError("this FrameGraph renders the whole cloud: make it with rows_capacity to pass rows")
            return 0
        if rows is None:
            raise RenderError("this FrameGraph renders rows (made with rows_capacity): pass the rows of each frame")
        rows = check_rows(rows, self.device)
        if len(rows) > len(self._rows):  # the capture reads the old buffer: capture again for the new one
            self._rows = self._scalars["rows"] = torch.zeros(len(rows), device=self.device, dtype=torch.int32)
            self.capacity = 0
        self._rows[:len(rows)].copy_(rows)
        return len(rows)

    def _camera(self, value, name: str, shape: tuple) -> torch.Tensor:
        """A camera tensor as set_frame reads it: float32, contiguous, on the cloud's device."""
        if not isinstance(value, torch.Tensor) or value.shape != shape or not value.is_floating_point():
            got = f"{tuple(value.shape)} {value.dtype}" if isinstance(value, torch.Tensor) else type(value).__name__
            raise RenderError(f"{name} must be a floating-point tensor of shape {shape}, got {got}")
        if value.dtype == torch.float32 and value.device == self.device and value.is_contiguous():
            return value  # as a training loop passes it: `.to` and `.contiguous` would each cost host time
        return value.to(self.device, torch.float32).contiguous()

    def _fit_capacity(self, wp_device: str, frame: list, count: int) -> None:
        """The keys' capacity follows the bound of recent frames of this size (tomgs.render): taken at
        the first frame (which waits for its count where no frame of this size has been counted),
        grown to the bound once a recent frame was read past it (any frame, not only the last: a
        caller may read a frame's counts after issuing the next; not when only the bound's headroom
        passed it: frames whose totals spread would be captured again at each new spread), shrunk
        once it holds more than 1/16 above the bound (the padded sort costs what the capacity holds), unless
        made with shrink_keys False (a clip played again and again: its frames' totals rise and fall
        along it, and a capacity that followed them captured camel's 90 frames 9 times in 6 passes);
        captured again at each change (two eager frames and the capture: 7-12 ms on an H100 at
        854x480). `frame`: set_frame's arguments, for the frames run here; `count`: the frame's rows."""
        bound = frame_layer.key_bounds.capacity(self._frame)
        if self.capacity and frame_layer.key_bounds.largest(self._frame) <= self.capacity and (
                not self._shrink_keys or self.capacity <= bound + bound // 16):
            return
        launch(project.set_frame, 1, device=wp_device, args=frame)
        if not bound:  # a first frame of this size: counted (the bound learns it)
            with torch.no_grad():
                issue_frame(self._prepare(count), self._frame, 0, wait=True)
        self.capacity = frame_layer.key_bounds.capacity(self._frame)
        self.captures += 1
        if self._captured:
            with torch.cuda.device(self.device):  # torch.cuda.graph captures on the current device
                self._capture()

    # ------------------------------------------------------------------------------- capture and replay

    def _prepare(self, count: int | None = None):
        """The frame's inputs; with `count`, of the buffer's first `count` rows only (the rest is padding)."""
        scalars = self._scalars if count is None or self._rows is None else dict(self._scalars, rows=self._rows[:count])
        return prepare_inputs(**self._leaves, viewmat=self._viewmat, K=self._K, **scalars)

    def _issue(self):
        """The frame from the camera and time in device memory, issued: (image, alpha, flags)."""
        self._p = self._prepare()
        image, alpha, _, flags, _ = issue_frame(self._p, self._frame, self.capacity, wait=False, queue_counts=False)
        return image, alpha, flags

    def _own_leaves(self) -> None:
        """Frames read leaves of their own, sharing the cloud's memory: a captured autograd graph must not
        hold the cloud's own gradient accumulators (made on the caller's stream, which a capture could
        not then depend on), and the caller's backward reaches the cloud through `_Replayed` alone."""
        self._leaves = {name: tensor.detach().requires_grad_() if tensor.requires_grad else tensor
                        for name, tensor in self.cloud.items()}

    def _backward_of(self, outputs, v) -> tuple:
        leaves = [self._leaves[name] for name, _ in self._params]
        return torch.autograd.grad(outputs[:2], leaves, v, allow_unused=True)

    def _capture(self) -> None:
        """The forward and backward graphs at `capacity`, after two frames run eagerly on a side stream
        (Warp's modules loaded and launches recorded before capturing; the sort's scratch is the
        graph's, `known_to_warp`)."""
        # the last capture's memory goes back first (what a caller holds of it, the new graph never writes)
        self._graphs = self._outputs = self._grads = self._v = None
        self._output_refs = ()  # their storages may go with them
        self._handed_out = False
        self._handed = ()
        self._p = None
        h, w = self.height, self.width
        current = torch.cuda.current_stream(self.device)
        side = torch.cuda.Stream(self.device)  # the warm-up's and the captures' (torch's default is one device's)
        side.wait_stream(current)
        with torch.cuda.stream(side), torch.enable_grad():
            for _ in range(2):
                outputs = self._issue()
                if self._params:
                    self._backward_of(outputs, (torch.zeros_like(outputs[0]), torch.zeros_like(outputs[1])))
            del outputs
        current.wait_stream(side)
        # fresh leaves for the capture: the warm-up's gradient accumulators were made on the side
        # stream, and its last inputs (SH colours with their graph) would have kept them alive
        self._p = None
        self._own_leaves()
        # one pool: the backward reuses the forward's scratch (keys, scans), as an eager frame does, so
        # its gradients may lie where the next forward writes (`_release_grads` runs before both)
        pool = torch.cuda.graph_pool_handle()
        forward = torch.cuda.CUDAGraph()
        with no_collection(), torch.enable_grad(), torch.cuda.graph(forward, pool=pool, stream=side), \
                known_to_warp(self.device):
            self._outputs = self._issue()
        self._output_refs = [(storage, _use_count(storage)) for storage in map(_storage_of, self._outputs[:2])]
        backward = None
        if self._params:
            backward = torch.cuda.CUDAGraph()
            with no_collection(), torch.cuda.graph(backward, pool=pool, stream=side):
                # the incoming gradients' buffers come from the pool too, where the forward's scratch
                # (dead by then) may lie: written before each backward replay, as an eager frame's are
                self._v = (torch.empty(h, w, 3, device=self.device), torch.empty(h, w, 1, device=self.device))
                self._grads = self._backward_of(self._outputs, self._v)
            storages = [None if g is None else _storage_of(g) for g in self._grads]
            self._grad_refs = [None if storage is None else (storage, _use_count(storage)) for storage in storages]
        self._graphs = (forward, backward)

    def _run_forward(self, wp_device: str, frame: list) -> tuple[torch.Tensor, torch.Tensor]:
        launch(project.set_frame, 1, device=wp_device, args=frame)
        if self._captured:
            self._graphs[0].replay()
        else:
            with torch.enable_grad():
                self._outputs = self._issue()
        image, alpha, _ = self._outputs
        return image.detach(), alpha.detach()

    def _run_backward(self, v_image, v_alpha) -> list:
        if not self._captured:
            return list(self._backward_of(self._outputs, (self._zeros_for(v_image, 3), self._zeros_for(v_alpha, 1))))
        for buffer, v in zip(self._v, (v_image, v_alpha)):
            if v is None:
                buffer.zero_()
            else:
                buffer.copy_(v)
        self._release_grads()
        self._graphs[1].replay()
        self._handed_out = True
        return [None if g is None else g.detach() for g in self._grads]

    def _zeros_for(self, v, channels: int) -> torch.Tensor:
        return torch.zeros(self.height, self.width, channels, device=self.device) if v is None else v

    def _release_outputs(self) -> None:
        """Before the forward writes the image and alpha again: those handed out and still held get
        memory of their own; a view of them still held raises RenderError."""
        for name, (storage, refs), handed in zip(("image", "alpha"), self._output_refs, self._handed):
            count = _use_count(storage)
            if count is not None and count <= refs:
                continue
            held = handed()
            if held is not None:  # the caller's tensor takes a copy: what it reads stays what it was
                held.data = held.data.clone()
                del held
                count = _use_count(storage)
            if count is not None and count > refs:
                raise RenderError(f"a view of the last frame's {name} is still held: clone what you keep of a "
                                  "FrameGraph's images before its next frame")
        self._handed = ()

    def _release_grads(self) -> None:
        """Before a replay writes where the gradients lie: a `.grad` still holding them gets its own
        copy; anything else holding them raises RenderError (a frame's gradients are the graph's)."""
        if not self._handed_out:
            return
        for (name, tensor), grad, watched in zip(self._params, self._grads, self._grad_refs):
            if grad is None:
                continue
            storage, refs = watched
            count = _use_count(storage)
            if count is not None and count <= refs:
                continue
            held = tensor.grad
            if held is not None and held.data_ptr() == grad.data_ptr():
                tensor.grad = held.clone()
                del held
                count = _use_count(storage)
            if count is not None and count > refs:
                raise RenderError(f"the last frame's gradient of {name} is still held outside its .grad: clone what "
                                  "you keep of a FrameGraph's gradients before its next frame")
        self._handed_out = False


def timed_frame(width: int, height: int, near: float, far: float, device: torch.device, times: torch.Tensor,
                row_count=NO_ARRAY):
    """The frame (tomgs.render.frame's, for `issue_frame`) of one image size whose time is read from `times`
    (float32 [2], t_hi and t_lo: device memory written before each replay, as `time_table`'s rows) and,
    with `row_count` (a descriptor of int32 [1]), whose rows are that many of those given."""
    with scope(device) as wp_device:
        return Frame(width, height, 0.0, 0.0, near, far, wp_device, times=wrap(times), row_count=row_count)


def time_table(times, device: torch.device) -> torch.Tensor:
    """float32 [T,2] (t_hi, t_lo) of each time t in `times` (t = t_hi + t_lo to ~48 bits, as a replayed
    frame reads it): a captured step picks its frame's row on the device."""
    return torch.tensor([check_time(t) for t in times], dtype=torch.float32, device=device).reshape(-1, 2)


def key_bound(frame) -> tuple[int, int]:
    """(the tile keys a frame of `frame`'s size holds without waiting for its count: tomgs.render.frame's bound
    of recent frames of that size, the largest total among them); (0, 0) before one was counted."""
    return frame_layer.key_bounds.capacity(frame), frame_layer.key_bounds.largest(frame)


def remember_total(frame, total: int) -> None:
    """A frame of `frame`'s size needed `total` tile keys (read after it ran): the bound learns it."""
    frame_layer.key_bounds.remember(frame, total)


@contextlib.contextmanager
def no_collection():
    """No garbage collection while capturing: a collection may free another CUDA graph, and a graph
    destroyed during a capture (global mode) invalidates the capture."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


@contextlib.contextmanager
def known_to_warp(device: torch.device, thread_local: bool = False):
    """Tell Warp that torch is capturing its current stream (in torch.cuda.graph's default mode, global,
    or with `thread_local` its capture_error_mode "thread_local"): Warp's sort then takes its scratch from
    the graph, where it is freed, and not from memory it would leak (and warn about) at every capture."""
    stream = torch_stream(warp_device(device))
    mode = wp.CaptureMode.THREAD_LOCAL if thread_local else wp.CaptureMode.GLOBAL
    wp.capture_begin(stream=stream, external=True, capture_mode=mode)
    try:
        yield
    finally:
        wp.capture_end(stream=stream)


class _Replayed(torch.autograd.Function):
    @staticmethod
    def forward(ctx, graph: FrameGraph, wp_device: str, frame: list, *params):
        """(image, alpha) of `graph`'s frame seen by `frame` (set_frame's arguments), in its memory."""
        ctx.graph = graph
        ctx.set_materialize_grads(False)  # an unused image or alpha passes None
        image, alpha = graph._run_forward(wp_device, frame)
        return image, alpha

    @staticmethod
    def backward(ctx, v_image, v_alpha):
        graph = ctx.graph
        grads = graph._run_backward(v_image, v_alpha)
        graph._in_flight = None
        return (None, None, None, *grads)
