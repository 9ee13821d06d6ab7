"""A training step with no host in it: the whole step captured as one CUDA graph and replayed.

A GPU machine's CPU spends ~3 ms issuing an eager step (~100 torch operations and Warp launches),
more than the kernels of a 1M-Gaussian step take, so training at that size was host bound. Here the
step (activations, projection, binning, raster, the L1 + D-SSIM loss, the backward, SeenAdam's update
and the densifier's statistics) is one graph; the host per step draws the frame, counts Adam's step,
writes both into device memory in one launch (`kernels/step.py`'s set_step) and replays:

    step = CapturedStep(trainer)        # once; `unsupported(trainer)` says when it cannot serve
    if step.ready():
        psnr = step.run(k, collect, growing)  # 0-d: the frame's PSNR, NaN when the step was dropped (below)

Memory of its own, in capacities that outlive many densifications: the parameters, Adam's moments and
the densifier's statistics live in buffers of `rows` rows (`rows_capacity`: the model's size plus a
quarter, at most the cap, while densification may add Gaussians; the model's size after), whose first
N rows the model, the optimiser and the densifier hold as views (their attributes are set to them,
`_bind`), and whose other rows are padding the projection culls (opacity 0), that Adam and the
statistics never take. When densification, pruning, a checkpoint or an edit gives them new tensors, the
next step copies them in (no capture) and binds the views again; a model past the rows (or under half
of them) is captured again at its new capacity. The frame's tile keys are held to the renderer's bound
of recent frames of this size (as a deferred frame's, tomgs.render.frame), scaled by the model's growth
since those frames, plus a quarter; captured again once frames may need more, or the bound fell to
under half of them. The first EAGER_STEPS steps run eagerly: their frames teach the bound.

Nothing on the step's path waits for the device. The graph itself decides whether the update applies
(`kernels/step.py`'s judge_step: the frame's keys held its whole list, its inputs kept the renderer's
contract) and records the frame's flags and PSNR in rings of RING steps; the host copies the flags to
itself every RING / 2 steps and reads them RING / 2 steps later: the bound learns each total, a
frame that passed its keys counts as `dropped` (it updated nothing; an eager step renders it again,
waiting, which a graph cannot), and a contract flag raises RenderError. The PSNRs go to the sampler
through the trainer's lagged flush, as an eager step's do.

On a CPU nothing is captured: each step issues the same work from Python (tests run the whole logic
there). Inputs outside its reach (`unsupported`) fall back to the trainer's eager step, as do the
steps before a frame of this size was counted.
"""

from __future__ import annotations

import math

import torch
import warp as wp

from tomgs.errors import RenderError
from tomgs.kernels import adam, project
from tomgs.kernels import step as kernels
from tomgs.metrics import training_loss
from tomgs.model import PARAM_NAMES
from tomgs.render.captured import key_bound, known_to_warp, no_collection, remember_total, time_table, timed_frame
from tomgs.render.frame import MAX_INTERSECTIONS, issue_frame
from tomgs.render.inputs import prepare_inputs
from tomgs.runtime import launch, scope, wrap, wrap_rows

RING = 16  # steps whose flags and PSNR the device keeps; the host copies the flags every RING // 2 steps
ROWS_HEADROOM = 4  # rows held beyond the model's N: N / ROWS_HEADROOM (a densification's growth, mostly)
KEYS_HEADROOM = 4  # tile keys held beyond what frames may need: that / KEYS_HEADROOM
# the first steps run eagerly, waiting where their frames overflowed their keys: the renderer's bound of this
# size learns the clip's views before the first capture takes its keys from it
EAGER_STEPS = 16
NEAR, FAR = 0.01, 1e10  # the trainer's frames' planes (rasterize's defaults)
# the padding rows' stored values: opacity 0 (sigmoid of the logit), culled by projection before anything else
PADDING = dict(means=0.0, quats=(1.0, 0.0, 0.0, 0.0), log_scales=0.0, opacity_logits=-1e4, sh_dc=0.0, sh_rest=0.0,
               t_means=0.0, log_t_scales=0.0)
CONTRACT_NAMES = {project.FLAG_OPACITIES: "opacities", project.FLAG_SCALES: "scales",
                  project.FLAG_T_SCALES: "t_scales", project.FLAG_K: "K", project.FLAG_VIEWMAT: "viewmat",
                  project.FLAG_BACKGROUND: "background", project.FLAG_ROWS: "rows"}


def unsupported(trainer) -> str | None:
    """Why `trainer`'s steps cannot be captured (a phrase), or None when they can."""
    if not trainer.sparse_adam:
        return "dense Adam (sparse_adam off)"
    if trainer.alive is not None:
        return "the alive index (alive_index on)"
    if trainer.weights is not None or trainer.alpha_targets is not None:
        return "per-pixel loss weights or alpha targets (a layer's fit)"
    if trainer.frames.device.type != trainer.device.type:
        return "frames kept on the host (too large for the GPU's memory)"
    return None


def rows_capacity(n: int, cap: int, growing: bool) -> int:
    """The rows a capture holds for a model of `n` Gaussians under a cap of `cap`: while densification may
    still add Gaussians (`growing`), n plus n / ROWS_HEADROOM, at most the cap (the cap is exact); else n."""
    return max(n, min(cap, n + n // ROWS_HEADROOM)) if growing else n


def rows_fit(rows: int, n: int, growing: bool) -> bool:
    """Whether a capture of `rows` rows serves a model of `n` Gaussians: it holds them, and no more than
    twice as many while it may grow, 1/16 more once it cannot (each row costs the per-Gaussian kernels a
    few loads, and its memory stays held; a prune of a few rows is not worth a capture)."""
    return n <= rows <= (2 * n if growing else n + n // 16)


def keys_needed(bound: int, growth: float) -> int:
    """The tile keys a frame may need: the renderer's bound of recent frames of this size (`bound`), scaled
    by how much the model grew since the frames it learned from (`growth`, its size now over theirs; a
    densification's clones add tiles, its splits fewer than their sources held), never below the bound."""
    return max(bound, math.ceil(bound * growth))


def keys_capacity(needed: int) -> int:
    """The tile keys a capture's frames hold for frames needing `needed`: a quarter more (a clip's views
    differ in their totals by tens of percent, and the bound follows the last few), at most what the sort
    takes."""
    return min(MAX_INTERSECTIONS, needed + needed // KEYS_HEADROOM)


def keys_fit(keys: int, needed: int) -> bool:
    """Whether frames holding `keys` tile keys serve frames that may need `needed` (`keys_needed`): they hold
    that many, and no more than twice as many (the padded sort costs what the keys hold; a capture costs
    two rehearsals, so the keys do not follow every turn of the bound)."""
    return 0 < keys and needed <= keys <= 2 * needed


class CapturedStep:
    """`trainer`'s training step (tomgs.train.trainer.Trainer) replayed from a CUDA graph; see the module
    docstring. `trainer` must pass `unsupported`. Reads the trainer's model, optimizer and densifier at
    every step (any of them may be replaced between steps)."""

    def __init__(self, trainer):
        self.trainer = trainer
        device = self.device = trainer.device
        self._captured = device.type == "cuda"
        self.rows = 0  # the rows its buffers hold (0: none yet)
        self.keys = 0  # the tile keys its frames hold (0: none yet)
        self.captures = 0  # how many times it took new capacities (captured them, on a GPU)
        self.dropped = 0  # steps whose frame passed its keys, read so far (their updates did not apply)
        self.steps = 0  # steps run
        f32 = dict(device=device, dtype=torch.float32)
        # what the host writes before each step (set_step) and what the graph leaves for the host: outside
        # the graph's memory, so they stay where they are across captures
        self._ints = torch.zeros(kernels.STEP_INTS, device=device, dtype=torch.int64)
        self._rates = torch.ones(3, adam.SLOTS, **f32)
        self._ok = torch.zeros(1, device=device, dtype=torch.int32)
        self._flags_ring = torch.zeros(RING, project.NUM_FLAGS, device=device, dtype=torch.int64)
        self._psnr_ring = torch.full((RING,), float("nan"), **f32)
        self._host_flags = torch.zeros(RING, project.NUM_FLAGS, dtype=torch.int64,
                                       pin_memory=self._captured)
        self._times = time_table(trainer.times, device)  # [T,2]
        self._empty = torch.empty(0, 1, **f32)  # an unused Adam slot
        self._frame = timed_frame(trainer.width, trainer.height, NEAR, FAR, device, self._times[0])  # its bound's key
        # (slot, keys, Gaussians) of the steps since the flags were last copied
        self._pending: list[tuple[int, int, int]] = []
        self._copied = None  # (event or None, _pending's entries) of the flags' last copy, not yet read
        self._counted_size = 0  # the model's size at the last step whose total the bound learned
        self._declined = 0  # steps it was not ready for (`ready`)
        self._buffers = None  # {"params" | "exp_avg" | "exp_avg_sq": {name: [rows, ...]}, "statistics": {...}}
        # (model, optimizer, densifier, {name: view}, {key: view}, optimizer.state) as last bound
        self._bound = None
        self._leaves = None  # the graph's leaves: the parameters' buffers, requiring grad
        self._trained: list[str] = []  # the parameters the step updates (those its loss reaches), slot order
        self._sh_degree = None  # the model's SH degree at capture
        self._graph = None

    def ready(self) -> bool:
        """Whether the next step can be captured: after EAGER_STEPS steps it declined (the trainer runs
        them eagerly), once a frame of this size has been counted and while the model has Gaussians."""
        if self._declined >= EAGER_STEPS and key_bound(self._frame)[0] > 0 and len(self.trainer.model) > 0:
            return True
        self._declined += 1
        return False

    def run(self, k: int, collect: bool, growing: bool) -> torch.Tensor:
        """Train one step on frame `k`, the densifier's statistics taking it when `collect`; `growing`: whether
        densification may still add Gaussians (rows held for them). Returns 0-d float32, the frame's PSNR
        (NaN when the step's update was dropped), where the device writes it (a view that RING later steps
        overwrite: stack or copy it before then)."""
        trainer = self.trainer
        model = trainer.model
        n = len(model)
        capture = False
        if self._stale() or not rows_fit(self.rows, n, growing):
            if not rows_fit(self.rows, n, growing):
                self._allocate(rows_capacity(n, trainer.config.max_gaussians or n, growing))
                capture = True
            self._bind()
        if not self._counted_size:  # the eager steps before the first capture counted this model's frames
            self._counted_size = n
        needed = keys_needed(key_bound(self._frame)[0], n / self._counted_size)
        if not keys_fit(self.keys, needed):
            self.keys = keys_capacity(needed)
            capture = True
        if model.sh_degree != self._sh_degree or self._leaves is None or (self._captured and self._graph is None):
            capture = True
        slot = self.steps % RING
        if capture:
            self._set(k, slot, apply=False, collect=False, rates=None)
            self._capture()
        self._set(k, slot, apply=True, collect=collect, rates=self._advance())
        if self._captured:
            self._graph.replay()
        else:
            self._issue()
        self.steps += 1
        self._pending.append((slot, self.keys, n))
        if len(self._pending) == RING // 2:
            self._copy_flags()
        return self._psnr_ring[slot]

    def settle(self) -> None:
        """Read the flags of every step run so far (waiting for the device): `dropped` counts them all."""
        self._copy_flags()
        self._read_flags()

    # ------------------------------------------------------------------------------- buffers and views

    def _stale(self) -> bool:
        """Whether the model, the optimizer or the densifier holds tensors other than the views bound."""
        bound = self._bound
        trainer = self.trainer
        if bound is None or bound[0] is not trainer.model or bound[1] is not trainer.optimizer \
                or bound[2] is not trainer.densifier or bound[5] is not trainer.optimizer.state:
            return True
        model, densifier = trainer.model, trainer.densifier
        return any(getattr(model, name) is not view for name, view in bound[3].items()) or \
            any(getattr(densifier, key) is not view for key, view in bound[4].items())

    def _allocate(self, rows: int) -> None:
        """Buffers of `rows` rows for the model's parameters, their moments and the densifier's statistics
        (the last capture's memory goes first)."""
        self._graph = self._leaves = None
        self._buffers = None
        params = self.trainer.model.parameters_by_name()
        shaped = {name: dict(size=(rows, *p.shape[1:]), device=self.device, dtype=p.dtype)
                  for name, p in params.items()}
        self._buffers = dict(
            params={name: torch.empty(**kw) for name, kw in shaped.items()},
            exp_avg={name: torch.zeros(**kw) for name, kw in shaped.items()},
            exp_avg_sq={name: torch.zeros(**kw) for name, kw in shaped.items()},
            statistics={key: torch.zeros(rows, device=self.device, dtype=value.dtype)
                        for key, value in self.trainer.densifier.statistics().items()})
        self.rows = rows
        self._bound = None

    @torch.no_grad()
    def _bind(self) -> None:
        """Copy the model's parameters, their Adam moments and the densifier's statistics into the
        buffers' first N rows (the rest padding), and hand their owners views of those rows."""
        trainer = self.trainer
        model, optimizer, densifier = trainer.model, trainer.optimizer, trainer.densifier
        buffers = self._buffers
        n = len(model)
        groups = {group["name"]: group for group in optimizer.param_groups}
        views = {}
        for name, param in model.parameters_by_name().items():
            held = buffers["params"][name]
            _take(held, param.detach(), PADDING[name])
            view = torch.nn.Parameter(held[:n], requires_grad=param.requires_grad)
            state = optimizer.state.pop(param, None) or {}
            moments = {}
            for key in ("exp_avg", "exp_avg_sq"):
                _take(buffers[key][name], state.get(key), 0.0)
                moments[key] = buffers[key][name][:n]
            optimizer.state[view] = dict(state, step=state.get("step", torch.tensor(0.0)), **moments)
            groups[name]["params"] = [view]
            setattr(model, name, view)
            views[name] = view
        statistics = {}
        for key, value in densifier.statistics().items():
            held = buffers["statistics"][key]
            _take(held, value, 0.0)
            statistics[key] = held[:n]
            setattr(densifier, key, statistics[key])
        self._bound = (model, optimizer, densifier, views, statistics, optimizer.state)

    # ----------------------------------------------------------------------------------- the step

    def _set(self, k: int, slot: int, apply: bool, collect: bool, rates) -> None:
        """Write the step's values where the graph reads them (one launch); `rates` (lr, bias1, bias2_sqrt)
        lists of the trained slots, None to keep the last (a rehearsal's: nothing is updated)."""
        args = [int(k), int(slot), int(apply), int(collect)]
        if rates is None:
            args += [adam.vec_slots(*[1.0] * adam.SLOTS)] * 3
        else:
            args += [adam.vec_slots(*(values + [1.0] * (adam.SLOTS - len(values)))) for values in rates]
        with scope(self.device) as device:
            launch(kernels.set_step, 1, device=device,
                   args=[*args, wrap(self._ints), wrap(self._rates, adam.vec_slots)])

    def _advance(self) -> tuple[list, list, list]:
        """Count the step in Adam's state of each trained parameter: (lr, bias1, bias2_sqrt) lists, slot order."""
        optimizer = self.trainer.optimizer
        groups = {group["name"]: group for group in optimizer.param_groups}
        rates = [optimizer.advance(groups[name], groups[name]["params"][0]) for name in self._trained]
        return [r[0] for r in rates], [r[1] for r in rates], [r[2] for r in rates]

    def _capture(self) -> None:
        """The step at the current capacities: on a GPU, two rehearsals on a side stream (Warp's modules
        loaded, launches recorded), then the capture; on a CPU one rehearsal. A rehearsal changes nothing
        (set_step's apply is 0): it finds the parameters the loss reaches."""
        self._graph = None
        self._sh_degree = self.trainer.model.sh_degree
        self.captures += 1
        if not self._captured:
            self._leaves = {name: held.detach().requires_grad_() for name, held in self._buffers["params"].items()}
            self._issue()
            return
        current = torch.cuda.current_stream(self.device)
        side = torch.cuda.Stream(self.device)
        side.wait_stream(current)
        with torch.cuda.device(self.device), torch.cuda.stream(side):
            for _ in range(2):
                self._leaves = {name: held.detach().requires_grad_() for name, held in self._buffers["params"].items()}
                self._issue()
        current.wait_stream(side)
        # fresh leaves for the capture: the rehearsals' gradient accumulators were made on the side stream
        self._leaves = {name: held.detach().requires_grad_() for name, held in self._buffers["params"].items()}
        # thread-local capture: the checkpoint writer's thread may be copying a state to the host meanwhile
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.device(self.device), no_collection(), \
                torch.cuda.graph(graph, pool=torch.cuda.graph_pool_handle(), stream=side,
                                 capture_error_mode="thread_local"), known_to_warp(self.device, thread_local=True):
            self._issue()
        self._graph = graph

    def _issue(self) -> None:
        """The step from the values set_step wrote: the frame, the loss, the backward, Adam and the
        statistics, issued (captured, on a GPU). Sets `_trained`."""
        trainer = self.trainer
        leaves, buffers = self._leaves, self._buffers
        k = self._ints[:1]
        with torch.enable_grad():
            inputs = trainer.model.render_inputs_of(leaves)
            times = self._times.index_select(0, k)[0]
            p = prepare_inputs(**inputs, viewmat=trainer.viewmats.index_select(0, k)[0], K=trainer.K,
                               width=trainer.width, height=trainer.height, t=0.0, background=None, near=NEAR, far=FAR,
                               dtype=torch.float32, fused_sh=True)
            frame = timed_frame(p.width, p.height, p.near, p.far, self.device, times)
            image, _, meta, flags, _ = issue_frame(p, frame, self.keys, wait=False, queue_counts=False)
            target = trainer.frames.index_select(0, k)[0].float() / 255.0
            loss, measured = training_loss(image, target, trainer.config.ssim_weight)
            wanted = [leaves[name] for name in PARAM_NAMES] + [meta["means2d"]]
            *grads, v_means2d = torch.autograd.grad(loss, wanted, allow_unused=True)
        grads = dict(zip(PARAM_NAMES, grads))
        self._trained = [name for name in PARAM_NAMES if grads[name] is not None and leaves[name].numel() > 0]
        in_view = torch.empty(self.rows, device=self.device, dtype=torch.bool)
        observed = torch.empty(self.rows, device=self.device, dtype=torch.bool)
        beta1, beta2 = trainer.optimizer.defaults["betas"]
        slots = [(buffers["params"][name], grads[name].contiguous(), buffers["exp_avg"][name],
                  buffers["exp_avg_sq"][name]) for name in self._trained]
        arrays = [wrap_rows(t) for slot in slots for t in slot] + [wrap(self._empty)] * (4 * (adam.SLOTS - len(slots)))
        with scope(self.device) as device:
            launch(kernels.judge_step, 1, device=device, args=[
                wrap(flags), wrap(measured), wrap(self._ints), int(self.keys), wrap(self._ok),
                wrap(self._flags_ring), wrap(self._psnr_ring)])
            launch(kernels.seen_rows, self.rows, device=device, args=[
                wrap(meta["radii"], wp.vec2i), wrap(self._ok), wrap(self._ints), wrap(in_view), wrap(observed)])
            launch(adam.adam_seen_rows_read, self.rows, device=device, args=[
                *arrays, wrap(in_view), wrap(self._rates, adam.vec_slots), beta1, beta2,
                trainer.optimizer.defaults["eps"]])
        if v_means2d is not None:
            trainer.densifier.accumulate(buffers["statistics"], v_means2d, None, observed, p.width, p.height)

    # ------------------------------------------------------------------------- what the host reads later

    def _copy_flags(self) -> None:
        """Read the last copy of the flags (queued RING // 2 steps ago: long done), then queue a copy of the
        steps' since."""
        self._read_flags()
        if not self._pending:
            return
        event = None
        self._host_flags.copy_(self._flags_ring, non_blocking=self._captured)
        if self._captured:
            event = torch.cuda.Event()
            event.record(torch.cuda.current_stream(self.device))
        self._copied, self._pending = (event, self._pending), []

    def _read_flags(self) -> None:
        """The copied steps' totals go to the renderer's bound; a frame past its keys counts as dropped, one
        outside the contract raises RenderError."""
        if self._copied is None:
            return
        event, steps = self._copied
        self._copied = None
        if event is not None:
            event.synchronize()
        rows = self._host_flags.tolist()
        for slot, keys, size in steps:
            flags = rows[slot]
            refused = [name for flag, name in CONTRACT_NAMES.items() if flags[flag]]
            if refused:
                raise RenderError(f"a training frame's {', '.join(refused)} left the renderer's contract (non-finite "
                                  "or out of range: the fit diverged)")
            total = flags[project.FLAG_TOTAL]
            remember_total(self._frame, total)
            self._counted_size = size
            if total > keys:
                self.dropped += 1


def _take(held: torch.Tensor, value: torch.Tensor | None, padding) -> None:
    """`held` [rows, ...] takes `value` [N, ...] in its first N rows (zeros for None) and `padding` (a row's
    value, broadcast) in the rest. A view of its own first rows is already there."""
    n = 0 if value is None else value.shape[0]
    if value is None:
        pass
    elif value.data_ptr() != held.data_ptr():
        held[:n].copy_(value)
    held[n:] = torch.as_tensor(padding, dtype=held.dtype, device=held.device)
