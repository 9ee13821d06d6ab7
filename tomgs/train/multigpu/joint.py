"""A sharded fit after phase 1 (tomgs.train.multigpu.shards, steps 4-5): the joint refinement of each
rank's part of the union, as the rank's Trainer with a gradient hook that sums the shared Gaussians'
gradients over the ranks; what its end must leave time for (`time_scene_io`); and rank 0's outputs
(`write_outputs`: the scene, the merged CSV and plot).

The refinement's Trainer steps as a fit's does (the same loss, sampler and Adam), with what a part of
a merged union needs: Adam at the rates phase 1 ended with (`joint_trainer`), primed from each row's
phase-1 state; no densification, pruning, growth, quality rounds or compaction (the rows of every
rank's part must stay those of the union); every Gaussian rendered (no alive index, no captured step:
a hook is not captured). The ranks stop together: the hook's one all_reduce a step also carries their
PSNRs and stop flags.
"""

from __future__ import annotations

import signal
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from tomgs.model import GaussianModel
from tomgs.train.log import write_csv, write_plot
from tomgs.train.multigpu.shards import Halo, boundary_psnr, log_row, merged_history, model_of, row_widths, unpack

NEVER = 2**31 - 1  # a densification interval no refinement reaches: no densify, no prune
# after the refinement's last step, beside what the ranks measure (the final measurement, the gather,
# the scene's write and read back): the ranks leaving the group and exiting (os._exit: ~0.02 s), the
# parent joining them, the logs gathered (CPU, gloo, 2 ranks: 0.05-0.1 s in all)
EXIT_S = 0.5
SAMPLE_IO_SHARE = 1 / 16  # rank 0 times the scene's write and read back on this share of the union
MIN_SAMPLE_IO = 20_000  # ... and on at least this many Gaussians


@dataclass
class Refined:
    """What the refinement did on one rank: steps, seconds, the rows it logged."""

    steps: int = 0
    seconds: float = 0.0
    rows: list = field(default_factory=list)
    stopped_by: int | None = None  # a signal number when SIGINT / SIGTERM stopped it


def refine_optimizer(model: GaussianModel, rates: dict[str, float], config, device: torch.device,
                     moments: torch.Tensor | None = None, steps: dict | None = None) -> torch.optim.Optimizer:
    """The refinement's Adam (the trainer's kind: make_adam) for `model`, at `rates`; with `moments`
    (float32 [M, 2 D], the model's rows of Union.moments) and `steps` (Union.steps), primed to go on
    from phase 1's state of each row (`prime_adam`) rather than from nothing: a fresh Adam's first
    steps are a full learning rate in the gradient's sign, whatever the gradient, and knock every
    converged Gaussian about (the union's training PSNR fell 1.3 dB over its first 400 steps)."""
    from tomgs.train.optim import make_adam, prime_adam, uses_seen_adam

    params = model.parameters_by_name()
    optimizer = make_adam(params, rates, uses_seen_adam(config, device), device)
    if moments is not None:
        width = sum(row_widths(model.max_sh_degree).values())
        first, second = unpack(moments[:, :width], model.max_sh_degree), unpack(moments[:, width:], model.max_sh_degree)
        prime_adam(optimizer, {name: (first[name], second[name]) for name in params}, steps or {})
    return optimizer


def joint_trainer(model: GaussianModel, frames: np.ndarray, cameras, config, rates: dict[str, float], extent: float,
                  device: torch.device, *, moments: torch.Tensor | None = None, adam_steps: dict | None = None,
                  seed: int = 0):
    """The Trainer of a rank's part `model` (its Halo's rows) on its own `frames` (uint8 [F,H,W,3]) with their
    `cameras` in clip time: Adam at `rates` (refine_optimizer), nothing added or removed, every Gaussian
    rendered; its sampler drawn with `seed`."""
    from tomgs.train.trainer import Trainer

    means_rate = rates["means"] / max(extent, 1e-12)  # the trainer's means rate is a share of the extent
    settings = config.replace(densify_interval=NEVER, densify_stop_fraction=0.0, opacity_reset_interval=0,
                              quality="max", compact_pixels=0.0, alive_index=False, captured_step=False,
                              lr_means=means_rate, lr_means_final=means_rate, max_gaussians=max(len(model), 1),
                              seed=seed)
    trainer = Trainer(frames, cameras, np.zeros((0, 3)), np.zeros((0, 3), np.float32), settings, device,
                      initial=(model, extent))
    trainer.optimizer = refine_optimizer(trainer.model, rates, settings, device, moments, adam_steps)
    return trainer


class SharedGradients:
    """Trainer.gradient_hook of the joint refinement: after a step's backward, one all_reduce sums the
    gradients and 'in view' flags of the Gaussians shared with other ranks (`part`: this rank's Halo), so
    that every replica takes the same Adam step, and carries [PSNR, signal, done] of every rank. `decide()`
    gives this rank's (signal number or 0, done) at that moment; `result` is then, on the device,
    [the ranks' PSNR sum, a signal, done, this rank's PSNR]."""

    def __init__(self, model: GaussianModel, part: Halo, device: torch.device, decide):
        import torch.distributed as dist

        from tomgs.train.sampler import MAX_PSNR

        self.all_reduce, self.max_psnr = dist.all_reduce, MAX_PSNR  # looked up once, not at every step
        self.params = list(model.parameters_by_name().values())
        self.shared, self.slots = part.shared.to(device), part.slots.to(device)
        self.total, self.device, self.decide = part.total, device, decide
        self.widths = [p[0].numel() if len(model) else 0 for p in self.params]
        self.result = None

    def __call__(self, k: int, measured: torch.Tensor, seen: torch.Tensor) -> None:
        grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in self.params]
        value = measured.detach().float().clamp(max=self.max_psnr).reshape(1)
        buffer = torch.zeros(self.total, sum(self.widths) + 1, device=self.device)
        buffer[self.slots] = torch.cat([g.index_select(0, self.shared).reshape(len(self.shared), -1) for g in grads]
                                       + [seen.index_select(0, self.shared).float()[:, None]], dim=1)
        # built on the host and sent without waiting (a copy from pageable memory that is not non_blocking waits)
        signum, done = self.decide()
        flags = torch.tensor([float(signum or 0), float(done)]).to(self.device, non_blocking=True)
        buffer = torch.cat([buffer.reshape(-1), value, flags])
        self.all_reduce(buffer)
        summed = buffer[:-3].view(self.total, -1).index_select(0, self.slots)
        at = 0
        for p, g, width in zip(self.params, grads, self.widths):
            g.index_copy_(0, self.shared, summed[:, at:at + width].reshape(len(self.shared), *g.shape[1:]))
            p.grad = g
            at += width
        seen.index_copy_(0, self.shared, summed[:, at] > 0)
        self.result = torch.cat([buffer[-3:], value])


def refine_jointly(trainer, part: Halo, *, steps: int = 0, until: float | None = None, start_wall: float = 0.0,
                   start_iteration: int = 0, log_rows=None, tick=None) -> Refined:
    """Train `trainer` (`joint_trainer`'s, rank part.rank's) jointly with the other ranks' (SharedGradients).
    Stops after `steps` steps, or before the wall-clock time `until` (time.time()) that any rank reaches
    first (when a step as long as its latest would end past it), or at SIGINT / SIGTERM on any rank
    (Refined.stopped_by). Needs an initialised default process group. `log_rows(row)` hears a CSV row every
    log_interval steps (wall_s from `start_wall`, iteration from `start_iteration`; train_psnr the ranks'
    mean); `tick(iteration, wall)` each step."""
    import torch.distributed as dist

    from tomgs.io.scene import vertex_bytes
    from tomgs.train.checkpoint import StopSignals
    from tomgs.train.log import log_memory_mb

    world, model, out = dist.get_world_size(), trainer.model, Refined()
    began = time.perf_counter()
    recent, clock = [], dict(step=0.0, stepped=began)  # the latest step's seconds

    def decide():
        done = steps > 0 and out.steps + 1 >= steps
        late = until is not None and time.time() + clock["step"] >= until  # the next step would end past it
        return stop.signum, done or late

    with StopSignals() as stop:
        trainer.gradient_hook = SharedGradients(model, part, trainer.device, decide)
        while True:
            trainer.step()
            out.steps += 1
            # the one wait for the device a step has: the sums and this rank's own PSNR together
            total, signum, finished, own = trainer.gradient_hook.result.tolist()
            clock["step"], clock["stepped"] = time.perf_counter() - clock["stepped"], time.perf_counter()
            recent.append(total / world)  # the ranks' mean: the union's training PSNR
            now = time.perf_counter() - began
            if tick is not None:
                tick(start_iteration + out.steps, start_wall + now)
            if log_rows is not None and (out.steps % trainer.config.log_interval == 0 or signum or finished):
                row = log_row(iteration=start_iteration + out.steps, wall_s=round(start_wall + now, 3),
                              train_psnr=round(float(np.mean(recent)), 3), gaussians=len(model),
                              scene_bytes=vertex_bytes(len(model), model.max_sh_degree),
                              memory_mb=round(log_memory_mb(trainer.device), 1))
                recent.clear()
                out.rows.append(row)
                log_rows(row)
            if signum:
                out.stopped_by = stop.signum or signal.SIGTERM  # another rank's signal stops this one too
                break
            if finished:
                break
    trainer.gradient_hook = None
    out.seconds = time.perf_counter() - began
    return out


def time_scene_io(union: torch.Tensor, sh: tuple, cameras, scene: Path, history: list) -> float:
    """Rank 0, before the refinement: seconds to write a scene of the union's size and read it back
    (the parent's load_scene), and to draw the plot, as timed here on a sample of the union's rows
    (SAMPLE_IO_SHARE of them, at least MIN_SAMPLE_IO) written beside the scene and removed; the
    per-Gaussian time scaled to the whole union (so the sample's fixed costs count several times)."""
    from tomgs.io.scene import load_scene, save_scene

    n = len(union)
    if n == 0:
        return 0.0
    step = max(1, min(round(1 / SAMPLE_IO_SHARE), n // MIN_SAMPLE_IO))
    sample = model_of(union[::step], *sh)
    path = scene.with_name(f".{scene.stem}.io-sample{scene.suffix}")
    figure = scene.with_name(f".{scene.stem}.io-sample.png")
    began = time.perf_counter()
    try:
        save_scene(path, sample, cameras, {})
        load_scene(path)
        io = (time.perf_counter() - began) * n / len(sample)
        began = time.perf_counter()
        write_plot(figure, history)  # matplotlib's import and a figure like the run's
        return io + time.perf_counter() - began
    finally:
        path.unlink(missing_ok=True)
        figure.unlink(missing_ok=True)


def write_outputs(job, everyone, stretches, cameras, payload, final, refine_rows, outputs, config, extent) -> dict:
    """Rank 0: the scene, the merged CSV and plot; the run's summary."""
    from tomgs.io.scene import save_scene, vertex_bytes

    frame_psnr = [p for rank in everyone for p in rank["frame_psnr"]]
    merged_before = [p for rank in everyone for p in rank["merged_psnr"]]
    clip_psnr = float(np.mean(frame_psnr))
    weights = [rank["own"][1] - rank["own"][0] for rank in everyone]
    phase1 = [[row for row in rank["history"] if int(row["iteration"]) <= rank["iterations"]] for rank in everyone]
    history = merged_history(phase1, weights)
    start_iteration = sum(rank["iterations"] for rank in everyone)
    start_wall = max(rank["train_seconds"] for rank in everyone)
    steps = everyone[0]["refine_steps"]
    refine_seconds = max(rank["refine_seconds"] for rank in everyone)
    for row in refine_rows:
        k = int(row["iteration"]) - everyone[0]["iterations"]
        history.append(dict(row, iteration=start_iteration + k * len(everyone), gaussians=len(final),
                            wall_s=round(start_wall + float(row["wall_s"]) - everyone[0]["train_seconds"], 3)))
    history.append(log_row(iteration=start_iteration + steps * len(everyone),
                           wall_s=round(start_wall + refine_seconds, 3),
                           train_psnr=history[-1]["train_psnr"] if history else "", clip_psnr=round(clip_psnr, 3),
                           clip_frames=len(frame_psnr), gaussians=len(final),
                           scene_bytes=vertex_bytes(len(final), final.max_sh_degree),
                           memory_mb=max(float(r["peak_gpu_mb"] or r["peak_host_mb"]) for r in everyone)))
    boundary = boundary_psnr(frame_psnr, stretches)
    shards = dict(ranks=len(everyone), overlap=stretches[0].hi - stretches[0].own_hi if len(stretches) > 1 else 0,
                  union=everyone[0]["union"], shared=everyone[0]["shared"],
                  refine_fraction=job.refine_fraction, refine_steps=steps, refine_seconds=round(refine_seconds, 3),
                  merged_psnr_before_refine=round(float(np.mean(merged_before)), 3), clip_psnr=round(clip_psnr, 3),
                  boundary=boundary, frame_psnr=[round(p, 3) for p in frame_psnr],
                  per_rank=[{k: rank[k] for k in ("rank", "frames", "own", "iterations", "train_seconds",
                                                  "steps_per_s", "phase1_psnr", "refine_steps_per_s",
                                                  "merge_seconds", "halo", "peak_host_mb", "peak_gpu_mb",
                                                  "reserve")}
                            for rank in everyone])
    notes = list(payload["notes"])
    notes.append(f"{len(everyone)} ranks: " + "; ".join(
        f"rank {r['rank']} {s.describe(cameras.frame_indices)}, {r['iterations']} iterations "
        f"({r['steps_per_s']:.1f}/s), {r['phase1_psnr'] if r['phase1_psnr'] is not None else '-'} dB alone"
        for r, s in zip(everyone, stretches)))
    notes.append(f"merged: {shards['merged_psnr_before_refine']:.2f} dB before the joint refinement, "
                 f"{clip_psnr:.2f} dB after {steps} steps on each rank ({refine_seconds:.1f} s); frames within "
                 f"{boundary['near']} of a boundary {boundary['boundary']} dB, the others {boundary['interior']} dB")
    info = dict(source=payload["source"], iterations=start_iteration + steps * len(everyone),
                train_seconds=round(start_wall + refine_seconds, 2), pose_seconds=round(payload["pose_seconds"], 2),
                clip_psnr=round(clip_psnr, 3), extent=extent, fps=payload["fps"], background=[0.0, 0.0, 0.0],
                config={k: v for k, v in vars(config).items()}, notes=notes, shards=shards)
    save_scene(outputs["scene"], final, cameras, info)
    write_csv(outputs["csv"], history)
    write_plot(outputs["plot"], history)
    return dict(clip_psnr=clip_psnr, iterations=info["iterations"], seconds=info["train_seconds"], history=history,
                notes=notes, shards=shards, peak_host_mb=max(r["peak_host_mb"] for r in everyone),
                peak_gpu_mb=(max(r["peak_gpu_mb"] for r in everyone) if everyone[0]["peak_gpu_mb"] is not None
                             else None))


__all__ = ["EXIT_S", "NEVER", "Refined", "SharedGradients", "joint_trainer", "refine_jointly", "refine_optimizer",
           "time_scene_io", "write_outputs"]
