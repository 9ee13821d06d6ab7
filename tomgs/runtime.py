"""The Warp runtime of tomgs: the one place that initialises Warp and launches its kernels.

    init_warp()                      initialise Warp once, quietly (deferred: importing tomgs stays cheap)
    warp_device(device) -> str       the Warp name of a torch device ("cpu", "cuda:N")
    scope(device)                    context that yields the Warp device name of `device` (launches go
                                     to torch's current stream there); RenderError for other types
    torch_stream(device)             Warp's handle of torch's current stream on a CUDA device
    wrap(tensor, dtype=None, ndim=None)
                                     zero-copy Warp array descriptor of a torch tensor
    wrap_rows(tensor)                the same of a contiguous [N, ...] tensor seen as [N, D]
    wrap_flat(tensor)                the same of a contiguous tensor seen as [numel]
    NO_ARRAY                         a descriptor of an empty array, for outputs a launch will not write
    indexable(grad, like, *size)     an incoming gradient as a kernel can index it (zeros for None)
    struct_values(struct)            the ctypes class of a wp.struct's values, filled with descriptors
    launch(kernel, dim, args, device, block_dim=256)
                                     a recorded launch per (kernel, device, block size), re-armed
    whole_blocks(n)                  the launch size, in whole blocks of 256, of n threads of work
    sort_pairs(keys, values, count, end_bit, begin_bit)
                                     Warp's radix sort of int64 keys and int32 values, on tensors
    kernels_compiled(device_type)    whether this machine has compiled these kernels for that device
                                     before (a marker in Warp's kernel cache); mark_kernels_compiled
                                     writes it once a fit has run them
    one_cpu_thread(device)           a context: torch's CPU ops in one thread while it runs on a CPU
                                     device (the tracker and a fit; see there)

Used by tomgs.render (the rasterizer), tomgs.metrics (SSIM), tomgs.train.optim (SeenAdam),
tomgs.edit.physics (XPBD), and tomgs.poses and tomgs.train.pipeline (one_cpu_thread). Every buffer
is a torch tensor handed to Warp without a copy, so torch's allocator and memory statistics see all
of it.

Warp has no public name for its array descriptor (the ctypes structure that kernels receive);
`wp.from_torch(tensor, return_ctype=True)` is the public way to build one. It costs ~3x more per
call than packing the structure's bytes directly (`wrap`), and it pins the tensor (the descriptor keeps a
reference), so a recorded launch would keep the previous frame's buffers alive until the next frame
re-arms it. So the descriptor class is taken from what `wp.from_torch(..., return_ctype=True)`
returns (no import of Warp's private modules) and filled directly; `_check_descriptor` compares the
result with `wp.from_torch`'s own on import, so a Warp release that changes the structure fails
here, loudly, and not as wrong pixels. Checked on Warp 1.19.0.

The one use of Warp's private modules is `sort_pairs`: its radix sort's native entry point, called
on tensors (the public function wants full Warp arrays; see there).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import struct
import sys

import torch
import warp as wp
import warp._src.context as _warp_context  # private: only for sort_pairs (see there)

from tomgs.errors import RenderError

__all__ = ["resolve_device", "kernels_compiled", "mark_kernels_compiled", "init_warp", "warp_device", "scope", "torch_stream", "wrap", "wrap_rows", "wrap_flat", "NO_ARRAY",
           "indexable", "struct_values", "launch", "Launches", "whole_blocks", "ArrayDescriptor", "sort_pairs",
           "one_cpu_thread"]

_warp_ready = False


def _compiled_marker(device_type: str):
    """The marker file, in Warp's kernel cache, of tomgs's kernels (their source's digest) compiled
    for `device_type`. Warp compiles a kernel module at its first launch and caches it by a hash of
    its code; a fresh machine (or a new tomgs) pays that once, about a minute on a 2-core CPU."""
    import hashlib
    from pathlib import Path

    kernels = Path(__file__).parent / "kernels"
    digest = hashlib.sha1()
    for path in sorted(kernels.glob("*.py")):
        digest.update(path.name.encode() + path.read_bytes())
    return Path(wp.config.kernel_cache_dir or "") / f"tomgs-{digest.hexdigest()[:12]}-{device_type}.compiled"


def kernels_compiled(device_type: str) -> bool:
    """Whether tomgs's kernels as they are now were compiled for `device_type` on this machine (and
    are in Warp's kernel cache); False on a first run, whose first steps compile them."""
    init_warp()
    return _compiled_marker(device_type).is_file()


def mark_kernels_compiled(device_type: str) -> None:
    """Record that the kernels ran (compiled) on `device_type`; a cache that cannot be written is left
    as it is (the next run only announces a compilation that does not come)."""
    init_warp()
    try:
        _compiled_marker(device_type).touch()
    except OSError:
        pass


def resolve_device(name: str | None = "auto") -> torch.device:
    """'auto' (CUDA when available, else CPU), 'cpu', 'cuda' or 'cuda:N'; raises RenderError otherwise."""
    name = "auto" if name is None else str(name)
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise RenderError(f"unknown device {name!r}: use auto, cpu, cuda or cuda:N") from None
    if device.type not in ("cpu", "cuda"):
        raise RenderError(f"device {name!r} is not supported: use auto, cpu, cuda or cuda:N")
    if device.type == "cuda" and (not torch.cuda.is_available()
                                  or (device.index or 0) >= torch.cuda.device_count()):
        raise RenderError(f"device {name!r} is not available on this machine: use cpu (or auto)")
    return device


def init_warp() -> None:
    """Initialise Warp once, quietly: no banner, no per-module compile lines, no CPU-only driver warning."""
    global _warp_ready
    if not _warp_ready:
        wp.config.log_level = max(wp.config.log_level, wp.LOG_ERROR)
        # Warp's native library prints "Could not find or load the NVIDIA CUDA driver" straight to
        # file descriptor 2 on machines without one, whatever the log level: on a CPU-only machine
        # (torch sees no GPU) that line is noise in every command's output
        with contextlib.nullcontext() if torch.cuda.is_available() else _native_stderr_silenced():
            wp.init()
        wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
        _warp_ready = True


@contextlib.contextmanager
def _native_stderr_silenced():
    """Send what native code writes to file descriptor 2 to /dev/null for the duration. What Python
    writes to sys.stderr meanwhile, from any thread (a rank's first line, the progress line), goes to
    the real stderr: sys.stderr is a writer on a copy of descriptor 2 until it is back."""
    sys.stderr.flush()
    saved = os.dup(2)
    python_stderr = sys.stderr
    on_descriptor_2 = _descriptor(python_stderr) == 2
    if on_descriptor_2:
        sys.stderr = open(saved, "w", buffering=1, encoding=getattr(python_stderr, "encoding", None),  # noqa: SIM115
                          errors=getattr(python_stderr, "errors", None), closefd=False)  # kept: see below
        sys.stderr.reconfigure(write_through=True)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        if on_descriptor_2:  # the copy stays open (once a process): a thread may still hold its writer
            sys.stderr.flush()
            sys.stderr = python_stderr
        else:
            os.close(saved)


def _descriptor(stream) -> int | None:
    try:
        return stream.fileno()
    except (AttributeError, OSError, ValueError):  # a captured or replaced stream has none
        return None


def warp_device(device: torch.device) -> str:
    """The Warp name of a CPU or CUDA torch device (CUDA without an index: torch's current one)."""
    if device.type == "cpu":
        return "cpu"
    return f"cuda:{device.index if device.index is not None else torch.cuda.current_device()}"


# Warp's handle of each torch CUDA stream (external streams), by raw handle: wrapping one costs tens
# of microseconds, so once per stream
_streams: dict[int, wp.Stream] = {}


def _public_raw_stream(index: int) -> int:
    return torch.cuda.current_stream(index).cuda_stream


# torch's current stream as a raw handle without building a torch.cuda.Stream object (~1 us against
# several on a GPU machine's CPU, once per launch); private to torch, so the public call stands in
# where a build lacks it
_raw_stream = getattr(torch._C, "_cuda_getCurrentRawStream", None) or _public_raw_stream


def torch_stream(device: str) -> wp.Stream:
    """Warp's handle of torch's current stream on the CUDA device `device` ("cuda:N")."""
    index = int(device[5:])
    raw = _raw_stream(index)
    stream = _streams.get(raw)
    if stream is None:
        stream = _streams[raw] = wp.stream_from_torch(torch.cuda.current_stream(index))
    return stream


class _Scope:
    """What `scope` returns: a context that yields the Warp device name and changes nothing. Launches
    take torch's current stream themselves (`torch_stream`), so Warp's own current stream is never
    switched: entering and leaving a wp.ScopedStream (a device switch and two native calls each
    way) cost ~20 us of a GPU machine's CPU, up to 16 times a training step."""

    __slots__ = ("name",)

    def __init__(self, name: str):
        self.name = name

    def __enter__(self) -> str:
        return self.name

    def __exit__(self, *exc) -> None:
        return None


_scopes: dict[torch.device, _Scope] = {}


def scope(device: torch.device) -> _Scope:
    """Run Warp launches on `device` (on torch's current stream when it is a GPU): a context that yields
    Warp's device name; RenderError for other device types."""
    init_warp()  # deferred to the first launch so that importing tomgs stays cheap
    found = _scopes.get(device)
    if found is not None:
        return found
    if device.type not in ("cpu", "cuda"):
        raise RenderError(f"tensors on {device} are not supported: use a CPU or CUDA device")
    found = _Scope(warp_device(device))
    if device.type == "cpu" or device.index is not None:  # "cuda" alone follows torch's current device
        _scopes[device] = found
    return found


# The class of the descriptors `wp.from_torch(..., return_ctype=True)` returns (see the module docstring).
ArrayDescriptor = type(wp.from_torch(torch.empty(0), requires_grad=False, return_ctype=True))

# trailing tensor axes a Warp dtype takes: 1 for a vector, 2 for a matrix (filled in on first use)
_INNER_AXES: dict = {wp.vec2: 1, wp.vec3: 1, wp.vec4: 1, wp.vec2i: 1, wp.mat33: 2, wp.mat44: 2}


def _inner_axes(dtype) -> int:
    axes = 2 if wp.types.type_is_matrix(dtype) else 1 if wp.types.type_is_vector(dtype) else 0
    _INNER_AXES[dtype] = axes
    return axes


# A descriptor's bytes (see _check_descriptor): data, grad, shape[4], strides[4], ndim, flags, padding.
# Packing them and copying the bytes in is ~2x quicker than the structure's own __init__ (a Python
# loop over the axes), and a frame builds ~40 descriptors.
_DESCRIPTOR_BYTES = struct.Struct("=QQ4i4iHH4x")
_NO_AXES = (0, 0, 0, 0)


def _descriptor_1d(pointer: int, length: int, stride: int):
    """A 1D array descriptor: `length` elements `stride` bytes apart from `pointer`."""
    return ArrayDescriptor.from_buffer_copy(_DESCRIPTOR_BYTES.pack(pointer, 0, length, 0, 0, 0, stride, 0, 0, 0, 1, 0))


def wrap(tensor: torch.Tensor, dtype=None, ndim: int | None = None):
    """Zero-copy Warp array descriptor of `tensor` [..., *dtype's shape]; a vector or matrix dtype folds
    the trailing axes, which must be contiguous; None (or a scalar dtype) keeps every axis. `ndim`
    keeps only the leading axes (what follows must be of size 1 or folded by dtype): an [H, W, 1]
    tensor as a 2D array, without a torch view call (each costs host time on a GPU machine).
    A tensor that is one element of `dtype` (a [4, 4] viewmat as wp.mat44) becomes a [1] array.

    What `wp.from_torch(tensor, dtype, requires_grad=False, return_ctype=True)` builds, at a fraction
    of its cost, which matters at ~60 arguments per frame. It does not own the tensor: the caller
    keeps `tensor` alive until the launch is queued.
    """
    inner = 0 if dtype is None else _INNER_AXES.get(dtype)
    if inner is None:
        inner = _inner_axes(dtype)
    keep = tensor.dim() - inner if ndim is None else ndim
    item = tensor.element_size()
    if keep == 0:  # the whole tensor is one element
        return _descriptor_1d(tensor.data_ptr(), 1, tensor.numel() * item)
    size, step = tensor.shape, tensor.stride()
    if keep == 1:  # most arguments: spelled out, a generator costs as much as the rest together
        return _descriptor_1d(tensor.data_ptr(), size[0], step[0] * item)
    shape = tuple(size[:keep]) + _NO_AXES[keep:]
    strides = tuple(s * item for s in step[:keep]) + _NO_AXES[keep:]
    return ArrayDescriptor.from_buffer_copy(_DESCRIPTOR_BYTES.pack(tensor.data_ptr(), 0, *shape, *strides, keep, 0))


def indexable(grad: torch.Tensor | None, like: torch.Tensor, *size: int) -> torch.Tensor:
    """An incoming gradient Warp can index: for None, zeros of `like`'s dtype and device and of `size`
    (default: like's shape); rows may be strided, the last axis must not be (nor any broadcast axis).
    Keep the result named until the launch is queued."""
    if grad is None:
        return like.new_zeros(size) if size else torch.zeros_like(like)
    if grad.dim() > 1 and grad.stride(-1) != 1 or 0 in grad.stride():
        return grad.contiguous()
    return grad


def wrap_rows(tensor: torch.Tensor):
    """`wrap` of a contiguous `tensor` [N, ...] viewed as [N, D] (D the product of the other axes),
    without a torch view call (on a GPU machine each costs microseconds of host time)."""
    if not tensor.is_contiguous() or tensor.dim() == 0:
        raise ValueError(f"wrap_rows needs a contiguous tensor of at least one axis, got shape {tuple(tensor.shape)}")
    rows = tensor.shape[0]
    cols = tensor.numel() // rows if rows else 0
    item = tensor.element_size()
    return ArrayDescriptor.from_buffer_copy(_DESCRIPTOR_BYTES.pack(
        tensor.data_ptr(), 0, rows, cols, 0, 0, cols * item, item, 0, 0, 2, 0))


def wrap_flat(tensor: torch.Tensor):
    """The values of a contiguous tensor as a 1D array [numel] of its dtype (no torch view call)."""
    if not tensor.is_contiguous():
        raise ValueError("wrap_flat takes a contiguous tensor")
    return _descriptor_1d(tensor.data_ptr(), tensor.numel(), tensor.element_size())


def wrap_part(tensor: torch.Tensor, start: int, length: int):
    """Elements [start, start + length) of a contiguous 1D tensor as a 1D array (no torch view call)."""
    if tensor.dim() != 1 or not tensor.is_contiguous() or start < 0 or start + length > tensor.shape[0]:
        raise ValueError(f"wrap_part takes a range of a contiguous 1D tensor, got [{start}, {start + length}) "
                         f"of shape {tuple(tensor.shape)}")
    item = tensor.element_size()
    return _descriptor_1d(tensor.data_ptr() + start * item, length, item)


# an empty array: what a kernel receives for an output it is told not to write (no allocation)
NO_ARRAY = ArrayDescriptor(0, 0, 1, (0,), (4,))


def _check_descriptor() -> None:
    """Our descriptors must equal, byte for byte, what `wp.from_torch` (the public build) makes."""
    base = torch.arange(60, dtype=torch.float32).reshape(4, 5, 3)
    rows = base.reshape(4, 15)
    for ours, tensor, dtype in ((wrap(base[:, ::2], wp.vec3), base[:, ::2], wp.vec3),
                                (wrap(base[:3, :3], wp.mat33), base[:3, :3], wp.mat33),
                                (wrap(base[1:, :, 0]), base[1:, :, 0], None), (wrap(base), base, None),
                                (wrap(base[1:, :, :1], ndim=2), base[1:, :, 0], None),
                                (wrap(base[0, :3]), base[0, :3], None),
                                (wrap(base[0, :3], wp.mat33), base[0, :3].reshape(1, 3, 3), wp.mat33),
                                (wrap_rows(base), rows, None), (wrap_flat(base), base.reshape(-1), None),
                                (wrap(base[0, 0, :1].expand(7)), base[0, 0, :1].expand(7), None)):
        theirs = wp.from_torch(tensor, dtype, requires_grad=False, return_ctype=True)
        if bytes(ours) != bytes(theirs):
            raise RuntimeError(f"tomgs.runtime: Warp {wp.__version__} builds array descriptors differently from "
                               "the version tomgs was checked on (1.19.0): update tomgs.runtime.wrap")


_check_descriptor()


class _Packed:
    """A struct argument's ctypes value as `wp.launch` takes a struct instance (what it packs is
    `__ctype__()`): for recording a launch from a value `struct_values` built."""

    __slots__ = ("value",)

    def __init__(self, value: ctypes.Structure):
        self.value = value

    def __ctype__(self) -> ctypes.Structure:
        return self.value


# each wp.struct's values' class, found once
_struct_values: dict = {}


def struct_values(struct):
    """The ctypes class of a `wp.struct`'s values, as kernels receive them: build one with keywords (`wrap`ped
    arrays, Python scalars, Warp vectors) and pass it to `launch` for a struct argument. Warp fills a struct
    instance's array fields from `wp.array`s only (~20 us each from a tensor); this fills them with
    descriptors. Taken from what a public instance returns (`__ctype__()`), as ArrayDescriptor is."""
    found = _struct_values.get(struct)
    if found is None:
        found = _struct_values[struct] = type(struct().__ctype__())
    return found


class Launches:
    """One recorded Warp launch per (kernel, device, block size), re-armed with fresh arguments.

    `wp.launch` spends tens of microseconds in Python per call validating and packing arguments;
    re-arming a recorded launch with ready-made descriptors skips that, which is a large share of
    a frame at 1M Gaussians. Arguments: `wrap`ped tensors for arrays, values of `struct_values` for
    structs, Python ints and floats for scalars, in the kernel's order. Not thread-safe: launch from
    one thread at a time.
    """

    def __init__(self):
        # (kernel, device, block size) -> [command, its dim, the arguments it holds, the addresses of
        # its own array descriptors and struct values (0 for a scalar), their types, their sizes]
        self._recorded: dict[tuple, list] = {}

    def __call__(self, kernel, dim: int, args: list, device: str, block_dim: int = 256) -> None:
        if dim == 0:
            return  # nothing to run, and Warp records no command for an empty launch
        key = (kernel, device, block_dim)  # the kernel itself: two modules may name kernels alike
        entry = self._recorded.get(key)
        if entry is None:
            # the command holds a vector or matrix argument as the object it is given and later sets its value
            # in place: each gets a copy of its own (one object passed twice would take both values, and the
            # caller's own object would change at later launches)
            args = [type(arg).from_buffer_copy(arg) if isinstance(arg, ctypes.Array) else arg for arg in args]
            inputs = [_Packed(arg) if isinstance(arg, ctypes.Structure) and type(arg) is not ArrayDescriptor
                      else arg for arg in args]
            cmd = wp.launch(kernel, dim=dim, inputs=inputs, device=device, block_dim=block_dim, record_cmd=True)
            # each array and struct argument gets a value of the command's own (the launch may hold the
            # caller's, which is shared: NO_ARRAY, a frame's saved descriptors), and later ones have their
            # bytes copied into it, where the launch already points (params[0] is the bounds)
            slots, types, sizes = [0] * len(args), [None] * len(args), [0] * len(args)
            for i, arg in enumerate(args):
                if isinstance(arg, ctypes.Structure):
                    cmd.set_param_at_index_from_ctype(i, type(arg).from_buffer_copy(arg))
                    slots[i], types[i], sizes[i] = ctypes.addressof(cmd.params[i + 1]), type(arg), ctypes.sizeof(arg)
            self._recorded[key] = [cmd, dim, list(args), slots, types, sizes]
        else:
            cmd, last_dim, held, slots, types, sizes = entry
            if dim != last_dim:
                cmd.set_dim(dim)
                entry[1] = dim
            for i, arg in enumerate(args):
                if slots[i]:  # an array or a struct: a new object every frame
                    if type(arg) is not types[i]:
                        raise TypeError(f"{kernel.key} argument {i}: a recorded launch takes `wrap`ped arrays and "
                                        f"`struct_values` structs, a {types[i].__name__} here; got "
                                        f"{type(arg).__name__}")
                    ctypes.memmove(slots[i], ctypes.addressof(arg), sizes[i])
                elif type(arg) is not int or type(held[i]) is not int or arg != held[i]:
                    # an int the command already holds (sizes, flags: most scalars, frame after frame)
                    # is not set again
                    cmd.set_param_at_index_from_ctype(i, arg)
                    held[i] = arg
        cmd.launch(None if device == "cpu" else torch_stream(device))


# the process's one cache of recorded launches
launch = Launches()


def whole_blocks(n: int) -> int:
    """Threads to launch for n items in a kernel that sums per block (every thread of a block reaches
    the block's reduction, the last block's spare threads too): n rounded up to whole blocks of 256,
    at least one block."""
    return max(1, -(-n // 256)) * 256


def sort_pairs(keys: torch.Tensor, values: torch.Tensor, count: int, end_bit: int, begin_bit: int = 0) -> None:
    """Sort keys[:count] (int64) by their bits [begin_bit, end_bit), stably, and values[:count] (int32) with
    them, in place, on the keys' device (a GPU: torch's current stream there).
    Both are contiguous and hold at least 2 * count elements: [count, 2 * count) is the sort's scratch.

    Warp's public `wp.utils.radix_sort_pairs` takes full `wp.array`s only: ~20 us each to build from
    a tensor on a GPU machine's CPU, twice a frame, after the frame's host sync, where the GPU waits
    for them. It reads their pointers and, for these dtypes, calls the native entry points below with
    the same arguments; they are Warp's private API (checked on 1.19.0), so a release that renames
    them fails here with an AttributeError, and tests/render/test_binning.py runs this on the CPU.
    """
    if (keys.dtype != torch.int64 or values.dtype != torch.int32 or not keys.is_contiguous()
            or not values.is_contiguous() or keys.device != values.device):
        raise ValueError(f"sort_pairs needs contiguous int64 keys and int32 values on one device, got "
                         f"{keys.dtype} on {keys.device} and {values.dtype} on {values.device}")
    if keys.numel() < 2 * count or values.numel() < 2 * count:
        raise ValueError(f"sort_pairs of {count} pairs needs {2 * count} elements of storage (the upper half is "
                         f"scratch), got {keys.numel()} keys and {values.numel()} values")
    if count == 0:
        return
    core = _warp_context.runtime.core
    args = (keys.data_ptr(), values.data_ptr(), count, begin_bit, end_bit, values.element_size())
    if keys.device.type == "cpu":
        core.wp_radix_sort_pairs_int64_host(*args)
        return
    # the native sort runs on Warp's current stream of the current device: torch's, for this call only
    with wp.ScopedStream(torch_stream(warp_device(keys.device)), sync_enter=False):
        core.wp_radix_sort_pairs_int64_device(*args)


# torch on a CPU: many small ops (the tracker's bundle adjustment: a few hundred unknowns; a training step's
# loss and bookkeeping around the Warp kernels, which run serially anyway). Handing each op to a second
# thread costs more than it saves, and on a 2-core machine that other work keeps busy the thread that waits
# for the other at every op is where the time goes: at load ~8 the bundled clip's poses took 45 s of wall
# time in two threads and 5.7 s in one, and 80 training steps 326 s against 158 s, same cameras and scene.
@contextlib.contextmanager
def one_cpu_thread(device):
    """torch's CPU ops in one thread while the block runs, where `device` is a CPU (a GPU's work is
    left as it is); the thread count before it is restored after."""
    if torch.device(device).type != "cpu":
        yield
        return
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
