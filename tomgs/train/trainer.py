"""The TOM-GS trainer: sample a frame, render it at its time, 0.8 L1 + 0.2 D-SSIM, Adam, densify.

Layers (tomgs.render.layers) use four hooks and nothing else: per-pixel loss `weights` (the background
layer ignores the masked object), `wide_fraction` (some of the background's Gaussians start alive
over the whole clip, so they fill the object's place in the frames where it covers them),
`alpha_targets` (the foreground layer is transparent outside its mask) and an `initial` model (the
foreground's Gaussians pinned to a plane).

Error against run time is part of the output: every `log_interval` iterations a CSV row
(iteration, wall seconds, training PSNR, clip PSNR and the frames it covers when measured, Gaussians,
memory), and at the end a PNG of PSNR against wall-clock time; the CSV is rewritten atomically at
each row.

Durability (tomgs/train/checkpoint.py): a checkpoint every `checkpoint_interval_s` seconds of
training (30 s), copied where the state lives at a step boundary and written by a thread while
training goes on (CheckpointWriter; spaced further when the wait for it is long, so that it costs
at most tomgs.train.loop.CHECKPOINT_OVERHEAD of the run), and one when SIGINT or SIGTERM arrives: the signal is read
at the next step boundary (never inside a densification, where the parameters and the optimiser disagree),
that step is saved and FitInterrupted raised. A crash (kill -9, power loss) loses at most the
interval (or 20 saves' time) of training; `resume=True` continues from the checkpoint, and a seeded
CPU run repeats exactly. A checkpoint or log row that cannot be written (a full disk) is noted and
training goes on; the last complete checkpoint stays the one to resume.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from tomgs.render.alive import TrainingIndex, pays_on
from tomgs.cameras import Cameras
from tomgs.io.scene import vertex_bytes
from tomgs.metrics import psnr, training_loss, weighted_psnr
from tomgs.model import GaussianModel
from tomgs.render.frame import blend_weights, render_frame
from tomgs.render.sequence import IssuedFrame, issue_in_order
from tomgs.errors import InputError
from tomgs.train.checkpoint import (FORMAT, START_OVER, VERSION, CheckpointWriter, check_same_settings, config_from,
                                    config_to_dict, own_copies, read_checkpoint, state_bytes, write_checkpoint)
from tomgs.train.captured_step import CapturedStep, unsupported
from tomgs.train.clip import frame_store, uint8_planes
from tomgs.train.config import TrainConfig
from tomgs.train.densify import Densifier
from tomgs.train.growth import Growth
from tomgs.train.init import initial_model
from tomgs.train.log import log_memory_mb
from tomgs.train.sparsify import Sparsifier
from tomgs.train.optim import make_adam, uses_seen_adam
from tomgs.train.budget import Budget
from tomgs.train.loop import RunHooks, TrainingRun
from tomgs.train.sampler import FrameSampler

# The sampler hears each step's PSNR up to this many steps late: reading it back every step made the
# host wait for the device once more per step than the rasterizer needs.
SAMPLER_LAG = 8
# a clip PSNR reads a frame's counts this many frames after issuing it: late enough that the read does not
# wait, and few, since each frame in flight holds its image until then (all 90 of camel's in flight, each with
# its own activated parameters and buffers, raised a 5M-Gaussian fit's peak GPU memory from 2.9 to 16.2 GB)
EVAL_AHEAD = 4


@dataclass
class FitResult:
    model: GaussianModel
    cameras: Cameras
    clip_psnr: float  # mean over frames of the final clip PSNR
    iterations: int
    seconds: float
    history: list[dict] = field(default_factory=list)  # the CSV rows
    notes: list[str] = field(default_factory=list)  # what was left out or assumed
    # filled by tomgs.train.pipeline (one process) or tomgs.train.multigpu.launch (shards): the plan, wall
    # seconds per phase and in all, peak memory (MiB)
    plan: object = None
    phase_seconds: dict = field(default_factory=dict)
    wall_seconds: float = 0.0
    peak_host_mb: float = 0.0
    peak_gpu_mb: float | None = None
    peak_host_mb_by_phase: dict = field(default_factory=dict)  # the peak so far at the end of each phase
    clip_frames: int = 0  # the frames the final clip PSNR covers (all of them, unless a budget's end was short)
    # a sharded fit's: each process's phases ({"parent" | "rankN": [{phase, start, end}]}, seconds since the
    # command started: tomgs.train.multigpu.job.Timeline) and its report (ranks, merge, refinement, PSNRs)
    timeline: dict | None = None
    shards: dict | None = None


class Trainer:
    """frames uint8 [T,H,W,3]; cameras: Cameras of the clip; points [P,3], colors [P,3] in [0,1]
    (the tracker's sparse cloud, may be empty).

    weights: None, or float [T,H,W] in [0,1], the loss weight of each pixel (0: not supervised; the
    L1 + D-SSIM loss, the sampler's PSNR and the clip PSNR then cover the weighted pixels only,
    and the initial Gaussians are drawn from pixels of weight > 0). alpha_targets: None, or float
    [T,H,W] in [0,1]: adds L1 between the rendered alpha and it. initial: None, or (model, extent)
    to train instead of the trainer's own initialisation (extent: the scene size for learning rates
    and densification). wide_fraction: the fraction of each frame's initial Gaussians that start
    alive over the whole clip (temporal sigma 1.0, like the tracked points; None: `config.init_wide_fraction`)
    instead of around their frame (`config.init_t_scale_frames`); the optimiser narrows the windows where the supervised
    pixels change. point_frames: None, or int [P,2], the first and last frame the tracker saw each
    point in: its Gaussian starts alive over those frames (centred on them, sigma half their span,
    at least `config.init_t_scale_frames`), not over the whole clip. init_progress: None, or
    callable(done, total) as the initial Gaussians of each frame are placed."""

    def __init__(self, frames: np.ndarray, cameras: Cameras, points: np.ndarray, colors: np.ndarray,
                 config: TrainConfig, device: torch.device, *, weights: np.ndarray | None = None,
                 alpha_targets: np.ndarray | None = None, initial: tuple[GaussianModel, float] | None = None,
                 wide_fraction: float | None = None, point_frames: np.ndarray | None = None, init_progress=None):
        frames = np.ascontiguousarray(frames)
        self.num_frames, self.height, self.width = frames.shape[:3]
        if len(cameras) != self.num_frames or (cameras.width, cameras.height) != (self.width, self.height):
            raise InputError(f"{self.num_frames} frames of {self.width}x{self.height} but {len(cameras)} cameras of "
                             f"{cameras.width}x{cameras.height}: give one camera per frame, at the frames' size "
                             f"(the same --frames and size the scene was fitted with)")
        self.config = config.replace(max_gaussians=config.cap(self.num_frames, self.height * self.width, device.type))
        self.device = device
        self.cameras = cameras
        # uint8, converted per step; on the device unless they would crowd out the Gaussians (then
        # each step copies its frame over)
        self.store = frame_store(frames.nbytes * (1 + (weights is not None) / 3 + (alpha_targets is not None) / 3),
                                  device)
        self.frames = torch.as_tensor(frames, device=self.store)
        self.weights, self.alpha_targets = (None if a is None else uint8_planes(a, frames.shape[:3], name, self.store)
                                            for a, name in ((weights, "weights"), (alpha_targets, "alpha_targets")))
        self.viewmats = cameras.viewmats(device)
        self.K = torch.as_tensor(cameras.K, dtype=torch.float32, device=device)
        self.times = [float(t) for t in cameras.times]
        self.notes: list[str] = []
        self.sparse_adam = uses_seen_adam(config, device)
        if initial is None:
            self.model, self.extent, notes = initial_model(
                self.frames, cameras, self.config, device, points, colors, weights=self.weights,
                point_frames=point_frames, progress=init_progress,
                wide_fraction=self.config.init_wide_fraction if wide_fraction is None else wide_fraction)
            self.notes += notes
        else:
            self.model, self.extent = initial[0].to(device), float(initial[1])
        self.optimizer = self._optimizer()
        self.sampler = FrameSampler(self.num_frames, config.sampling, config.psnr_momentum, config.seed)
        self.densifier = Densifier(self.config, self.extent, len(self.model), device, config.seed, self.times)
        self.sparsifier = Sparsifier(self.config, self.height * self.width)
        supervised = self.num_frames * self.height * self.width if self.weights is None else \
            float(self.weights.sum(dtype=torch.float64)) / 255.0  # no float copy of every frame's weights
        self.growth = Growth(self.config, len(self.model), supervised)
        self.densifier.limit = self.growth.limit
        # which Gaussians each frame renders (rebuilt, not saved: checkpoints leave it out)
        use_index = pays_on(device) if config.alive_index is None else bool(config.alive_index)
        self.alive = TrainingIndex(self.times, dense=not self.sparse_adam, lookahead=device.type == "cuda") \
            if use_index else None
        # on a GPU a step does not wait for the device: its frame's counts are read once the backward is
        # queued (tomgs.render.render_frame(defer=True)), the sampler's PSNRs a flush late
        self.pipelined = device.type == "cuda"
        self.captured = self._captured_step()
        self.iteration = 0
        self.progress = 0.0  # fraction of the run done: iterations or wall-clock budget, whichever is further
        self.elapsed = 0.0  # wall seconds of a resumed run's earlier runs
        self.history: list[dict] = []
        self.clip: dict = {}  # what identifies the clip, saved with checkpoints (tomgs.train.pipeline fills it)
        self._measured: list[tuple[int, torch.Tensor]] = []  # (frame, PSNR) not yet given to the sampler
        self._in_flight = None  # (frames, PSNRs on their way to the host, the event after their copy)
        self.eval_frame_seconds = 0.0  # seconds a frame of the last clip PSNR took
        # None, or hook(frame, PSNR 0-d, seen bool [M]) after each eager step's backward, before Adam (a sharded
        # fit's joint refinement sums the shared Gaussians' gradients over the ranks: tomgs.train.multigpu.joint)
        self.gradient_hook = None

    # -- set-up --------------------------------------------------------------------------------

    def _optimizer(self) -> torch.optim.Optimizer:
        c = self.config
        lr = dict(means=c.lr_means * self.extent, quats=c.lr_quats, log_scales=c.lr_scales,
                  opacity_logits=c.lr_opacity, sh_dc=c.lr_sh_dc, sh_rest=c.lr_sh_rest,
                  t_means=c.lr_t_means if c.temporal else 0.0, log_t_scales=c.lr_t_scales if c.temporal else 0.0)
        return make_adam(self.model.parameters_by_name(), lr, self.sparse_adam, self.device)

    def _captured_step(self) -> CapturedStep | None:
        """The step replayed from a CUDA graph (config.captured_step), or None for the eager step: by default
        on a GPU wherever the fit can have it; InputError when asked for where it cannot."""
        asked = self.config.captured_step
        if asked is False or (asked is None and self.device.type != "cuda"):
            return None
        why = unsupported(self)
        if why is not None and asked is None:
            return None
        if why is not None:
            raise InputError(f"captured_step: a training step is captured only without {why}; leave captured_step off")
        return CapturedStep(self)

    def _set_means_lr(self) -> None:
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = self._means_lr()

    def _means_lr(self) -> float:
        c = self.config
        frac = min(self.progress, 1.0)
        return self.extent * math.exp((1 - frac) * math.log(c.lr_means) + frac * math.log(c.lr_means_final))

    # -- the loop ------------------------------------------------------------------------------

    def target(self, k: int, image: torch.Tensor | None = None) -> torch.Tensor:
        """Frame k [H,W,3] in [0,1]. With weights and the render `image`, the unsupervised pixels show
        the render itself (detached): no L1 there, and SSIM windows reaching into them compare the
        render with itself, so masked content never pulls on the model."""
        target = self.frames[k].to(self.device, non_blocking=True).float() / 255.0
        if self.weights is None or image is None:
            return target
        w = self.weight(k)
        return w * target + (1 - w) * image.detach()

    def weight(self, k: int) -> torch.Tensor:
        """Frame k's loss weights [H,W,1] in [0,1] (with `weights` only)."""
        return self.weights[k, :, :, None].to(self.device, non_blocking=True).float() / 255.0  # [H,W,1]

    def loss(self, k: int, image: torch.Tensor, alpha: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """(1 - w) L1 + w D-SSIM of the render image [H,W,3] against `target` (`self.target(k, image)`)
        over frame k's weighted pixels, plus L1 of alpha [H,W,1] against its target when there is one."""
        return self._loss_and_psnr(k, image, alpha, target)[0]

    def _loss_and_psnr(self, k: int, image: torch.Tensor, alpha: torch.Tensor,
                       target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(`loss`, `_psnr` of the same image and target): without weights both come from the loss's
        passes, so a step measures its frame for its sampler at no further host cost."""
        loss, measured = training_loss(image, target, self.config.ssim_weight,
                                       None if self.weights is None else self.weight(k))
        if self.alpha_targets is not None:
            alpha_target = self.alpha_targets[k].to(self.device, non_blocking=True).float() / 255.0
            loss = loss + (alpha[..., 0] - alpha_target).abs().mean()
        return loss, measured

    def measure(self, k: int, image: torch.Tensor, target: torch.Tensor | None = None) -> float:
        """PSNR of the render image [H,W,3] against frame k (or its `target`, already made) over its
        weighted pixels."""
        return float(self.frame_psnr(k, image, target))

    def frame_psnr(self, k: int, image: torch.Tensor, target: torch.Tensor | None = None) -> torch.Tensor:
        """`measure` as a 0-d tensor where the image lives (no wait for the device)."""
        image = image.detach()
        target = self.target(k, image) if target is None else target.detach()
        if self.weights is None:
            return psnr(image, target)
        return weighted_psnr(image, target, self.weight(k))

    def render(self, k: int, defer: bool = False, inputs: dict | None = None, **kw):
        """Frame k at its time: (image, alpha, meta) as `rasterize` gives them for the Gaussians that
        may be alive then (tomgs.render.alive), meta['rows'] naming them (int [M]; None: all N). With
        `defer`, meta['counts'] is the frame's FrameCounts when it did not wait for them (else None).
        `inputs`: the model's `render_inputs()` when the caller renders several frames of one state."""
        rows = None if self.alive is None else self.alive.rows(k, self.model, self.optimizer, self.iteration)
        inputs = self.model.render_inputs() if inputs is None else inputs
        image, alpha, meta, counts = render_frame(**inputs, viewmat=self.viewmats[k],
                                                  K=self.K, width=self.width, height=self.height, t=self.times[k],
                                                  rows=rows, defer=defer, **kw)
        meta["rows"], meta["counts"] = rows, counts
        return image, alpha, meta

    def step(self) -> None:
        k = self.sampler.sample()
        if self.captured is not None and self.captured.ready():
            self._set_means_lr()
            # the whole step in one replay; the densifier decides after it, on the host, as after an eager one
            self._heard(k, self.captured.run(k, self.densifier.collecting(self.progress),
                                             self.densifier.may_grow(self.progress)))
            self.iteration += 1
            self.densifier.schedule(self.model, self.optimizer, self.iteration, self.progress)
            return
        defer = self.pipelined
        while True:
            image, alpha, meta = self.render(k, defer=defer)
            if self.alive is not None:
                self.alive.settle()  # the last step's check, from a copy queued a step ago
            self.densifier.step_pre_backward(meta, self.progress)
            target = self.target(k, image)  # once per step: the loss and the sampler's PSNR share it
            loss, measured = self._loss_and_psnr(k, image, alpha, target)
            loss.backward()
            # read once the backward is queued, so the device is busy meanwhile; a frame whose keys
            # overflowed their bound lacks entries: its gradients go, and it renders again, waiting
            if meta["counts"] is None or not meta["counts"].overflowed:
                break
            self.optimizer.zero_grad(set_to_none=True)
            defer = False
        self._heard(k, measured)
        seen = in_view = (meta["radii"] > 0).any(-1)  # bool [M]: the rendered rows this step's gradient reaches
        if self.gradient_hook is not None:  # before Adam: it may change the gradients and `seen` in place
            self.gradient_hook(k, measured, seen)
        if meta["rows"] is not None:  # -> bool [N]
            in_view = torch.zeros(len(self.model), dtype=torch.bool, device=self.device).index_put_(
                (meta["rows"],), seen)
        self._set_means_lr()
        if self.sparse_adam:
            self.optimizer.step(in_view)
        else:
            self.optimizer.step()
        if self.alive is not None:
            self.alive.check(self.model, self.optimizer, meta["rows"], seen)  # only these moved freely
        self.optimizer.zero_grad(set_to_none=True)
        self.iteration += 1
        self.densifier.step_post_backward(self.model, self.optimizer, meta, in_view, self.iteration, self.progress)

    def _heard(self, k: int, measured: torch.Tensor) -> None:
        """Frame k's PSNR (0-d, where the device wrote it) for the sampler, handed over SAMPLER_LAG steps at a time."""
        self._measured.append((k, measured))
        if len(self._measured) >= SAMPLER_LAG:
            self.flush_measurements(wait=not self.pipelined)

    def flush_measurements(self, wait: bool = True) -> None:
        """Hand the PSNRs measured so far to the sampler, in order. Without `wait` (a pipelined step's
        flush) they are copied to the host without waiting and handed over at the next flush: the
        sampler hears them SAMPLER_LAG to 2 x SAMPLER_LAG steps late, and the host never stalls for them."""
        if self._in_flight is not None:
            frames, values, copied = self._in_flight
            self._in_flight = None
            if copied is not None:
                copied.synchronize()  # long done: queued a flush ago
            for k, value in zip(frames, values.tolist()):
                self.sampler.update(k, value)
        if not self._measured:
            return
        frames = [k for k, _ in self._measured]
        values = torch.stack([v for _, v in self._measured])
        self._measured.clear()
        if wait:
            for k, value in zip(frames, values.tolist()):
                self.sampler.update(k, value)
            return
        copied = None
        if values.is_cuda:
            values = values.to("cpu", non_blocking=True)
            copied = torch.cuda.Event()
            copied.record()
        self._in_flight = (frames, values, copied)

    @torch.no_grad()
    def clip_psnr(self, tick=None, frames=None, hidden: torch.Tensor | None = None) -> list[float]:
        """PSNR of every frame, or of `frames` (frame numbers), of its weighted pixels, rendered at its
        time: floats, one a frame; without the Gaussians `hidden` (bool [N]; their opacity 0: culled as
        if removed). tick(text) after each frame (a display's heartbeat on long clips)."""
        frames = range(self.num_frames) if frames is None else [int(k) for k in frames]
        bad = [k for k in frames if not 0 <= k < self.num_frames]
        if bad:
            raise ValueError(f"clip_psnr: frame {bad[0]} is not one of the clip's {self.num_frames}")
        out = []
        with torch.no_grad():
            inputs = self.model.render_inputs()  # the activated parameters once, shared by every frame
            if hidden is not None:
                inputs["opacities"] = inputs["opacities"].masked_fill(hidden, 0.0)

            def issue(position: int, k: int, wait: bool) -> IssuedFrame:
                image, _, meta = self.render(k, defer=not wait, inputs=inputs)
                # only the image and the counts stay in flight: the rasterizer's buffers in meta (keys,
                # projections; ~0.3 GB a frame at 5M Gaussians) go back to the allocator now
                return IssuedFrame(position, k, image, {}, meta["counts"], None)

            # frames issued without waiting for their counts, read EVAL_AHEAD frames later (the host queues
            # the next while the device renders: 90 camel frames at 5M Gaussians took 0.2-0.3 s waiting on each)
            for i, (k, image, _) in enumerate(issue_in_order(frames, issue, EVAL_AHEAD)):
                out.append(self.frame_psnr(k, image))
                if tick is not None:
                    tick(f"measuring the clip PSNR: frame {i + 1} of {len(frames)}")
        return torch.stack(out).tolist() if out else []

    def remove(self, rows: torch.Tensor) -> int:
        """Remove the Gaussians `rows` (bool [N]) from the model, with their Adam moments and densification
        statistics; returns how many went."""
        removed = self.densifier.remove(self.model, self.optimizer, rows)
        if removed:
            self.densifier.reset_stats(len(self.model), self.device)
        return removed

    def mark_changed(self) -> None:
        """The cloud changed at this step (a round's prune): the clip PSNR dips for a few dozen steps, and the
        cadences that price or measure it wait (tomgs.train.loop.TrainingRun.settled)."""
        self.densifier.changed_at = self.iteration

    def compact(self, tick=None) -> int:
        """Leave out the Gaussians that give no frame of the clip `config.compact_pixels` pixels' worth
        of colour (`tomgs.render.blend_weights`, the largest over the frames); returns how many went
        (noted in `notes`). tick(text) after each frame. The end of a run calls it before its last
        measurement, so the PSNR it reports is the saved scene's."""
        threshold = self.config.compact_pixels
        if threshold <= 0 or len(self.model) == 0:
            return 0
        began = time.perf_counter()
        gaussians = {k: v.detach() for k, v in self.model.render_inputs().items() if k != "colors"}
        largest = torch.zeros(len(self.model), device=self.device)
        for k in range(self.num_frames):
            rows = None if self.alive is None else self.alive.rows(k, self.model, self.optimizer, self.iteration)
            weights = blend_weights(**gaussians, viewmat=self.viewmats[k], K=self.K, width=self.width,
                                    height=self.height, t=self.times[k], rows=rows)
            torch.maximum(largest, weights, out=largest)
            if tick is not None:
                tick(f"finding the Gaussians no frame shows: frame {k + 1} of {self.num_frames}")
        if len(self.model) and bool((largest < threshold).all()):  # an empty scene helps nobody: say so instead
            self.notes.append(f"compact_pixels {threshold:g} would leave out every Gaussian (the most any gives a "
                              f"frame is {float(largest.max()):.3g} of a pixel's colour): all kept; give a smaller "
                              f"--compact")
            return 0
        removed = self.remove(largest < threshold)
        if removed:
            self.notes.append(f"left out {removed:,} Gaussians that gave no frame {threshold:g} of a pixel's colour "
                              f"({len(self.model):,} kept; {time.perf_counter() - began:.1f} s)")
        return removed

    def run(self, budget: Budget | None = None, hooks: RunHooks | None = None) -> FitResult:
        """Train to the budget's iterations or its time limit (default `Budget.of_training`: config.iterations,
        and config.max_seconds of training), the cadences of tomgs.train.loop around the steps; `hooks` say
        where it saves and whom it tells (RunHooks). The run stops early enough that its end (the compaction
        and the last clip PSNR) ends by the limit, and keeps at most END_SHARE of it for that end."""
        return TrainingRun(self, Budget.of_training(self.config) if budget is None else budget,
                           RunHooks() if hooks is None else hooks).run()

    def run_result(self) -> FitResult:
        """The FitResult of a run that has ended: the summaries of growth, the quality rule and the captured
        step in the notes, and the final clip PSNR (measured now when the run's last step did not)."""
        if len(self.growth.stages) > 1:
            self.notes.append(self.growth.summary())
        if self.sparsifier.measured:
            self.notes.append(self.sparsifier.summary(self.config.quality))
        if self.captured is not None:
            self.captured.settle()
            if self.captured.dropped:
                self.notes.append(f"{self.captured.dropped} of {self.captured.steps} captured steps updated nothing "
                                  "(their frames needed more tile keys than captured; captured again larger)")
        ended = self.history[-1] if self.history else {}
        if ended.get("clip_psnr", "") != "" and ended.get("iteration") == self.iteration:
            final, covered = ended["clip_psnr"], int(ended["clip_frames"])
        else:  # nothing measured at this step (a resume of a finished run): every frame now
            final, covered = float(np.mean(self.clip_psnr())), self.num_frames
        return FitResult(self.model, self.cameras, float(final), self.iteration, self.elapsed, self.history,
                         list(self.notes), clip_frames=covered)

    def status(self) -> str:
        """'iteration N, PSNR x dB, G Gaussians': where training is, for a display (the PSNR of the
        training frames as the sampler has heard it, left out before it has)."""
        train = self.train_psnr()
        psnr = "" if train is None else f", PSNR {train:.2f} dB"
        return f"iteration {self.iteration:,}{psnr}, {len(self.model):,} Gaussians"

    def grow(self) -> None:
        """At a densification interval of a fit growing in stages (tomgs.train.growth), while it densifies:
        the densifier's limit doubles when its stage has paid, or densification stops."""
        if not self.growth.staged or self.progress >= self.config.densify_stop_fraction:
            return
        done = self.growth.update(self.progress, len(self.model), self.densifier.capped, self.train_psnr())
        if done == "grow":
            self.densifier.limit, self.densifier.capped = self.growth.limit, False
            self.densifier.reset_stats(len(self.model), self.device)
        elif done == "stop":
            self.densifier.stopped = True
            self.notes.append(f"densification stopped {self.growth.stopped} ({self.config.quality} quality)")

    def train_psnr(self) -> float | None:
        """The training PSNR: the mean over the frames trained on so far of each one's last PSNR (None before
        any), as the sampler has heard them. Handing it the measurements still on their way would change
        what it draws next at moments set by the clock, and a seeded run would no longer repeat."""
        return self.sampler.latest_mean()

    def log_row(self, now: float, clip: tuple[float, int] | None, count: int | None = None) -> dict:
        """The CSV row at `now` seconds; clip: (clip PSNR, the frames it covers) or None; count: the
        Gaussians that clip PSNR measured (default: the model's now). Its train PSNR is `train_psnr`."""
        train = self.train_psnr()
        count = len(self.model) if count is None else int(count)
        return dict(iteration=self.iteration, wall_s=round(now, 3),
                    train_psnr="" if train is None else round(train, 3),
                    clip_psnr="" if clip is None else round(clip[0], 3), clip_frames="" if clip is None else clip[1],
                    gaussians=count, scene_bytes=vertex_bytes(count, self.model.max_sh_degree),
                    memory_mb=round(log_memory_mb(self.device), 1))

    # -- checkpoints ---------------------------------------------------------------------------

    def state_dict(self) -> dict:
        """The trainer's state as tensors and plain data (tomgs/train/checkpoint.py's layout). The
        measurements the sampler has not heard yet go with it as they are (handing them over now would
        change the draws that follow, as `train_psnr` says)."""
        # tensors stay where they live: torch.save copies one storage at a time to the file, where a
        # whole-model host copy made the checkpoint the training phase's host peak (7.4M Gaussians,
        # 1080p x 900 on the H100: +0.96 GiB during training); read_checkpoint maps them to the CPU
        densifier = self.densifier.state_dict()
        return dict(
            format=FORMAT, version=VERSION, iteration=int(self.iteration), elapsed=float(self.elapsed),
            extent=float(self.extent), config=config_to_dict(self.config),
            frames=[int(self.num_frames), int(self.height), int(self.width)],
            params={k: v.detach() for k, v in self.model.parameters_by_name().items()},
            sh_degree=int(self.model.sh_degree), optimizer=self.optimizer.state_dict(),
            sampler=dict(self.sampler.state_dict(), pending=self._pending()), densifier=densifier,
            sparsifier=self.sparsifier.state_dict(), growth=self.growth.state_dict(),
            history=[dict(r) for r in self.history],
            notes=[str(n) for n in self.notes], clip=dict(self.clip),
        )

    def _pending(self) -> list[list]:
        """[[frame, PSNR], ...]: the measurements not yet handed to the sampler, in the order it hears them."""
        pending = []
        if self._in_flight is not None:
            frames, values, copied = self._in_flight
            if copied is not None:
                copied.synchronize()
            pending += [[k, v] for k, v in zip(frames, values.tolist())]
        if self._measured:
            values = torch.stack([v for _, v in self._measured]).tolist()
            pending += [[k, v] for (k, _), v in zip(self._measured, values)]
        return pending

    def _restore_pending(self, pending: list) -> None:
        """Put `_pending`'s measurements back where they were: a pipelined trainer's older ones on their
        way to the sampler (heard at the next flush), the last iteration % SAMPLER_LAG steps' waiting
        for it, so the flushes keep their steps."""
        waiting = min(self.iteration % SAMPLER_LAG, len(pending)) if self.pipelined else len(pending)
        sent, kept = pending[:len(pending) - waiting], pending[len(pending) - waiting:]
        self._in_flight = ([int(k) for k, _ in sent], torch.tensor([float(v) for _, v in sent]), None) \
            if sent else None
        self._measured = [(int(k), torch.tensor(float(v), device=self.device)) for k, v in kept]

    def checkpoint_in_background(self, path: Path, writer: CheckpointWriter) -> None:
        """Hand `writer` a copy of the state (made where the tensors live, at this step boundary), or
        write it here when the device lacks the room for that copy."""
        writer.wait()
        state = self.state_dict()
        if self.device.type == "cuda":
            free, _ = torch.cuda.mem_get_info(self.device)
            free += torch.cuda.memory_reserved(self.device) - torch.cuda.memory_allocated(self.device)
            if state_bytes(state) > free / 2:
                try:
                    writer.done = write_checkpoint(path, state)
                except OSError as e:
                    writer.failed = e
                return
        copies, ready = own_copies(state), None
        if self.device.type == "cuda":
            ready = torch.cuda.Event()
            ready.record(torch.cuda.current_stream(self.device))
        writer.submit(path, copies, ready)

    def save_checkpoint(self, path: Path) -> None:
        """Write the state to `path` (tomgs.train.checkpoint.write_checkpoint: an exclusively created
        temporary, fsync, rename; the previous checkpoint stays until the new one is complete)."""
        write_checkpoint(path, self.state_dict())

    def load_checkpoint(self, checkpoint) -> dict:
        """Continue from `checkpoint`: a path (read with weights_only and checked) or a state that
        `read_checkpoint` returned. InputError when it was fitted on other frames or frame sizes, or
        with another SH degree or temporal mode than this trainer's. Returns the state."""
        where = "the checkpoint" if isinstance(checkpoint, dict) else str(checkpoint)
        state = checkpoint if isinstance(checkpoint, dict) else read_checkpoint(checkpoint)
        views, height, width = state["frames"]
        if (views, height, width) != (self.num_frames, self.height, self.width):
            raise InputError(f"{where} was fitted on {views} frames of {width}x{height}, but this run has "
                             f"{self.num_frames} of {self.width}x{self.height}: resume with the options it was "
                             f"started with (--frames, --max-side), or {START_OVER}")
        check_same_settings(state["config"], self.config, where)
        saved = config_from(state["config"], where)
        current = self.model.parameters_by_name()
        for name, value in state["params"].items():
            if value.shape[1:] != current[name].shape[1:]:
                raise InputError(f"{where}: parameter {name} has rows of shape {tuple(value.shape[1:])}, this "
                                 f"model's are {tuple(current[name].shape[1:])}; {START_OVER}")
        changed = [f"{k} {getattr(saved, k)} -> {getattr(self.config, k)}" for k in config_to_dict(saved)
                   if getattr(saved, k) != getattr(self.config, k)]
        self.model.replace({k: v.to(self.device) for k, v in state["params"].items()})
        self.model.sh_degree = state["sh_degree"]
        self.extent = float(state["extent"])
        self.optimizer = self._optimizer()
        # every setting but the learning rate is this optimiser's: how this device runs Adam, and the
        # settings torch's Adam needs that a SeenAdam checkpoint (a GPU's) lacks
        own = [{k: v for k, v in group.items() if k not in ("params", "lr")} for group in self.optimizer.param_groups]
        self.optimizer.load_state_dict(state["optimizer"])
        for group, settings in zip(self.optimizer.param_groups, own):
            group.update(settings)
        self.sampler.load_state_dict(state["sampler"])
        densifier = dict(state["densifier"])
        densifier["grad_sum"] = densifier["grad_sum"].to(self.device)
        densifier["seen"] = densifier["seen"].to(self.device)
        self.densifier.load_state_dict(densifier)
        if "sparsifier" in state:  # checkpoints before it: no round taken yet
            self.sparsifier.load_state_dict(state["sparsifier"])
        if "growth" in state:
            self.growth.load_state_dict(state["growth"])
        else:  # checkpoints before it: grown as far as the densifier's limit (the cap), no stage to take
            self.growth.limit = self.densifier.limit
        self.iteration, self.elapsed = state["iteration"], float(state["elapsed"])
        self._restore_pending(state["sampler"].get("pending", []))  # checkpoints before it: none
        self.history, self.notes = list(state["history"]), list(state["notes"])
        self.densifier.extent = self.extent
        self.clip = dict(state["clip"])
        if changed:
            self.notes.append(f"resumed at iteration {self.iteration} with other settings: {', '.join(changed)}")
        return state
