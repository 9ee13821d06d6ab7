"""The frame layer and the public rasterizer: `rasterize(...)`, `render_frame`, `blend_weights`, and each
stage alone (`project_stage`, `bin_stage`).

A frame issues the stages of tomgs.render.stages (project -> binning -> raster -> + background) with one
host sync, the intersection count and the contract flags read together (`issue_frame`), or none
(`render_frame(defer=True)`: the counts come back later, `FrameCounts`); the tile keys are written
before that sync into buffers of a bound kept between frames of a size (`KeyBounds`).
"""

from __future__ import annotations

import math
import struct
from collections import deque

import torch
import warp as wp

from tomgs.constants import TILE_SIZE
from tomgs.kernels import binning, project
from tomgs.render.inputs import RasterInputs, RenderError, prepare_inputs
from tomgs.render.stages import MAX_INTERSECTIONS, Frame, Image, Project, Rasterize, WorkLists, sort_and_range, \
    write_keys
from tomgs.runtime import NO_ARRAY, launch, scope, whole_blocks, wrap

# one raster thread per pixel of the tile-padded image, counted in int32
MAX_THREADS = 2**31 - 1


def check_scalars(width, height, t, near, far) -> tuple[float, float]:
    """Refuse non-finite or non-integer sizes and a non-finite time or plane; return t as float32
    (t_hi, t_lo) with t_hi + t_lo = t to ~48 bits, so (t - m) keeps the precision of a float64 t."""
    for name, value in (("width", width), ("height", height)):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) or hasattr(value, "__index__")
        if not ok or not math.isfinite(value) or value != int(value) or value < 1:
            raise RenderError(f"{name} must be a positive integer, got {value!r}")
    t_hi, t_lo = check_time(t)
    for name, value in (("near", near), ("far", far)):
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise RenderError(f"{name} must be a number, got {value!r}") from None
        if math.isnan(value) or (name == "near" and not math.isfinite(value)):
            raise RenderError(f"need 0 < near < far (near finite, far may be inf), got near={near}, far={far}")
    return t_hi, t_lo


def check_time(t) -> tuple[float, float]:
    """t as float32 (t_hi, t_lo), t_hi + t_lo = t to ~48 bits; RenderError for a time that is not a finite
    number within float32's range."""
    try:
        t = float(t)
        t_hi = struct.unpack("f", struct.pack("f", t))[0]  # OverflowError beyond float32
    except (TypeError, ValueError, OverflowError):
        raise RenderError(f"t must be a finite time within float32's range, got {t!r}") from None
    if not math.isfinite(t_hi):
        raise RenderError(f"t must be a finite time within float32's range, got {t!r}")
    return t_hi, struct.unpack("f", struct.pack("f", t - t_hi))[0]


def _first_bad(name: str, rule: str, bad: torch.Tensor, values: torch.Tensor) -> str:
    """'<name> <rule>: k of N do not, the first at index i (value)' for bool `bad` [N] or [N, C]."""
    rows = bad.reshape(bad.shape[0], -1).any(-1)
    first = int(torch.nonzero(rows)[0, 0])
    value = values[first].tolist()
    return f"{name} {rule}: {int(rows.sum())} of {rows.shape[0]} do not, the first at index {first} ({value})"


def _contract_error(stats: list[int], p) -> RenderError:
    """The message for the contract flags the kernels raised (slow path: only on bad input)."""
    problems = []
    if stats[project.FLAG_OPACITIES]:
        o = p.opacities
        problems.append(_first_bad("opacities", "must lie in [0, 1] (base opacity, not a logit)",
                                   ~((o >= 0) & (o <= 1)), o))
    if stats[project.FLAG_SCALES]:
        problems.append(_first_bad("scales", "must be >= 0 (scales, not log scales)", p.scales < 0, p.scales))
    if stats[project.FLAG_T_SCALES]:
        problems.append(_first_bad("t_scales", "must be >= 0 (temporal sigma, not its log)", p.t_scales < 0,
                                   p.t_scales))
    if stats[project.FLAG_K]:
        problems.append(f"K must be finite with fx = K[0, 0] > 0 and fy = K[1, 1] > 0, got {p.K.tolist()}")
    if stats[project.FLAG_VIEWMAT]:
        problems.append(f"viewmat must be finite, got {p.viewmat.tolist()}")
    if stats[project.FLAG_BACKGROUND]:
        problems.append(f"background must be finite, got {p.background.tolist()}")
    if stats[project.FLAG_ROWS]:
        n = p.means.shape[0]
        problems.append(_first_bad("rows", f"must index the {n} Gaussians (0 .. N-1)",
                                   (p.rows < 0) | (p.rows >= n), p.rows))
    return RenderError("; ".join(problems))


class KeyBounds:
    """Upper bounds on a frame's intersection count, kept between frames per (Warp device, width,
    height), so that a frame's keys are written before its host sync (`write_keys`): the largest
    total of the last FRAMES frames of that size, plus twice their spread (largest - smallest) but
    at most an eighth of it, plus 1/256 of it and 256; at most MAX_INTERSECTIONS; 0 (keys written
    after the sync) until a frame of that size has been counted. The headroom follows how much the
    totals move: a training run's views (totals apart by tens of percent) get the eighth, frames
    that repeat (a benchmark, a still camera) almost none, which the keys' memory would pay for
    (24 bytes a slot: ~22 MB at 1080p with 1M Gaussians for a flat eighth)."""

    FRAMES = 16

    def __init__(self):
        self._recent: dict[tuple, deque] = {}
        self._capacity: dict[tuple, int] = {}

    @staticmethod
    def _key(frame: Frame) -> tuple:
        return frame.device, frame.width, frame.height

    def capacity(self, frame: Frame) -> int:
        return self._capacity.get(self._key(frame), 0)

    def largest(self, frame: Frame) -> int:
        """The largest total of the last FRAMES frames of this size (0: none counted)."""
        return max(self._recent.get(self._key(frame), ()), default=0)

    def remember(self, frame: Frame, total: int) -> None:
        key = self._key(frame)
        recent = self._recent.setdefault(key, deque(maxlen=self.FRAMES))
        recent.append(total)
        top = max(recent)
        headroom = min(2 * (top - min(recent)), top // 8) + top // 256 + 256
        self._capacity[key] = min(MAX_INTERSECTIONS, top + headroom)


# the process's bounds (not thread-safe, like tomgs.runtime.launch)
key_bounds = KeyBounds()


def _bin(wrapped: dict, n: int, ends: torch.Tensor, frame: Frame, total: int,
         written: tuple[torch.Tensor, torch.Tensor] | None = None, lists: WorkLists | None = None):
    """Stage 2 after the host sync: (ids [>= total] int32 Gaussian per intersection, keys [>= total] int64
    `tile << 32 | depth bits`, sorted; the first `total` entries are the list), and the ranges [tiles, 2]
    int32 of `wrapped` (zeroed by the caller) filled with each tile's [start, end) into them.

    `written`: (keys, ids) from `write_keys` before the sync; written again here, at the right size,
    when `total` exceeds their capacity (or for None). `wrapped`, `ends` and `lists` as for `write_keys`;
    `wrapped` holds the descriptor of `ranges` too.
    """
    if total > MAX_INTERSECTIONS:
        raise RenderError(
            f"this frame needs {total:,} Gaussian-tile intersections, more than the {MAX_INTERSECTIONS:,} the "
            f"rasterizer can sort; render at a lower resolution or with fewer or smaller Gaussians")
    if written is None or written[0].shape[0] < 2 * total:  # past the bound: correct, just slower
        written = write_keys(wrapped, n, ends, frame, total, lists)
    return sort_and_range(wrapped, written, total, frame)


def _bin_padded(wrapped: dict, n: int, ends: torch.Tensor, frame: Frame, written: tuple[torch.Tensor, torch.Tensor]):
    """Stage 2 without the intersection count (a frame that does not wait for it): the keys written
    before the sync (`write_keys`, its capacity > 0) are padded from the total to their capacity and
    sorted whole, so the list comes first and `tile_ranges` skips the padding. A total past the
    capacity leaves the list without its last Gaussians' entries: `FrameCounts.overflowed` says so.
    Returns (ids, keys) as `_bin`; `wrapped` holds the descriptor of `ranges`."""
    capacity = written[0].shape[0] // 2
    launch(binning.pad_tile_keys, capacity, device=frame.device,
           args=[wrap(ends), n, frame.padding_key, wrapped["keys"]])
    return sort_and_range(wrapped, written, capacity, frame)


def _project_frame(p: RasterInputs, frame: Frame, wrapped: dict):
    """Stage 1, launched, and the buffers the frame's one host sync reads: ((means2d, conics, depths, radii,
    opacities_t, tiles_touched), ends [N] int64 the inclusive scan of tiles touched, flags
    [project.NUM_FLAGS] int64 for `_read_flags`, the work lists of projection (pass 0) and binning
    (pass 1) or None). Fills `wrapped` with projection's descriptors."""
    viewmat, K = p.viewmat.contiguous(), p.K.contiguous()
    n = p.means.shape[0] if p.rows is None else p.rows.shape[0]  # M: the Gaussians projected
    # contract flags, counts and the intersection count, written on the device, read back together
    flags = torch.zeros(project.NUM_FLAGS, device=p.means.device, dtype=torch.int64)
    lists = WorkLists.of(n, 2, p.means.device)
    outputs = Project.apply(p.means.contiguous(), p.quats.contiguous(), p.scales.contiguous(),
                             p.opacities.contiguous(), p.t_means.contiguous(), p.t_scales.contiguous(), viewmat, K,
                             flags, frame, wrapped, p.rows, lists)
    ends = torch.cumsum(outputs[-1], 0, dtype=torch.int64)  # [N] inclusive scan of tiles touched
    has_bg = p.background is not None
    threads = whole_blocks(-(-n // project.STATS_ROWS))
    launch(project.frame_stats, threads, device=frame.device, args=[
        wrapped["tiles_touched"], wrapped["opacities_t"], wrap(ends), n, threads, wrapped["viewmat"], wrapped["K"],
        wrap(p.background, wp.vec3) if has_bg else NO_ARRAY, int(has_bg), wrap(flags)])
    return outputs, ends, flags, lists


def _read_flags(flags: torch.Tensor, p: RasterInputs) -> list[int]:
    """The one host sync per frame: the intersection count sizes the sort buffers; the contract flags
    and the visible and alive counts travel with it, so they cost no extra wait. RenderError on
    input outside the contract."""
    stats = flags.tolist()
    if any(stats[k] for k in project.CONTRACT_FLAGS):
        raise _contract_error(stats, p)
    return stats


def _counts(stats: list[int]) -> dict:
    return dict(n_visible=stats[project.FLAG_VISIBLE], n_alive=stats[project.FLAG_ALIVE],
                n_intersections=stats[project.FLAG_TOTAL])


class FrameCounts:
    """The counts of a frame rendered without waiting for them (`render_frame(defer=True)`): its flags
    are copied to the host as soon as projection has written them, and `read()` waits for that copy
    only, not for the rest of the frame, so the host can issue the next frame meanwhile. Read them
    before using the image: RenderError for inputs outside the contract, and `overflowed` when the
    frame needed more intersections than its keys held (its image then lacks some; render it again
    waiting for its counts: the bound has grown)."""

    def __init__(self, flags: torch.Tensor, p: RasterInputs, frame: Frame, capacity: int):
        self._event = None
        if flags.is_cuda:
            flags = flags.to("cpu", non_blocking=True)  # pinned: the copy is queued, nothing waits
            self._event = torch.cuda.Event()
            self._event.record()
        self._flags, self._inputs, self._frame, self.capacity = flags, p, frame, capacity
        self._counts: dict | None = None

    def read(self) -> dict:
        """n_visible, n_alive, n_intersections (ints) of the frame, as `rasterize`'s meta has them."""
        if self._counts is None:
            if self._event is not None:
                self._event.synchronize()
            stats = _read_flags(self._flags, self._inputs)
            self._inputs = None  # only its error messages needed them
            key_bounds.remember(self._frame, stats[project.FLAG_TOTAL])
            self._counts = _counts(stats)
        return self._counts

    def known(self) -> dict | None:
        """The counts if `read` has read them, else None (nothing waits)."""
        return self._counts

    @property
    def overflowed(self) -> bool:
        return self.read()["n_intersections"] > self.capacity


def rasterize(
    means: torch.Tensor,  # [N,3] world
    quats: torch.Tensor,  # [N,4] w x y z, any finite norm (zero = identity)
    scales: torch.Tensor,  # [N,3] >= 0
    opacities: torch.Tensor,  # [N] base opacity in [0, 1]
    colors: torch.Tensor,  # [N,3] RGB, or [N,K,3] SH with K in {1, 4, 9, 16}
    t_means: torch.Tensor,  # [N] temporal centre
    t_scales: torch.Tensor,  # [N] temporal sigma >= 0 (0: a Gaussian alive at no time)
    viewmat: torch.Tensor,  # [4,4] world -> camera, OpenCV axes, finite
    K: torch.Tensor,  # [3,3] intrinsics in pixels, pixel centres at +0.5, finite, fx and fy > 0
    width: int,
    height: int,
    t: float,  # any finite float: used to float64 precision (t - t_means is formed before rounding)
    *,
    background: torch.Tensor | None = None,  # [3]
    near: float = 0.01,
    far: float = 1e10,
    rows: torch.Tensor | None = None,  # int [M]: render these Gaussians only (tomgs.render.alive)
):
    """Render the Gaussians at time t: (image [H,W,3], alpha [H,W,1], meta).

    Opacity at t is tomgs.temporal.opacity_at(opacities, t_means, t_scales, t); a Gaussian below 1/255
    at t is culled in projection and costs no tile work. Differentiable in every tensor input; runs on
    the device of the inputs (CPU or CUDA) in float32. `meta` holds per-Gaussian `radii` [N,2],
    `means2d` [N,2] (call `.retain_grad()` on it for screen-space gradients), `depths`, `conics`,
    `opacities_t`, and counts (ints) `n_visible`, `n_alive` (alive at t), `n_intersections`. N = 0 is fine.

    With `rows` only those Gaussians are rendered, as if the inputs held them alone (ascending rows
    composite ties in the full cloud's order): per-Gaussian work and meta's per-Gaussian outputs
    are [M], and gradients reach the full [N] inputs at those rows (zero elsewhere), without a
    gather of the inputs. A row outside [0, N) raises RenderError; a repeated row renders that
    Gaussian twice, as gathered inputs would (its gradients summed).

    A Gaussian with a non-finite mean, scale, quaternion or temporal window is culled (zero
    gradient). Anything else outside the contract above (an opacity outside [0, 1], a negative
    scale, a non-finite camera or background, fx <= 0, a non-integer size, a non-finite t) raises
    RenderError naming the input; the per-Gaussian checks run inside the projection kernel and come
    back with the intersection count, in the one host sync a frame has anyway.
    """
    image, alpha, meta, _ = render_frame(means, quats, scales, opacities, colors, t_means, t_scales, viewmat, K,
                                         width, height, t, background=background, near=near, far=far, rows=rows)
    return image, alpha, meta


def blend_weights(means, quats, scales, opacities, t_means, t_scales, viewmat, K, width: int, height: int,
                  t: float, *, near: float = 0.01, far: float = 1e10, rows: torch.Tensor | None = None) -> torch.Tensor:
    """[N]: each Gaussian's blend weights alpha_i T_i summed over the frame's pixels (`rasterize`'s
    arguments without colours; with `rows`, 0 for the others): how many pixels' worth of colour it
    gives the image at time t (0 where culled, out of view or hidden behind opaque ones). It is the
    gradient of the image's sum (one channel) with respect to its colour, from the renderer's own
    backward."""
    ones = torch.ones(means.shape[0], 3, device=means.device, requires_grad=True)
    gaussians = [x.detach() for x in (means, quats, scales, opacities)]
    with torch.enable_grad():
        image, _, _ = rasterize(*gaussians, ones, t_means.detach(), t_scales.detach(), viewmat, K, width, height, t,
                                near=near, far=far, rows=rows)
        (grad,) = torch.autograd.grad(image[..., 0].sum(), ones)
    return grad[:, 0]


def render_frame(means, quats, scales, opacities, colors, t_means, t_scales, viewmat, K, width, height, t, *,
                 background=None, near=0.01, far=1e10, rows=None, defer: bool = False):
    """`rasterize` (same arguments) -> (image, alpha, meta, counts). With `defer`, once frames of this
    size have been counted, the frame does not wait for its counts: the host returns while the
    device still projects, meta lacks the counts and `counts` (FrameCounts) reads them, raising
    RenderError for inputs outside the contract; read them before trusting the image or its
    gradients (`counts.overflowed`: render again). Else counts is None and meta has them."""
    t_hi, t_lo = check_scalars(width, height, t, near, far)
    p = prepare_inputs(means, quats, scales, opacities, colors, t_means, t_scales, viewmat, K, width, height, t,
                       background, near, far, torch.float32, fused_sh=True, rows=rows)
    with scope(p.means.device) as wp_device:
        frame = Frame(p.width, p.height, t_hi, t_lo, p.near, p.far, wp_device)
        capacity = key_bounds.capacity(frame)
        image, alpha, meta, _, counts = issue_frame(p, frame, capacity, wait=not (defer and capacity))
    return image, alpha, meta, counts


def issue_frame(p: RasterInputs, frame: Frame, capacity: int, wait: bool, queue_counts: bool = True):
    """A frame of prepared inputs `p` (float32, colours evaluated) issued on `frame.device`, inside its
    runtime.scope: (image [H,W,3] over p's background, alpha [H,W,1], meta, flags [project.NUM_FLAGS]
    int64 on the device, counts).

    `wait`: the frame's one host sync reads the flags (RenderError for inputs outside the contract),
    sizes the sort to the intersection count and remembers it in the bound; meta holds the counts and
    counts is None. Else (`capacity` > 0) nothing waits: the keys are held to `capacity` and sorted
    padded (`_bin_padded`), and counts is a FrameCounts, its copy queued once projection has written
    the flags; or None without `queue_counts` (a frame captured in a CUDA graph, whose caller reads
    `flags` after each replay)."""
    if frame.num_tiles * TILE_SIZE * TILE_SIZE > MAX_THREADS:
        raise RenderError(f"a {frame.width}x{frame.height} image is too large to render in one piece: keep "
                          f"width x height below {MAX_THREADS:,} pixels")
    wrapped = {}  # Warp descriptors of the frame's buffers, by name, built once for the stages that follow
    (means2d, conics, depths, radii, opacities_t, _), ends, flags, lists = _project_frame(p, frame, wrapped)
    # before the sync, what needs no intersection count (the GPU projects meanwhile): the keys,
    # up to the bound of recent frames of this size, and the buffers of the sort and the raster.
    # Fresh buffers every frame: the backward reads ids, and two frames' backwards may be pending.
    n = means2d.shape[0]
    written = write_keys(wrapped, n, ends, frame, capacity, lists)
    ranges = torch.zeros(frame.num_tiles, 2, device=p.means.device, dtype=torch.int32)
    pixels = Image(frame, p.means.device)
    colors = p.colors.contiguous()
    wrapped.update(ranges=wrap(ranges), colors=wrap(colors, wp.vec3))
    counts = None
    if wait:
        stats = _read_flags(flags, p)
        # after it, on a GPU's critical path (idle until issued): the sort, the ranges, the raster
        total = stats[project.FLAG_TOTAL]
        ids, _ = _bin(wrapped, n, ends, frame, total, written, lists)
    else:
        if queue_counts:
            counts = FrameCounts(flags, p, frame, capacity)
        ids, _ = _bin_padded(wrapped, n, ends, frame, written)
    color, trans = Rasterize.apply(means2d, conics, opacities_t, colors, ranges, ids, frame, wrapped, pixels)
    image = color if p.background is None else color + trans * p.background
    meta = dict(radii=radii, means2d=means2d, depths=depths, conics=conics, opacities_t=opacities_t,
                tile_size=TILE_SIZE, width=frame.width, height=frame.height)
    if wait:
        key_bounds.remember(frame, total)
        meta.update(_counts(stats))
    return image, 1.0 - trans, meta, flags, counts


def project_stage(
    means: torch.Tensor,  # [N,3] world
    quats: torch.Tensor,  # [N,4] w x y z, any finite norm
    scales: torch.Tensor,  # [N,3] >= 0
    opacities: torch.Tensor,  # [N] in [0, 1]
    t_means: torch.Tensor,  # [N]
    t_scales: torch.Tensor,  # [N] >= 0
    viewmat: torch.Tensor,  # [4,4] world -> camera
    K: torch.Tensor,  # [3,3]
    width: int,
    height: int,
    t: float,
    *,
    near: float = 0.01,
    far: float = 1e10,
) -> dict[str, torch.Tensor]:
    """Stage 1 alone, as `rasterize` runs it (same checks, same kernel), for tests and tools: per
    Gaussian `means2d` [N,2], `conics` [N,3], `depths` [N], `radii` [N,2] int32, `opacities_t` [N],
    `tiles_touched` [N] int32; a culled Gaussian has zero means2d, conics, radii and tiles touched
    (depths and opacities_t are written for all). means2d, conics and opacities_t are differentiable;
    a culled Gaussian gets zero gradient. See tomgs.render.reference.project_reference."""
    t_hi, t_lo = check_scalars(width, height, t, near, far)
    zeros = torch.zeros_like(means) if isinstance(means, torch.Tensor) else means  # projection reads no colour
    p = prepare_inputs(means, quats, scales, opacities, zeros, t_means, t_scales, viewmat, K, width, height, t,
                       None, near, far, torch.float32)
    with scope(p.means.device) as wp_device:
        frame = Frame(p.width, p.height, t_hi, t_lo, p.near, p.far, wp_device)
        outputs, _, flags, _ = _project_frame(p, frame, {})
        _read_flags(flags, p)
    return dict(zip(("means2d", "conics", "depths", "radii", "opacities_t", "tiles_touched"), outputs))


def bin_stage(
    means2d: torch.Tensor,  # [N,2] float32 pixels
    conics: torch.Tensor,  # [N,3] float32
    opacities_t: torch.Tensor,  # [N] float32
    radii: torch.Tensor,  # [N,2] int32; (0, 0) = culled
    depths: torch.Tensor,  # [N] float32, > 0 wherever a radius is not zero
    tiles_touched: torch.Tensor,  # [N] int32: tiles of each Gaussian's ellipse, as projection counts them
    width: int,
    height: int,
) -> dict[str, torch.Tensor]:
    """Stage 2 alone, as `rasterize` runs it, for tests and tools: `keys` [M] int64 `tile << 32 | float32
    depth bits` sorted, `ids` [M] int32 the Gaussian of each, `ranges` [tiles, 2] int32 each tile's
    [start, end) in them ((0, 0) for an empty tile). See tomgs.render.reference.bin_reference."""
    check_scalars(width, height, 0.0, 0.01, 1e10)
    ends = torch.cumsum(tiles_touched, 0, dtype=torch.int64)
    total = int(ends[-1]) if ends.numel() else 0
    # named: a descriptor does not keep a contiguous copy alive
    means2d, conics, opacities_t, radii, depths = (x.contiguous() for x in (means2d, conics, opacities_t, radii,
                                                                             depths))
    wrapped = dict(means2d=wrap(means2d, wp.vec2), conics=wrap(conics, wp.vec3), opacities_t=wrap(opacities_t),
                   radii=wrap(radii, wp.vec2i), depths=wrap(depths))
    with scope(means2d.device) as wp_device:
        frame = Frame(int(width), int(height), 0.0, 0.0, 0.01, 1e10, wp_device)
        ranges = torch.zeros(frame.num_tiles, 2, device=means2d.device, dtype=torch.int32)
        wrapped["ranges"] = wrap(ranges)
        ids, keys = _bin(wrapped, means2d.shape[0], ends, frame, total)
    ids, keys = ids[:total], keys[:total]
    return dict(keys=keys, ids=ids, ranges=ranges)
