"""The rasterizer's three stages, in pipeline order, each as it launches its Warp kernels:

    project (Project, a torch.autograd.Function) -> binning (write_keys, then sort_and_range: no gradient)
    -> raster (Rasterize, a torch.autograd.Function)

`Frame` is what the stages of one frame share; `kernel_choices` which kernel paths they take. When
each stage runs, what waits for the intersection count and what it is bounded by is the frame layer's
(tomgs.render.frame). Every buffer is a torch tensor handed to Warp without a copy, so torch's allocator
and memory statistics see the whole frame; kernels run on torch's current stream, where the inputs live.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import warp as wp

from tomgs.constants import TILE_SIZE, sort_low_bit
from tomgs.kernels import binning, lanes, project, raster, raster_batched
from tomgs.runtime import NO_ARRAY, indexable, launch, scope, sort_pairs, struct_values, wrap, wrap_part

# The radix sort needs 2 x count slots and counts in int32: 2^30 keeps both inside int32.
MAX_INTERSECTIONS = 2**30


@dataclass(frozen=True)
class Frame:
    """What the stages of one frame share: its size, its time, its planes and the Warp device they run on."""

    width: int
    height: int
    t_hi: float  # t = t_hi + t_lo: t rounded to float32, and the rest rounded to float32
    t_lo: float
    near: float
    far: float
    device: str  # the Warp device its launches go to ("cpu", "cuda:N"), inside a runtime.scope
    # a descriptor of (t_hi, t_lo) float32 [2] in device memory, read in place of the two above (a frame
    # replayed from a CUDA graph, tomgs.render.captured); NO_ARRAY: the scalars hold t
    times: object = field(default=NO_ARRAY, compare=False)
    # a descriptor of int32 [1] in device memory: a frame rendering rows renders only the first this many
    # of them, the rest being padding (a replayed frame's fixed buffer of rows); NO_ARRAY: all of them
    row_count: object = field(default=NO_ARRAY, compare=False)

    @property
    def tiles_x(self) -> int:
        return (self.width + TILE_SIZE - 1) // TILE_SIZE

    @property
    def tiles_y(self) -> int:
        return (self.height + TILE_SIZE - 1) // TILE_SIZE

    @property
    def num_tiles(self) -> int:
        return self.tiles_x * self.tiles_y

    @property
    def key_bits(self) -> int:
        """The bits of a tile key the sort reads: 32 of depth, and the tile's, wide enough that a
        padding key (`padding_key`) is past every tile."""
        return 32 + self.num_tiles.bit_length()

    @property
    def sort_low_bit(self) -> int:
        """The lowest key bit the sort reads: the depth's lower bits are left out (constants.DEPTH_SORT_BITS)."""
        return sort_low_bit(self.width, self.height)

    @property
    def padding_key(self) -> int:
        """A key in `key_bits` that sorts after every key of this frame (a tile >= num_tiles)."""
        return (1 << self.key_bits) - 1


# Host time per frame (a GPU machine's CPU spends 10-60 us per torch op or launch, and a 1M-Gaussian
# temporal frame is host bound): stages pass Warp descriptors along instead of re-wrapping tensors,
# gradients nobody asked for are not materialised, and what needs no intersection count is
# allocated before the frame's one host sync, the tile keys included (into a buffer of a bound kept
# between frames). What each of these saved: docs/notes/rasterizer.md ("Host path").


@dataclass
class KernelChoices:
    """Which kernel paths a frame takes; None picks by device. Set a field of the process's
    `kernel_choices` to compare two paths in one process (tests, A/B timings).

    inline_lanes   visible (or alive) lanes from which a warp runs a stage's long path itself rather
                   than listing its rows for a pass in full warps (tomgs/kernels/lanes.py). None:
                   lanes.INLINE_LANES on CUDA, 1 on a CPU (every thread runs alone: lists would only
                   add passes)
    batched        which kernel pair composites: True the batched pair (raster_batched: a block stages
                   each batch of its tile's list in shared memory), False the per-pixel pair (raster:
                   every thread loads every entry). None: batched on CUDA; a CPU runs one thread at a
                   time, where staging only adds copies, so it keeps the per-pixel pair
    ordered_tiles  blocks take the tiles longest list first, forward and backward. None: on CUDA, where
                   blocks run at once and a long tile started last runs alone at the end; a CPU runs
                   the tiles one by one, in any order alike
    """

    inline_lanes: int | None = None
    batched: bool | None = None
    ordered_tiles: bool | None = None

    def lanes_on(self, device: torch.device) -> int:
        if self.inline_lanes is not None:
            return self.inline_lanes
        return lanes.INLINE_LANES if device.type == "cuda" else 1

    def batched_on(self, device: torch.device) -> bool:
        return device.type == "cuda" if self.batched is None else self.batched

    def ordered_on(self, device: torch.device) -> bool:
        return device.type == "cuda" if self.ordered_tiles is None else self.ordered_tiles


# the process's choices (not thread-safe, like tomgs.render.frame.key_bounds and tomgs.runtime.launch)
kernel_choices = KernelChoices()


class WorkLists:
    """Work lists (tomgs/kernels/lanes.py) of `passes` passes over M rows, one after another on one
    stream: work [WORK_LISTS x capacity] int32, shared (a pass's listed launch has read it before the
    next pass writes it), and counts [lanes.work_counters(passes)] int32, zeroed, each pass its own,
    for one dense launch (a pass asked for again runs inline: its counts are not zeroed again).
    Descriptors do not own their tensors: keep this object until the last launch reading them is queued."""

    def __init__(self, m: int, passes: int, inline: int, device: torch.device):
        self.inline = inline
        self.capacity = lanes.work_capacity(m)
        self.slots = int(lanes.WORK_LISTS) * self.capacity  # a listed launch's size
        self.work = torch.empty(self.slots, device=device, dtype=torch.int32)
        self.counts = torch.zeros(lanes.work_counters(passes), device=device, dtype=torch.int32)
        self._work_d = wrap(self.work)
        self._taken: set[int] = set()

    @staticmethod
    def of(m: int, passes: int, device: torch.device) -> WorkLists | None:
        """Lists for M rows, or None where every lane runs inline (inline lanes 1: nothing is listed)."""
        inline = kernel_choices.lanes_on(device)
        return WorkLists(m, passes, inline, device) if inline > 1 else None

    def take(self, k: int) -> list | None:
        """Pass k's (inline lanes, capacity, work, counts) kernel arguments the first time they are asked
        for, None after; a listed launch takes the last three."""
        if k in self._taken:
            return None
        self._taken.add(k)
        size = lanes.work_counters(1)
        return [self.inline, self.capacity, self._work_d, wrap_part(self.counts, k * size, size)]


def pass_args(lists: WorkLists | None, k: int) -> list:
    """Pass k's (inline lanes, capacity, work, counts) arguments: every lane runs inline (lanes 1, nothing
    listed: no listed launch) without lists or once their pass k has been taken."""
    return (lists and lists.take(k)) or [1, 0, NO_ARRAY, NO_ARRAY]


# the values of the projection kernels' structs, filled with descriptors
CLOUD, VIEW = struct_values(project.Cloud), struct_values(project.View)
PROJECTED, GRADIENTS = struct_values(project.Projected), struct_values(project.Gradients)


class Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, t_means, t_scales, viewmat, K, flags, frame: Frame,
                wrapped: dict, rows: torch.Tensor | None, lists: WorkLists | None):
        """Outputs (means2d [M,2], conics [M,3], depths [M], radii [M,2] int32, opacities_t [M],
        tiles_touched [M] int32) of Gaussians `rows` (int32 [M]; None: all, M = N); their
        descriptors, and the camera's, go into `wrapped` by name. `lists`: work lists for M rows
        (`WorkLists.of`), pass 0 this stage's."""
        n = means.shape[0] if rows is None else rows.shape[0]
        f32 = dict(device=means.device, dtype=torch.float32)
        means2d = torch.empty(n, 2, **f32)
        conics = torch.empty(n, 3, **f32)
        depths = torch.empty(n, **f32)
        opacities_t = torch.empty(n, **f32)
        radii = torch.empty(n, 2, device=means.device, dtype=torch.int32)
        tiles_touched = torch.empty(n, device=means.device, dtype=torch.int32)
        # the Gaussians and the view are bundled once and reused by the backward (their tensors are saved)
        viewmat_d, K_d = wrap(viewmat, wp.mat44), wrap(K, wp.mat33)
        cloud = CLOUD(means=wrap(means, wp.vec3), quats=wrap(quats, wp.vec4), scales=wrap(scales, wp.vec3),
                      opacities=wrap(opacities), t_means=wrap(t_means), t_scales=wrap(t_scales), n=means.shape[0],
                      rows=NO_ARRAY if rows is None else wrap(rows), has_rows=int(rows is not None),
                      row_count=frame.row_count)
        view = VIEW(viewmats=viewmat_d, Ks=K_d, width=frame.width, height=frame.height, tiles_x=frame.tiles_x,
                    tiles_y=frame.tiles_y, t_hi=frame.t_hi, t_lo=frame.t_lo, times=frame.times, near=frame.near,
                    far=frame.far)
        wrapped.update(means2d=wrap(means2d, wp.vec2), conics=wrap(conics, wp.vec3), depths=wrap(depths),
                       radii=wrap(radii, wp.vec2i), opacities_t=wrap(opacities_t),
                       tiles_touched=wrap(tiles_touched), viewmat=viewmat_d, K=K_d)
        out = PROJECTED(means2d=wrapped["means2d"], conics=wrapped["conics"], depths=wrapped["depths"],
                        radii=wrapped["radii"], opacities_t=wrapped["opacities_t"],
                        tiles_touched=wrapped["tiles_touched"])
        # the long path of the outputs in warps holding few alive ones is listed, run in full warps after
        work_d = pass_args(lists, 0)
        launch(project.project_forward, n, device=frame.device, args=[cloud, view, out, wrap(flags), *work_d])
        if work_d[0] > 1:
            launch(project.project_listed, lists.slots, device=frame.device, args=[cloud, view, out, *work_d[1:]])
        ctx.rows = rows
        ctx.descriptors = (cloud, view, wrapped["radii"])
        ctx.save_for_backward(means, quats, scales, opacities, t_means, t_scales, viewmat, K, radii, conics)
        ctx.mark_non_differentiable(depths, radii, tiles_touched)
        ctx.set_materialize_grads(False)  # no zero-filled gradients for depths, radii, tiles (never read)
        return means2d, conics, depths, radii, opacities_t, tiles_touched

    @staticmethod
    def backward(ctx, v_means2d, v_conics, _v_depths, _v_radii, v_opacities_t, _v_tiles):
        means, quats, scales, opacities, t_means, t_scales, viewmat, K, radii, conics = ctx.saved_tensors
        rows = ctx.rows
        n = radii.shape[0]  # M: the Gaussians projected
        camera_grads = ctx.needs_input_grad[6] or ctx.needs_input_grad[7]
        # every row written, or with rows only theirs: the rest stays zero
        fresh = torch.empty_like if rows is None else torch.zeros_like
        v_means, v_quats, v_scales = fresh(means), fresh(quats), fresh(scales)
        v_opacities, v_t_means, v_t_scales = fresh(opacities), fresh(t_means), fresh(t_scales)
        cloud, view, radii_d = ctx.descriptors
        # named, so that a dense copy lives until the launch is queued (a descriptor does not own it)
        v_means2d, v_conics = indexable(v_means2d, conics, n, 2), indexable(v_conics, conics)
        v_opacities_t = indexable(v_opacities_t, conics, n)
        if camera_grads:  # per-Gaussian camera partials only when someone asked
            v_viewmat_parts = torch.empty(n, 4, 4, device=means.device, dtype=torch.float32)
            v_K_parts = torch.empty(n, 4, device=means.device, dtype=torch.float32)
            parts = [wrap(v_viewmat_parts, wp.mat44), wrap(v_K_parts, wp.vec4)]
        else:
            parts = [NO_ARRAY, NO_ARRAY]
        # the visible outputs of warps holding few, run in full warps after
        lists = WorkLists.of(n, 1, means.device)
        work_d = pass_args(lists, 0)
        grads = GRADIENTS(v_means2d=wrap(v_means2d, wp.vec2), v_conics=wrap(v_conics, wp.vec3),
                          v_opacities_t=wrap(v_opacities_t), camera_grads=int(camera_grads),
                          v_means=wrap(v_means, wp.vec3), v_quats=wrap(v_quats, wp.vec4),
                          v_scales=wrap(v_scales, wp.vec3), v_opacities=wrap(v_opacities), v_t_means=wrap(v_t_means),
                          v_t_scales=wrap(v_t_scales), v_viewmat_parts=parts[0], v_K_parts=parts[1])
        with scope(means.device) as device:
            launch(project.project_backward, n, device=device, args=[cloud, view, radii_d, grads, *work_d])
            if work_d[0] > 1:
                launch(project.project_backward_listed, lists.slots, device=device,
                       args=[cloud, view, grads, *work_d[1:]])
        v_viewmat = v_K = None
        if camera_grads:
            v_viewmat = v_viewmat_parts.sum(0)
            fx, fy, cx, cy = v_K_parts.sum(0).unbind()
            zero = torch.zeros_like(fx)
            v_K = torch.stack([fx, zero, cx, zero, fy, cy, zero, zero, zero]).reshape(3, 3)
        return (v_means, v_quats, v_scales, v_opacities, v_t_means, v_t_scales, v_viewmat, v_K, None, None, None, None,
                None)


def write_keys(wrapped: dict, n: int, ends: torch.Tensor, frame: Frame, capacity: int,
               lists: WorkLists | None = None):
    """Stage 2's list, unsorted, in buffers of `capacity` pairs plus the sort's scratch: (keys [2 capacity]
    int64 `tile << 32 | depth bits`, ids [2 capacity] int32 the Gaussian of each), Gaussian i in slots
    [ends[i-1], ends[i]) (`ends` [N] int64 the inclusive scan of tiles touched, binning.tiles_of),
    those below `capacity` only. Needs no intersection count, so it runs before the host sync.

    `wrapped`: descriptors of projection's means2d, conics, opacities_t, radii, depths [N]; those of
    keys and ids go into it (for the stages after the sync, replacing any before). `lists`: the
    frame's work lists (tomgs.render.frame makes them), pass 1 binning's (taken by the call that
    launches: a frame's keys written again, past their bound, run inline); without them every warp
    writes its own.
    """
    keys = torch.empty(2 * capacity, device=ends.device, dtype=torch.int64)  # the sort uses the upper half
    ids = torch.empty(2 * capacity, device=ends.device, dtype=torch.int32)
    wrapped.update(keys=wrap(keys), ids=wrap(ids))
    if capacity:
        # the visible Gaussians of warps holding few are listed, their keys written in full warps after
        work_d = pass_args(lists, 1)
        shared = [wrapped["means2d"], wrapped["conics"], wrapped["opacities_t"], wrapped["radii"], wrapped["depths"],
                  wrap(ends), frame.tiles_x, frame.tiles_y, capacity, wrapped["keys"], wrapped["ids"]]
        launch(binning.write_tile_keys, n, device=frame.device, args=[*shared, *work_d])
        if work_d[0] > 1:
            launch(binning.write_tile_keys_listed, lists.slots, device=frame.device, args=[*shared, *work_d[1:]])
    return keys, ids


def sort_and_range(wrapped: dict, written: tuple[torch.Tensor, torch.Tensor], count: int, frame: Frame):
    """Sort the first `count` pairs of `written` (keys, ids) and fill `wrapped`'s ranges from them."""
    keys, ids = written
    sort_pairs(keys, ids, count, frame.key_bits, frame.sort_low_bit)
    launch(binning.tile_ranges, count, device=frame.device,
           args=[wrapped["keys"], count, frame.num_tiles, wrapped["ranges"]])
    return ids, keys


class Image:
    """The raster stage's per-pixel outputs, allocated before the frame's host sync (they need no
    intersection count): color [H,W,3], trans [H,W,1] (transmittance), end [H,W] int32 (one past each
    pixel's last composited list entry), with their descriptors."""

    def __init__(self, frame: Frame, device: torch.device):
        self.color = torch.empty(frame.height, frame.width, 3, device=device, dtype=torch.float32)
        self.trans = torch.empty(frame.height, frame.width, 1, device=device, dtype=torch.float32)
        self.end = torch.empty(frame.height, frame.width, device=device, dtype=torch.int32)
        self.color_d, self.state = wrap(self.color, wp.vec3), [wrap(self.trans, ndim=2), wrap(self.end)]


class Rasterize(torch.autograd.Function):
    @staticmethod
    def _kernels(device: torch.device) -> tuple:
        """(forward, backward) for a frame on `device`, each (kernel, threads a tile, block width)."""
        pixels = TILE_SIZE * TILE_SIZE
        if not kernel_choices.batched_on(device):
            return (raster.raster_forward, pixels, pixels), (raster.raster_backward, pixels, pixels)
        # a CPU block is one thread unless Warp runs cooperative blocks (wp.config.enable_cpu_blocks);
        # the width is passed as it will run, so each width gets its own recorded launch. The batched
        # backward runs a thread per two pixels.
        blocks = device.type == "cuda" or wp.config.enable_cpu_blocks
        pairs = raster_batched.PAIR_THREADS
        return ((raster_batched.raster_forward_batched, pixels, pixels if blocks else 1),
                (raster_batched.raster_backward_batched, pairs, pairs if blocks else 1))

    @staticmethod
    def forward(ctx, means2d, conics, opacities_t, colors, ranges, ids, frame: Frame, wrapped: dict, image: Image):
        """(color [H,W,3], trans [H,W,1]) of `image`, composited; `wrapped` holds the descriptors of
        means2d, conics, opacities_t, colors, ranges and ids (built before the frame's host sync)."""
        # the list, the per-Gaussian inputs and the per-pixel state, shared with the backward
        order = NO_ARRAY
        if kernel_choices.ordered_on(means2d.device):
            tile_order = torch.argsort(ranges[:, 0] - ranges[:, 1]).to(torch.int32)  # [tiles], the longest first
            order = wrap(tile_order)
            ctx.tile_order = tile_order  # alive while the backward's launch reads it
        shared = [wrapped["ranges"], wrapped["ids"], wrapped["means2d"], wrapped["conics"], wrapped["opacities_t"],
                  wrapped["colors"], frame.width, frame.height, frame.tiles_x, order]
        forward_launch, ctx.backward_launch = Rasterize._kernels(means2d.device)  # the backward: the pair's
        kernel, per_tile, block = forward_launch
        launch(kernel, frame.num_tiles * per_tile, device=frame.device, block_dim=block,
               args=[*shared, image.color_d, *image.state])
        ctx.frame = frame
        ctx.descriptors = (shared, image.state)
        ctx.save_for_backward(means2d, conics, opacities_t, colors, ranges, ids, image.trans, image.end)
        ctx.set_materialize_grads(False)  # an unused image or alpha passes None, not a zero-filled tensor
        return image.color, image.trans

    @staticmethod
    def backward(ctx, v_color, v_trans):
        means2d, _, _, colors, _, _, trans, _ = ctx.saved_tensors
        frame = ctx.frame
        shared, state = ctx.descriptors
        kernel, per_tile, block = ctx.backward_launch
        n = means2d.shape[0]
        # accumulated by atomics, so zeroed: the projection's three in one fill (read by its backward
        # only), the colours' alone, so that a leaf's .grad takes it without a copy
        v_means2d, v_conics, v_opacities_t = means2d.new_zeros(n, 6).split((2, 3, 1), 1)
        v_opacities_t = v_opacities_t.squeeze(1)
        v_colors = colors.new_zeros(n, 3)
        # named: alive until the launch is queued
        v_color = indexable(v_color, trans, frame.height, frame.width, 3)
        v_trans = indexable(v_trans, trans)
        with scope(means2d.device) as wp_device:
            launch(kernel, frame.num_tiles * per_tile, device=wp_device, block_dim=block,
                   args=[*shared, *state, wrap(v_color, wp.vec3), wrap(v_trans, ndim=2),
                         wrap(v_means2d, wp.vec2), wrap(v_conics, wp.vec3), wrap(v_opacities_t),
                         wrap(v_colors, wp.vec3)])
        return v_means2d, v_conics, v_opacities_t, v_colors, None, None, None, None, None
