"""Adaptive density control (3DGS clone / split / prune) with a cap, plus TOM-GS's temporal pruning.

Talks to the renderer only through `meta` (screen-space gradients and radii), and keeps Adam's
moments aligned with the rows it keeps, copies and adds (new rows start with zero moments).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import warp as wp

from tomgs.constants import ALPHA_MIN
from tomgs.geometry import quat_to_rotmat
from tomgs.model import PARAM_NAMES, GaussianModel, stored_opacities, stored_scales
from tomgs.temporal import peak_opacity_at


@dataclass(frozen=True)
class DensifySettings:
    """The densification strategy's knobs, its own (as gsplat's strategies hold theirs), read once from a
    TrainConfig (`of`): the cap; densify every `interval` steps inside [start, stop) of the run's progress;
    `threshold` the view-space gradient that makes a Gaussian hot; clone below `percent_dense` of the scene
    extent, split above; `share_opacity`: a clone's or split's pair share its opacity; prune below
    `prune_opacity`, and (`temporal`) what is alive at no training frame; the 3DGS opacity reset every
    `opacity_reset_interval` steps (0: off)."""

    cap: int | None
    start: float
    stop: float
    interval: int
    threshold: float
    percent_dense: float
    share_opacity: bool
    prune_opacity: float
    temporal: bool
    opacity_reset_interval: int

    @classmethod
    def of(cls, config, device_type: str) -> "DensifySettings":
        """The settings of TrainConfig `config` (its cap resolved) on a `device_type` device."""
        return cls(config.max_gaussians, config.densify_start_fraction, config.densify_stop_fraction,
                   config.densify_interval, config.threshold(device_type), config.percent_dense,
                   config.shares_opacity(device_type), config.prune_opacity, config.temporal,
                   config.opacity_reset_interval)


class Densifier:
    def __init__(self, config, extent: float, num_gaussians: int, device, seed: int = 0, times=None):
        """`config`: a TrainConfig, its cap resolved (DensifySettings.of); `times`: the clip times of the
        training frames ([T]; None: any time in [0, 1]), at which a Gaussian must be alive somewhere to be kept."""
        self.settings = DensifySettings.of(config, torch.device(device).type)
        self.times = None if times is None else torch.as_tensor(sorted(times), dtype=torch.float32, device=device)
        self.extent = extent
        self.generator = torch.Generator(device=device).manual_seed(seed + 1)
        self.reset_stats(num_gaussians, device)
        self.limit = self.settings.cap  # the most Gaussians now: the cap, or a stage's (tomgs.train.growth)
        self.capped = False  # at the limit
        self.stopped = False  # growth ended by the quality's price (tomgs.train.growth)
        self.changed_at = 0  # the iteration of the last densification, prune or opacity reset
        self.densified_at = 0  # the iteration of the last densification

    def reset_stats(self, n: int, device) -> None:
        self.grad_sum = torch.zeros(n, device=device)
        self.seen = torch.zeros(n, device=device)

    def statistics(self) -> dict[str, torch.Tensor]:
        """The per-step statistics by attribute name, float [N] each, which `accumulate` adds to: a
        captured training step (tomgs.train.captured_step) holds them in memory of its own and puts
        views of it in these attributes."""
        return dict(grad_sum=self.grad_sum, seen=self.seen)

    def observe(self, meta: dict, visible: torch.Tensor) -> None:
        """Accumulate the view-space positional gradient of the Gaussians visible in this frame
        (`visible`: bool [N], the rasterizer's radii > 0), in NDC units, and count the view. A render
        of some Gaussians only names them in meta['rows'] (int [M]; its means2d are [M,2]): their rows
        take its statistics."""
        grad = meta["means2d"].grad
        if grad is None:
            return
        rows = meta.get("rows")
        self.accumulate(self.statistics(), grad, None if rows is None else rows.long().contiguous(), visible,
                        meta["width"], meta["height"])

    @staticmethod
    def accumulate(statistics: dict[str, torch.Tensor], grad: torch.Tensor, rows: torch.Tensor | None,
                   visible: torch.Tensor, width: int, height: int) -> None:
        """`statistics` (`statistics()`'s layout, float [N] each) take a frame of `width` x `height`: grad
        [M,2] the projected means' gradient (pixels), rows int64 [M] the Gaussian of each (None: M = N),
        visible bool [N] the Gaussians that count. One launch (tomgs/kernels/densify.py)."""
        from tomgs.kernels.densify import observe_view_gradients
        from tomgs.runtime import NO_ARRAY, launch, scope, wrap

        grad, visible = grad.contiguous(), visible.contiguous()  # held until the launch is queued
        with scope(grad.device) as device:
            launch(observe_view_gradients, grad.shape[0], device=device, args=[
                wrap(grad, wp.vec2), NO_ARRAY if rows is None else wrap(rows), wrap(visible),
                wp.vec2(width / 2.0, height / 2.0), wrap(statistics["grad_sum"]), wrap(statistics["seen"])])

    # -- the schedule (gsplat's strategy shape: the trainer calls these two around backward) -------

    def collecting(self, progress: float) -> bool:
        """Whether this step's screen-space gradients are wanted: until densification stops
        (`densify_stop_fraction` of the run), the cap is reached or growth is stopped."""
        return progress < self.settings.stop and not self.capped and not self.stopped

    def may_grow(self, progress: float) -> bool:
        """Whether densification may still add Gaussians: before the end of its window, under the limit."""
        return self.collecting(progress) and self.settings.start < self.settings.stop

    def step_pre_backward(self, meta: dict, progress: float) -> None:
        """Before loss.backward(): keep the gradient of the projected means when collecting."""
        if self.collecting(progress):
            meta["means2d"].retain_grad()

    def step_post_backward(self, model: GaussianModel, optimizer, meta: dict, visible: torch.Tensor,
                           iteration: int, progress: float) -> None:
        """After loss.backward() and the optimiser's step (as gsplat's strategies run): collect this
        step's statistics (`visible`: bool [N], the Gaussians it reached; the projected means'
        gradient, which the optimiser does not touch), then, at `iteration` (the step just taken,
        counted from 1) and `progress` (by iterations or by the wall-clock budget, whichever is
        further): densify every `densify_interval` steps inside [densify_start_fraction,
        densify_stop_fraction) until the limit (the cap, or a stage's), else prune every 10 intervals;
        reset opacities every `opacity_reset_interval` steps while densifying. A prune inside the window that frees rows under
        a reached cap lets densification go on into them: Gaussians the optimiser has faded out at
        every frame (windows shrunk between frames) give their room to those with high gradients."""
        if self.collecting(progress):
            self.observe(meta, visible)
        self.schedule(model, optimizer, iteration, progress)

    def schedule(self, model: GaussianModel, optimizer, iteration: int, progress: float) -> None:
        """`step_post_backward`'s decisions, once the step's statistics are in (a captured step
        accumulates them on the device): densify, prune, reset opacities when due."""
        c = self.settings
        if self.due(iteration, progress) and not self.capped and not self.stopped:
            self.step(model, optimizer)
            self.changed_at = self.densified_at = iteration
        elif iteration % (10 * c.interval) == 0:
            if self.prune(model, optimizer) and progress < c.stop and len(model) < self.limit:
                self.capped = False
            self.reset_stats(len(model), model.means.device)
            self.changed_at = iteration
        if c.opacity_reset_interval and iteration % c.opacity_reset_interval == 0 and progress < c.stop:
            self.reset_opacity(model, optimizer)
            self.changed_at = iteration

    def due(self, iteration: int, progress: float) -> bool:
        """Every `densify_interval` iterations while the run's progress (by iterations or by
        wall-clock budget) is inside [densify_start_fraction, densify_stop_fraction)."""
        c = self.settings
        return c.start <= progress < c.stop and iteration % c.interval == 0

    def step(self, model: GaussianModel, optimizer: torch.optim.Optimizer) -> dict:
        """Clone small and split large Gaussians with high gradients (until the limit), then prune.
        Returns counts of what happened."""
        c = self.settings
        n = len(model)
        grads = self.grad_sum / self.seen.clamp_min(1.0)
        hot = grads >= c.threshold
        scales = model.scales.detach()
        max_scale = scales.amax(-1)
        room = max(self.limit - n, 0)
        clone = hot & (max_scale <= c.percent_dense * self.extent)
        split = hot & ~clone
        clone, split = _limit(clone, split, room, grads)
        self.capped = self.capped or room == 0 or bool((clone.sum() + 2 * split.sum()) >= room)

        params = {k: v.detach() for k, v in model.parameters_by_name().items()}
        if c.share_opacity and (clone.any() or split.any()):
            params["opacity_logits"] = torch.where(clone | split, shared_opacity_logits(params["opacity_logits"]),
                                                   params["opacity_logits"])
        added = {k: [params[k][clone]] for k in PARAM_NAMES}
        if split.any():
            samples = self._split(params, scales, split)
            for k in PARAM_NAMES:
                added[k].append(samples[k])
        # a split replaces its source; a clone's source keeps its row, with the shared opacity where it is shared
        _apply(model, optimizer, ~split, {k: torch.cat(v) for k, v in added.items()}, replace=params)
        pruned = self.prune(model, optimizer)
        self.reset_stats(len(model), params["means"].device)
        return dict(cloned=int(clone.sum()), split=int(split.sum()), pruned=pruned, total=len(model))

    def prune(self, model: GaussianModel, optimizer) -> int:
        """Remove Gaussians that are transparent, or dead at every training frame (with `times`; else
        over the whole clip [0, 1]). Returns how many went."""
        return self.remove(model, optimizer, self._prunable(model))

    def remove(self, model: GaussianModel, optimizer, rows: torch.Tensor) -> int:
        """Remove the Gaussians `rows` (bool [N]) and their Adam moments; returns how many went. The
        statistics keep their rows: `reset_stats` before the next step that collects."""
        count = int(rows.sum())
        if count:
            _apply(model, optimizer, ~rows, None)
        return count

    @torch.no_grad()
    def _prunable(self, model: GaussianModel) -> torch.Tensor:
        remove = model.opacities < self.settings.prune_opacity
        if self.settings.temporal:
            peak = model.peak_opacity(0.0, 1.0) if self.times is None else \
                peak_opacity_at(model.opacities, model.t_means, model.t_scales, self.times)
            remove |= peak < ALPHA_MIN
        return remove

    def _split(self, params, scales: torch.Tensor, mask: torch.Tensor) -> dict[str, torch.Tensor]:
        """Two samples per selected Gaussian, drawn from it (`scales` [N,3]: the model's), each with
        scales / 1.6."""
        rot = quat_to_rotmat(params["quats"][mask]).repeat(2, 1, 1)
        scales = scales[mask].repeat(2, 1)
        noise = torch.randn(scales.shape, generator=self.generator, device=scales.device)
        out = {k: params[k][mask].repeat(2, *([1] * (params[k].dim() - 1))) for k in PARAM_NAMES}
        out["means"] = out["means"] + (rot @ (scales * noise)[..., None])[..., 0]
        out["log_scales"] = stored_scales(scales / 1.6)
        return out

    def reset_opacity(self, model: GaussianModel, optimizer) -> None:
        """The 3DGS opacity reset (off in TOM-GS; kept for the ablation)."""
        logit_001 = stored_opacities(0.01)
        new = torch.minimum(model.opacity_logits.detach(), torch.full_like(model.opacity_logits, logit_001))
        keep = torch.ones(len(model), dtype=torch.bool, device=new.device)
        tensors = {k: v.detach() for k, v in model.parameters_by_name().items()}
        tensors["opacity_logits"] = new
        _apply(model, optimizer, keep, None, replace=tensors, reset_moments=("opacity_logits",))

    def state_dict(self) -> dict:
        return dict(grad_sum=self.grad_sum, seen=self.seen, capped=self.capped, limit=self.limit,
                    generator=self.generator.get_state(), changed_at=self.changed_at, stopped=self.stopped,
                    densified_at=self.densified_at)

    def load_state_dict(self, state: dict) -> None:
        self.grad_sum, self.seen, self.capped = state["grad_sum"], state["seen"], state["capped"]
        self.generator.set_state(state["generator"])
        self.changed_at = int(state.get("changed_at", 0))  # checkpoints before it: as if unchanged
        self.stopped = bool(state.get("stopped", False))  # checkpoints before it: growth never stopped
        self.densified_at = int(state.get("densified_at", 0))
        self.limit = state.get("limit", self.settings.cap)  # checkpoints before it: the cap


def shared_opacity_logits(logits: torch.Tensor) -> torch.Tensor:
    """The opacity logits [N] of the two Gaussians that share one of opacity sigmoid(logits) [N]: each a' =
    1 - sqrt(1 - a), so that 1 - (1 - a')^2 = a. With s = sqrt(1 - a), a' / (1 - a') = a / (s (1 + s)), in
    softplus terms finite for every finite logit (a float32 sigmoid rounds to 0 or 1 far sooner)."""
    log_s = -0.5 * torch.nn.functional.softplus(logits)  # log sqrt(1 - a)
    return -torch.nn.functional.softplus(-logits) - log_s - torch.log1p(torch.exp(log_s))


def _limit(clone: torch.Tensor, split: torch.Tensor, room: int, grads: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Keep clones and splits within `room` new Gaussians (a split adds one net): the cap is exact.
    Under the cap, the candidates with the largest gradients go first."""
    n_clone, n_split = int(clone.sum()), int(split.sum())
    if n_clone + n_split <= room:
        return clone, split
    keep_split = min(n_split, room // 2)
    keep_clone = min(n_clone, room - keep_split)
    return _largest(clone, keep_clone, grads), _largest(split, keep_split, grads)


def _largest(mask: torch.Tensor, k: int, score: torch.Tensor) -> torch.Tensor:
    """The `k` entries of `mask` with the largest `score`."""
    out = torch.zeros_like(mask)
    if k > 0:
        candidates = torch.nonzero(mask).squeeze(-1)
        out[candidates[torch.topk(score[candidates], k).indices]] = True
    return out


def _apply(model: GaussianModel, optimizer, keep: torch.Tensor, added: dict | None, replace: dict | None = None,
           reset_moments: tuple = ()) -> None:
    """Rows `keep` of every parameter, then `added` rows; Adam moments follow (zeros for new rows)."""
    old = model.parameters_by_name()
    base = replace if replace is not None else {k: v.detach() for k, v in old.items()}
    new = {k: base[k][keep] if added is None else torch.cat([base[k][keep], added[k]]) for k in PARAM_NAMES}
    model.replace(new)
    fresh = model.parameters_by_name()
    for group in optimizer.param_groups:
        name = group["name"]
        param = old[name]
        state = optimizer.state.pop(param, None)
        group["params"] = [fresh[name]]
        if state:
            for key in ("exp_avg", "exp_avg_sq"):
                moment = state[key][keep]
                if name in reset_moments:
                    moment = torch.zeros_like(moment)
                if added is not None:
                    moment = torch.cat([moment, torch.zeros_like(added[name])])
                state[key] = moment
            optimizer.state[fresh[name]] = state
