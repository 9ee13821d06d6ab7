"""The alive index: which Gaussians may be alive at each frame, so that a frame's work follows what
lives in it rather than the whole cloud (docs/design.md "Principles": no work for the dead).

Frames, in time order, are grouped into buckets of F consecutive frames; bucket b lists every
Gaussian whose alive window (tomgs.temporal.alive_window, widened by GATHER_SLACK so that float32
projection never finds one alive outside it) holds one of b's frame times, as CSR:
`offsets` on the host (a frame's rows are a slice, no device sync), `ids` on the device, ascending
within a bucket (so a subset sorts its tile keys in the order the full cloud would, and composites
exactly as it does). A frame's rows are its bucket's list: a superset of the Gaussians alive at its
time; projection still culls exactly.

Bucket size: a Gaussian whose window spans w of the clip sits in about w B + 1 of B buckets, so
small buckets cost entries and large ones render Gaussians dead at the frame. F is the smallest
power of two whose index holds at most ENTRIES_PER_GAUSSIAN x N entries (int32 ids: 32 bytes per
Gaussian at most, 40 with its bucket range; its parameters, gradients and Adam moments take 256 at SH
degree 0, 976 at degree 3), except that a larger F is taken when it renders within WORK_TOLERANCE as
much (a clip of Gaussians alive throughout gets one bucket, its rows are then all of them: `rows`
returns None).

Training moves the windows every step; `TrainingIndex` keeps the index exact under Adam: see there.
"""

from __future__ import annotations

import functools
import math
import weakref
from dataclasses import dataclass

import numpy as np
import torch

from tomgs import temporal
from tomgs.constants import ALPHA_MIN
from tomgs.model import activated_opacities, activated_t_scales

# relative and absolute widening of an indexed alive window (tomgs.temporal.alive_radius's slack):
# float32 projection rounds o(t) near 1/255 either way, the index must never be the narrower
GATHER_SLACK = 1e-3
ENTRIES_PER_GAUSSIAN = 8  # the index's memory bound: entries <= this x N
WORK_TOLERANCE = 1 / 16  # a larger bucket is taken when a frame's rows grow by at most this share
CHUNK_ENTRIES = 1 << 22  # entries built at a time: the build's scratch memory, whatever N is


def windows(opacities: torch.Tensor, t_means: torch.Tensor, t_scales: torch.Tensor,
            alpha_min: float = ALPHA_MIN) -> tuple[torch.Tensor, torch.Tensor]:
    """(first, last) float64 [N]: the clip times between which o_i(t) >= alpha_min, widened by
    GATHER_SLACK (first > last: alive at no time), from the renderer's inputs [N]."""
    return temporal.alive_window(opacities.double(), t_means.double(), t_scales.double(), alpha_min,
                                 slack=GATHER_SLACK)


@dataclass
class AliveIndex:
    """Buckets of frames and the Gaussians that may be alive in each (CSR). Build with `build`."""

    n: int  # Gaussians indexed
    size: int  # frames per bucket (the last bucket may hold fewer)
    bucket_of: np.ndarray  # int64 [T]: the bucket of each frame position
    times: torch.Tensor  # float64 [T] on the device: the frame times, ascending (bucket b: [b size, (b+1) size))
    offsets: list  # [B + 1] ints: bucket b's ids are ids[offsets[b]:offsets[b + 1]]
    ids: torch.Tensor  # [E] int32 (int64 from 2^31 Gaussians), ascending within a bucket
    b_first: torch.Tensor  # [N] int32: the first bucket listing each Gaussian
    b_last: torch.Tensor  # [N] int32: the last one (< b_first: listed nowhere)

    @property
    def entries(self) -> int:
        return self.offsets[-1]

    @property
    def nbytes(self) -> int:
        """Device memory the index holds (ids, the per-Gaussian bucket ranges, the frame times)."""
        return sum(t.numel() * t.element_size() for t in (self.ids, self.b_first, self.b_last, self.times))

    @property
    def most_rows(self) -> int:
        """The rows of the longest bucket: the most a frame renders."""
        return max((b - a for a, b in zip(self.offsets[:-1], self.offsets[1:])), default=0)

    @property
    def num_buckets(self) -> int:
        return len(self.offsets) - 1

    def rows(self, position: int) -> torch.Tensor | None:
        """The Gaussians that may be alive at frame `position` (int [M], a view of `ids`), or None
        when its bucket lists all of them (render the cloud as it is, no rows)."""
        b = int(self.bucket_of[position])
        start, end = self.offsets[b], self.offsets[b + 1]
        return None if end - start == self.n else self.ids[start:end]

    def covers(self, first: torch.Tensor, last: torch.Tensor, rows: torch.Tensor | None) -> torch.Tensor:
        """bool [M] on the device: every frame time inside [first_i, last_i] (float64 [M], the
        windows of Gaussians `rows`, None: all) lies in a bucket that lists Gaussian i. No sync.
        (Training checks this in tomgs/kernels/alive.py's `reach_escapes`; this is its torch form.)"""
        start, stop = _frame_span(first, last, self.times)
        b_first = (self.b_first if rows is None else self.b_first.index_select(0, rows)).long()
        b_last = (self.b_last if rows is None else self.b_last.index_select(0, rows)).long()
        return (stop <= start) | ((start // self.size >= b_first) & ((stop - 1) // self.size <= b_last))


def _frame_span(first: torch.Tensor, last: torch.Tensor, times: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(start, stop) int64 [N]: the ascending frame `times` [T] inside [first_i, last_i] are
    times[start_i:stop_i] (none when stop <= start: dead at every frame; NaN windows too, which
    projection culls)."""
    bad = torch.isnan(first) | torch.isnan(last)
    start = torch.searchsorted(times, first.masked_fill(bad, math.inf), side="left")
    stop = torch.searchsorted(times, last.masked_fill(bad, -math.inf), side="right")
    return start, stop


def build(first: torch.Tensor, last: torch.Tensor, times, budget: float = ENTRIES_PER_GAUSSIAN) -> AliveIndex:
    """The index of Gaussians with alive windows [first_i, last_i] (float64 [N], first > last or
    NaN: never alive) over frames at `times` ([T] clip times, any order): bucket b lists Gaussian i
    when one of b's frame times lies in its window. Host syncs: three."""
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    n, device, count = int(first.shape[0]), first.device, len(times)
    order = np.argsort(times, kind="stable")
    sorted_times = torch.as_tensor(times[order], device=device)
    start, stop = _frame_span(first.double(), last.double(), sorted_times)
    listed = stop > start
    # how many Gaussians start and stop at each frame position: all the bucket sizes need (one sync)
    starts_at, stops_at = _spans_histogram(start, stop, listed, count)
    sizes = [1 << i for i in range(max(count - 1, 0).bit_length())] + [max(count, 1)]  # 1, 2, 4, .., one bucket
    options = [(size, *_entries_and_work(starts_at, stops_at, size, count)) for size in sizes]
    fitting = [o for o in options if o[1] <= budget * max(n, 1)] or options[-1:]  # one bucket holds <= N
    least = min(o[2] for o in fitting)
    size = max(o[0] for o in fitting if o[2] <= least * (1 + WORK_TOLERANCE))

    buckets = (count + size - 1) // size
    bucket_of = np.empty(count, dtype=np.int64)
    bucket_of[order] = np.arange(count) // size
    b_first = torch.where(listed, start // size, 1)  # unlisted: 1 > 0
    b_last = torch.where(listed, (stop - 1) // size, 0)
    positions = np.arange(count + 1)
    # Gaussians listed in bucket b: those starting in a bucket <= b less those ending in one < b
    first_in, last_in = np.zeros(buckets + 1, dtype=np.int64), np.zeros(buckets, dtype=np.int64)
    np.add.at(first_in, positions // size, starts_at)  # starts_at[count] is 0: no Gaussian starts there
    np.add.at(last_in, (positions[1:] - 1) // size, stops_at[1:])
    per_bucket = np.cumsum(first_in[:buckets]) - np.cumsum(last_in) + last_in
    offsets = [0] + np.cumsum(per_bucket).tolist()
    ids = torch.empty(offsets[-1], dtype=torch.int32 if n < 2**31 else torch.int64, device=device)
    small = torch.int32 if buckets < 2**31 else torch.int64
    b_first, b_last = b_first.to(small), b_last.to(small)
    _fill(ids, b_first, b_last, torch.tensor(offsets[:-1], dtype=torch.int64, device=device), buckets)
    return AliveIndex(n=n, size=size, bucket_of=bucket_of, times=sorted_times, offsets=offsets, ids=ids,
                      b_first=b_first, b_last=b_last)


def _spans_histogram(start: torch.Tensor, stop: torch.Tensor, listed: torch.Tensor,
                     count: int) -> tuple[np.ndarray, np.ndarray]:
    """(starts_at, stops_at) int64 [count + 1] on the host: of the listed Gaussians (bool [N]), how
    many have start_i = f and stop_i = f (frame positions, _frame_span's), for f in 0..count."""
    past = count + 1  # the unlisted fall past the end and are dropped
    both = torch.stack([torch.where(listed, start, past), torch.where(listed, stop, past)])
    counts = torch.stack([torch.bincount(row, minlength=past + 1) for row in both]).cpu().numpy()
    return counts[0, :past], counts[1, :past]


def _entries_and_work(starts_at: np.ndarray, stops_at: np.ndarray, size: int, count: int) -> tuple[int, int]:
    """(entries, frames rendered) of the index in buckets of `size` frames, from the histograms of
    `_spans_histogram`: Gaussian i sits in buckets start_i // size .. (stop_i - 1) // size, and is
    rendered at each frame of them, of which the last bucket may hold fewer."""
    f = np.arange(count + 1, dtype=np.int64)
    first, last = f // size, (f[1:] - 1) // size  # bucket of a start at f, of a stop at f (f >= 1)
    entries = int((stops_at[1:] * last).sum() - (starts_at * first).sum() + starts_at.sum())
    work = int((stops_at[1:] * np.minimum((last + 1) * size, count)).sum() - (starts_at * first * size).sum())
    return entries, work


def _fill(ids: torch.Tensor, b_first: torch.Tensor, b_last: torch.Tensor, starts: torch.Tensor, buckets: int) -> None:
    """Write each Gaussian i into buckets b_first_i .. b_last_i of `ids` (bucket b from starts[b]),
    ascending within a bucket: Gaussians in chunks of about CHUNK_ENTRIES entries, each chunk's
    entries stably sorted by bucket (the narrowest integer key) and placed after the earlier chunks'."""
    device = ids.device
    per_gaussian = (b_last.long() - b_first.long() + 1).clamp_min(0)
    ends = torch.cumsum(per_gaussian, 0)
    total = len(ids)
    marks = torch.tensor(list(range(CHUNK_ENTRIES, total, CHUNK_ENTRIES)), dtype=torch.int64, device=device)
    bounds = [0] + torch.searchsorted(ends, marks, side="right").tolist() + [len(ends)]
    # the entries before each chunk, read in one sync (not two a chunk: the host would wait each time)
    inner = torch.tensor(bounds[1:-1], device=device, dtype=torch.int64)
    before = [0] + torch.where(inner > 0, ends[(inner - 1).clamp_min(0)], 0).tolist() + [total]
    placed = torch.zeros(buckets, dtype=torch.int64, device=device)  # entries written so far per bucket
    key = torch.int16 if buckets < 2**15 else torch.int32
    for g0, g1, e0, e1 in zip(bounds[:-1], bounds[1:], before[:-1], before[1:]):
        if g1 <= g0:
            continue
        counts = per_gaussian[g0:g1]
        entries = e1 - e0
        gaussian = torch.repeat_interleave(torch.arange(g0, g1, device=device), counts, output_size=entries)
        # entry j of Gaussian i is in bucket b_first_i + j: its base minus where its run starts, plus j
        base = torch.repeat_interleave(b_first[g0:g1].long() - (torch.cumsum(counts, 0) - counts), counts,
                                       output_size=entries)
        bucket, order = torch.sort((base + torch.arange(entries, device=device)).to(key), stable=True)
        # where each bucket's run begins in the sorted entries (a search, not a histogram: a GPU's
        # bincount into a few bins serialises on its atomics)
        runs = torch.searchsorted(bucket, torch.arange(buckets + 1, device=device, dtype=key))
        # bucket b's entries of this chunk go after those of the earlier chunks
        shift = starts + placed - runs[:-1]
        ids[shift[bucket.long()] + torch.arange(entries, device=device)] = gaussian[order].to(ids.dtype)
        placed += runs[1:] - runs[:-1]


def index_of(opacities: torch.Tensor, t_means: torch.Tensor, t_scales: torch.Tensor, times,
             budget: float = ENTRIES_PER_GAUSSIAN) -> AliveIndex:
    """The index of a fixed cloud (the renderer's inputs [N]) over frames at `times` [T]."""
    return build(*windows(opacities, t_means, t_scales), times, budget)


# -- training: an index that stays exact while Adam moves the windows ------------------------------

# Headroom, in steps of each parameter's learning rate, added to the windows a rebuilt index lists
# (beyond the one step a rebuild allows anyway). Less lists fewer dead Gaussians per frame, more
# outgrow their buckets. 300 steps of a 30-frame synthetic clip, 33% alive per frame, SeenAdam read a
# step late: 0 -> 43.6% listed per frame, 12 rebuilds (5 of them densification's); 2 -> 44.6%, 10;
# 4 -> 45.8%, 10; 8 -> 48.1%, 7. Dense Adam read at once: 64-67% listed, 6-9 rebuilds, whatever it is.
HEADROOM_STEPS = 2.0
MOVER_SHARE = 1 / 32  # movers (rendered at every frame) beyond this share of the cloud: rebuild
REBUILD_EVERY = 200  # steps: a rebuild also narrows the windows that shrank since the last one
TEMPORAL = ("t_means", "log_t_scales", "opacity_logits")  # the parameters an alive window depends on


@functools.lru_cache(maxsize=8)
def _bias_factor(beta1: float, beta2: float) -> float:
    """sup over steps t >= 1 of sqrt(1 - beta2^t) / (1 - beta1^t): Adam's bias corrections scale a
    step by at most this (1 for the default betas). Past 10^6 steps beta1^t < 1e-4 for beta1 <= 0.99999."""
    t = np.arange(1, 10**6 + 1, dtype=np.float64)
    return max(1.0, float(np.max(np.sqrt(1 - beta2**t) / (1 - beta1**t)))) * (1 + 1e-4)


def adam_reach(param: torch.Tensor, group: dict, state: dict, rows: torch.Tensor | None, *,
               dense: bool, spikes: int) -> torch.Tensor:
    """float64 [M]: how far Adam can move rows `rows` (None: all) of the 1-D parameter `param` in
    `spikes` steps with any gradients and then, for `dense` Adam, any number with zero gradient
    (SeenAdam leaves a row alone then), from each row's moments.

    An Adam step is lr m^ / (sqrt(v^) + eps), at most F lr |m| / sqrt(v) with F = `_bias_factor`.
    Write r = |m| / sqrt(v) for a row now, q = beta1 / sqrt(beta2), c = (1 - beta1)^2 / (1 - beta2):
    - a step with zero gradient (coasting) scales r by q exactly, so coasting from r moves a row at
      most F lr q r / (1 - q) in all;
    - a step with any gradient g gives, by Cauchy-Schwarz over (old moments, g), r' <= sqrt(q^2 r^2
      + c) <= q r + sqrt(c) (one spike from rest: 3.16 learning rates for the default betas);
    so with r_0 = r, r_j = q r_(j-1) + sqrt(c): F lr (r_1 + .. + r_s + [dense] q r_s / (1 - q)).
    The bound is consistent under coasting (a coasted row's new bound plus the way it moved is its
    old bound), so a row the index does not look at again stays inside what it was checked for.
    Plus float32 rounding of the updates (1e-3 relative, 1e-5 (1 + |p|) absolute)."""
    scale, q, root_c = _adam_constants(group)
    p = param.detach() if rows is None else param.detach().index_select(0, rows)
    rounding = 1e-5 * (1 + p.double().abs())
    if scale == 0:  # a learning rate of 0: the parameter stays, whatever its moments
        return rounding
    if "exp_avg" in state:
        m = (state["exp_avg"] if rows is None else state["exp_avg"].index_select(0, rows)).abs()
        v = state["exp_avg_sq"] if rows is None else state["exp_avg_sq"].index_select(0, rows)
        r = torch.where(m == 0, 0.0, m / v.sqrt()).double()  # inf where v underflowed: listed everywhere
    else:
        r = torch.zeros(p.shape, dtype=torch.float64, device=p.device)
    moved = torch.zeros_like(r)
    for _ in range(spikes):
        r = q * r + root_c
        moved += r
    if dense:
        moved += q / (1 - q) * r
    return scale * moved + rounding


def _adam_constants(group: dict) -> tuple[float, float, float]:
    """(F lr (1 + 1e-3), q, sqrt(c)) of an Adam parameter group (`adam_reach`); ValueError for
    what its bound does not cover."""
    beta1, beta2 = group["betas"]
    if group.get("weight_decay", 0) or group.get("amsgrad", False) or not beta1 < math.sqrt(beta2) or beta1 > 0.99999:
        raise ValueError("the alive index bounds plain Adam steps (no weight decay or amsgrad, beta1 < sqrt(beta2))")
    return (_bias_factor(beta1, beta2) * group["lr"] * (1 + 1e-3), beta1 / math.sqrt(beta2),
            (1 - beta1) / math.sqrt(1 - beta2))


def _temporal_groups(model, optimizer) -> dict:
    """name -> (parameter, its group, its Adam state) for the temporal parameters."""
    params = model.parameters_by_name()
    return {g["name"]: (params[g["name"]], g, optimizer.state.get(params[g["name"]], {}))
            for g in optimizer.param_groups if g.get("name") in TEMPORAL}


def reach_reference(model, optimizer, rows: torch.Tensor | None, *, spikes: int, dense: bool,
                    headroom: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """(first, last) float64 [M]: the widest alive windows rows `rows` (None: all) of `model` can
    reach in `spikes` steps with any gradient and then coasting (`adam_reach`, plus `headroom`
    learning rates): the torch form of tomgs/kernels/alive.py's `reach_window`, which tests hold
    to it."""
    move = {name: adam_reach(param, group, state, rows, dense=dense, spikes=spikes) + headroom * group["lr"]
            for name, (param, group, state) in _temporal_groups(model, optimizer).items()}
    take = (lambda x: x.detach()) if rows is None else (lambda x: x.detach().index_select(0, rows))
    opacities = activated_opacities(take(model.opacity_logits).double() + move["opacity_logits"])
    t_scales = activated_t_scales(take(model.log_t_scales).double() + move["log_t_scales"])
    first, last = temporal.alive_window(opacities, take(model.t_means).double(), t_scales, slack=GATHER_SLACK)
    return first - move["t_means"], last + move["t_means"]


class TrainingIndex:
    """The alive index of a model under training, exact at every step: `rows(k)` lists every Gaussian
    alive at frame k's time for the parameters as they are when frame k renders.

    Rows a step does not render get exactly zero gradient (with or without the index: dead at the
    frame, projection culls them), so under dense Adam they coast and under SeenAdam they stay.
    After each optimiser step, `check` bounds for the rows the step gave a gradient (rendered and
    in view), the windows they can reach before the index next looks (`adam_reach`: by
    coasting on a CPU, where the check is read at once; on a GPU it is read once the next frame's
    render is issued (`settle`, waiting only for a copy queued a step before), so the bound allows
    one more step with any gradient, `lookahead`), and finds those that reach a frame
    outside their buckets. The rows it does not look at stay inside by the bound's consistency.
    Those it finds become movers, rendered at every frame until the next rebuild (a few rows each,
    where rebuilding costs O(N)). A rebuild lists each Gaussian over the windows the check would
    allow plus one more arbitrary step (a row's first step after it never makes it a mover) and
    HEADROOM_STEPS learning rates.

    Rebuilt when the model's parameters are replaced (densification, pruning, opacity reset, a
    checkpoint loaded), when the temporal learning rates change, when movers pass MOVER_SHARE of
    the cloud, and every REBUILD_EVERY steps."""

    def __init__(self, times, *, dense: bool, lookahead: bool, headroom: float = HEADROOM_STEPS,
                 rebuild_every: int = REBUILD_EVERY, budget: float = ENTRIES_PER_GAUSSIAN):
        self.times = np.asarray(times, dtype=np.float64)
        self.dense, self.lookahead = bool(dense), bool(lookahead)
        self.headroom, self.rebuild_every, self.budget = float(headroom), int(rebuild_every), budget
        self.index: AliveIndex | None = None
        self.movers: torch.Tensor | None = None  # sorted Gaussian ids rendered at every frame
        self.stale = True
        self.pending = None  # (rows, escaped positions [cap], count on the host, event): not read yet
        self.built_at = 0
        self.rebuilds = 0
        self._params: tuple = ()  # weak references to the indexed parameters
        self._lrs: tuple = ()

    def _bound(self, model, optimizer, spikes: int, headroom: float) -> tuple[object, list]:
        """tomgs/kernels/alive.py's `Bound` of the model and optimiser, and the tensors it points at
        (held until the launch is queued)."""
        import warp as wp

        from tomgs.kernels import alive as kernels
        from tomgs.runtime import struct_values, wrap

        groups = _temporal_groups(model, optimizer)
        if len({tuple(group["betas"]) for _, group, _ in groups.values()}) > 1:
            raise ValueError("the alive index's kernel takes one pair of Adam betas for the temporal parameters")
        held, has, scale, room = [], [], [], []
        q = root_c = 0.0
        for name in TEMPORAL:
            param, group, state = groups[name]
            scale_i, q, root_c = _adam_constants(group)
            present = "exp_avg" in state
            held += [param.detach(), state["exp_avg"] if present else param.detach(),
                     state["exp_avg_sq"] if present else param.detach()]  # the parameter: a stand-in, unread
            has.append(int(present))
            scale.append(scale_i)
            room.append(headroom * group["lr"])
        t_means, m_t, v_t, log_t_scales, m_s, v_s, opacity_logits, m_o, v_o = (wrap(t) for t in held)
        bound = struct_values(kernels.Bound)(
            t_means=t_means, log_t_scales=log_t_scales, opacity_logits=opacity_logits, m_t=m_t, v_t=v_t, m_s=m_s,
            v_s=v_s, m_o=m_o, v_o=v_o, has_moments=wp.vec3i(*has), scale=wp.vec3d(*scale), headroom=wp.vec3d(*room),
            q=q, root_c=root_c, spikes=int(spikes), dense=int(self.dense), slack=GATHER_SLACK)
        return bound, held

    def reach(self, model, optimizer, spikes: int, headroom: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
        """(first, last) float64 [N]: the windows every Gaussian of `model` can reach in `spikes`
        steps with any gradient, then coasting, widened by `headroom` learning rates (one launch of
        tomgs/kernels/alive.py; `reach_reference` in torch)."""
        from tomgs.kernels import alive as kernels
        from tomgs.runtime import launch, scope, wrap

        n, device = len(model), model.t_means.device
        first = torch.empty(n, dtype=torch.float64, device=device)
        last = torch.empty(n, dtype=torch.float64, device=device)
        bound, held = self._bound(model, optimizer, spikes, headroom)
        with scope(device) as wp_device:
            launch(kernels.reach_windows, n, device=wp_device, args=[bound, wrap(first), wrap(last)])
        del held
        return first, last

    def _current(self, model, optimizer, iteration: int) -> bool:
        params = model.parameters_by_name()
        lrs = tuple(g["lr"] for g in optimizer.param_groups if g.get("name") in TEMPORAL)
        same = (len(self._params) == len(TEMPORAL)
                and all(ref() is params[name] for ref, name in zip(self._params, TEMPORAL)) and lrs == self._lrs)
        return same and not self.stale and iteration - self.built_at < self.rebuild_every

    def rows(self, k: int, model, optimizer, iteration: int) -> torch.Tensor | None:
        """The Gaussians of `model` that may be alive at frame k (int64 [M] ascending, as the
        densifier's statistics take them; None: all), rebuilding the index first when it is due."""
        if self.index is None or not self._current(model, optimizer, iteration):
            self.rebuild(model, optimizer, iteration)
        rows = self.index.rows(k)
        if rows is None:
            return None
        if self.movers is None:
            return rows.long()
        return torch.unique(torch.cat([rows, self.movers]).long())  # sorted, and a mover listed here once

    @torch.no_grad()
    def rebuild(self, model, optimizer, iteration: int) -> None:
        # one arbitrary step beyond what the checks allow, so a row's first step after the rebuild
        # (a spike from rest: three learning rates, and under dense Adam the coasting after it)
        # never makes it a mover
        spikes = self.lookahead + 1
        self.index = build(*self.reach(model, optimizer, spikes, self.headroom), self.times, self.budget)
        params = model.parameters_by_name()
        self._params = tuple(weakref.ref(params[name]) for name in TEMPORAL)
        self._lrs = tuple(g["lr"] for g in optimizer.param_groups if g.get("name") in TEMPORAL)
        self.movers, self.stale, self.pending, self.built_at = None, False, None, iteration
        self.rebuilds += 1

    @torch.no_grad()
    def check(self, model, optimizer, rows: torch.Tensor | None, moved: torch.Tensor) -> None:
        """After the optimiser's step: find the rows a step rendered (`rows`, None: all) and gave a
        gradient (`moved`, bool [M]: in view) that now reach a frame outside their buckets. Read at
        once, or at `settle` (lookahead)."""
        from tomgs.kernels import alive as kernels
        from tomgs.runtime import launch, scope, wrap

        index = self.index
        if index is None or self.stale or len(model) != index.n or index.entries == index.num_buckets * index.n:
            return  # nothing to check, or every Gaussian listed everywhere (a static fit): none can escape
        device = model.t_means.device
        checked = torch.arange(index.n, dtype=torch.int32, device=device) if rows is None else rows.to(torch.int32)
        if len(checked) == 0:
            return
        out = torch.empty(len(checked), dtype=torch.bool, device=device)
        count = torch.zeros(1, dtype=torch.int32, device=device)
        bound, held = self._bound(model, optimizer, int(self.lookahead), 0.0)
        with scope(device) as wp_device:
            launch(kernels.reach_escapes, len(checked), device=wp_device, args=[
                wrap(checked), wrap(moved), bound, wrap(index.times), index.size, wrap(index.b_first),
                wrap(index.b_last), wrap(out), wrap(count)])
        del held
        room = int(MOVER_SHARE * index.n) - (0 if self.movers is None else len(self.movers))
        where = (torch.nonzero_static(out, size=room, fill_value=0).squeeze(1) if room > 0  # no sync
                 else torch.empty(0, dtype=torch.int64, device=device))
        event = None
        if count.is_cuda:
            count = count.to("cpu", non_blocking=True)
            event = torch.cuda.Event()
            event.record()
        self.pending = (rows, where, count, event)
        if not self.lookahead:
            self.settle()

    def settle(self) -> None:
        """Read the last check (on a GPU: after a host sync, so the copy is there and nothing waits)
        and list its escapees at every frame; too many: rebuild instead."""
        if self.pending is None:
            return
        rows, where, count, event = self.pending
        self.pending = None
        if event is not None:
            event.synchronize()
        count = int(count[0])
        if count == 0:
            return
        if count > len(where):
            self.stale = True
            return
        escaped = where[:count] if rows is None else rows.index_select(0, where[:count])
        escaped = escaped.to(self.index.ids.dtype)
        self.movers = escaped.unique() if self.movers is None else torch.unique(torch.cat([self.movers, escaped]))
        # listed at every frame now: their bucket range is all of them, so later checks pass them
        self.index.b_first[escaped] = 0
        self.index.b_last[escaped] = self.index.num_buckets - 1


def pays_on(device) -> bool:
    """Whether a training step renders its frame's indexed rows (`rasterize(rows=)`) rather than every
    Gaussian on `device` (where projection culls the dead ones). On a CPU, whose kernels pay for every
    Gaussian, it does: benchmarks/alive_index.py, 100k Gaussians 15% alive at 160x90, a step 56.5 ms
    against 63.4 without (torch gathers of the rows, before the kernels read them in place: 59.0).
    On the H100 (4M Gaussians, 15% alive, 854x480) it loses even with the kernels reading the rows in
    place: a step 8.93 ms against 7.32, frames 587 against 653 fps, rendering 18.3% of the rows for
    13.2% alive (`alive_index.py --device cuda`). Storing the cloud in time order, so that a frame's
    rows lie in runs, did not change that (an indexed step 3.95-4.54 ms
    against 3.30-3.50 rendering all; indexed frames 624-678 fps against 778-934 before): scattered
    rows are not what the index costs there. (Rendering a fixed cloud: `pays_for_sequence`.)"""
    return torch.device(device).type != "cuda"


# frames of one cloud a GPU sequence renders before its index has paid for its build (pays_for_sequence)
SEQUENCE_FRAMES = 32


def pays_for_sequence(device, frames: int) -> bool:
    """Whether `render_sequence` renders `frames` frames of one cloud from its index (built once for
    them). On a CPU it does (`pays_on`). On the H100 an indexed frame of a fitted DAVIS clip (5M
    Gaussians, 10-21% alive, 854x480) took 0.3-0.38 ms less than one of every Gaussian (kite-surf
    0.93-0.98 against 1.29 ms, camel 1.48-1.54 against 1.86: benchmarks/render_speed.py),
    while the build takes ~7 ms: it pays from a few tens of frames (SEQUENCE_FRAMES), not for one.
    (On a machine whose host set the pace, ~1.7 ms a frame either way, a light clip lost 3% with it.)"""
    return pays_on(device) or int(frames) >= SEQUENCE_FRAMES
