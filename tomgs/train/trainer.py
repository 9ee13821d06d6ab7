"""The TOM-GS trainer: sample a frame, render it at its time, 0.8 L1 + 0.2 D-SSIM, Adam, densify.

Error against run time is part of the output: every `log_interval` iterations a CSV row
(iteration, wall seconds, training PSNR, full-clip PSNR when measured, Gaussians, memory), and at
the end a PNG of PSNR against wall-clock time. Checkpoints every few minutes and on Ctrl-C let
`resume=True` continue a run where it stopped; a seeded CPU run repeats exactly.
"""

from __future__ import annotations

import csv
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from tomgs.cameras import Cameras
from tomgs.metrics import psnr, ssim
from tomgs.model import GaussianModel, nearest_neighbour_distance
from tomgs.render import rasterize
from tomgs.train.config import TrainConfig
from tomgs.train.densify import Densifier
from tomgs.train.sampler import FrameSampler

CSV_FIELDS = ("iteration", "wall_s", "train_psnr", "clip_psnr", "gaussians", "memory_mb")


@dataclass
class FitResult:
    model: GaussianModel
    cameras: Cameras
    clip_psnr: float  # mean over frames of the final full-clip PSNR
    iterations: int
    seconds: float
    history: list[dict] = field(default_factory=list)  # the CSV rows
    notes: list[str] = field(default_factory=list)  # what was left out or assumed


class Trainer:
    """frames uint8 [T,H,W,3]; cameras: Cameras of the clip; points [P,3], colors [P,3] in [0,1]
    (the tracker's sparse cloud, may be empty)."""

    def __init__(self, frames: np.ndarray, cameras: Cameras, points: np.ndarray, colors: np.ndarray,
                 config: TrainConfig, device: torch.device):
        self.config = config
        self.device = device
        self.cameras = cameras
        self.frames = torch.as_tensor(np.ascontiguousarray(frames), device=device)  # uint8, converted per step
        self.num_frames, self.height, self.width = self.frames.shape[:3]
        self.viewmats = cameras.viewmats(device)
        self.K = torch.as_tensor(cameras.K, dtype=torch.float32, device=device)
        self.times = [float(t) for t in cameras.times]
        self.notes: list[str] = []
        self.model, self.extent = self._initial_model(np.asarray(points, dtype=np.float64).reshape(-1, 3),
                                                      np.asarray(colors, dtype=np.float32).reshape(-1, 3))
        self.optimizer = self._optimizer()
        self.sampler = FrameSampler(self.num_frames, config.sampling, config.psnr_momentum, config.seed)
        self.densifier = Densifier(config, self.extent, len(self.model), device, config.seed)
        self.iteration = 0
        self.progress = 0.0  # fraction of the run done: iterations or wall-clock budget, whichever is further
        self.elapsed = 0.0  # wall seconds of earlier sessions of a resumed run
        self.history: list[dict] = []

    # -- set-up --------------------------------------------------------------------------------

    def _initial_model(self, points: np.ndarray, colors: np.ndarray) -> tuple[GaussianModel, float]:
        """Tracked points (static, alive over the whole clip) plus points unprojected from every
        frame at the scene depth, each alive around its frame's time."""
        c = self.config
        g = torch.Generator().manual_seed(c.seed)
        w2c = self.cameras.viewmats()
        depth = self._median_depth(points, w2c)
        per_frame = max(int(c.init_points_per_frame), 1)
        xs, cols, ts = [], [], []
        fx, fy, cx, cy = self.cameras.K[0, 0], self.cameras.K[1, 1], self.cameras.K[0, 2], self.cameras.K[1, 2]
        for k in range(self.num_frames):
            u = torch.rand(per_frame, generator=g, dtype=torch.float64) * self.width
            v = torch.rand(per_frame, generator=g, dtype=torch.float64) * self.height
            z = depth[k] * torch.exp(0.1 * torch.randn(per_frame, generator=g, dtype=torch.float64))
            cam = torch.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], -1).numpy()
            c2w = self.cameras.c2w[k]
            xs.append(cam @ c2w[:3, :3].T + c2w[:3, 3])
            pix = self.frames[k, v.long().clamp(max=self.height - 1), u.long().clamp(max=self.width - 1)]
            cols.append(pix.float().cpu().numpy() / 255.0)
            ts.append(np.full(per_frame, self.times[k]))
        frame_sigma = c.init_t_scale_frames / max(self.num_frames - 1, 1)
        t_sigma = np.concatenate([np.full(len(points), 1.0), np.full(per_frame * self.num_frames, frame_sigma)])
        # sizes: tracked points from their neighbours (few), per-frame points from one sample's
        # share of the image (many: a neighbour search over them would be quadratic)
        pixel_size = max(float(np.median(depth)) / float(fx) * math.sqrt(self.width * self.height / per_frame), 1e-6)
        sizes = np.full(len(points) + per_frame * self.num_frames, pixel_size)
        if len(points):
            sizes[:len(points)] = nearest_neighbour_distance(torch.as_tensor(points, dtype=torch.float32)).numpy()
        all_points = np.concatenate([points, *xs]) if len(points) else np.concatenate(xs)
        all_colors = np.concatenate([colors, *cols]) if len(points) else np.concatenate(cols)
        t_means = np.concatenate([np.full(len(points), 0.5), *ts])
        model = GaussianModel.from_points(torch.as_tensor(all_points, dtype=torch.float32),
                                          torch.as_tensor(all_colors, dtype=torch.float32),
                                          torch.as_tensor(t_means, dtype=torch.float32), 1.0, max_sh_degree=c.sh_degree,
                                          sizes=torch.as_tensor(sizes, dtype=torch.float32))
        with torch.no_grad():
            model.log_t_scales.copy_(torch.log(torch.as_tensor(t_sigma, dtype=torch.float32)))
            if not c.temporal:
                model.log_t_scales.fill_(math.log(1e3))
        if c.sh_degree > 0:
            model.sh_degree = c.sh_degree
        else:
            self.notes.append("SH degree 0: view-dependent colour left out (ask for it with sh_degree)")
        return model.to(self.device), float(np.median(depth))

    @staticmethod
    def _median_depth(points: np.ndarray, w2c: np.ndarray) -> np.ndarray:
        """Median depth [T] of the tracked points in each camera (1.0 where none is in front)."""
        out = np.ones(len(w2c))
        if len(points) == 0:
            return out
        for k, m in enumerate(w2c):
            z = points @ m[2, :3] + m[2, 3]
            z = z[z > 1e-6]
            if len(z):
                out[k] = float(np.median(z))
        return out

    def _optimizer(self) -> torch.optim.Optimizer:
        c = self.config
        lr = dict(means=c.lr_means * self.extent, quats=c.lr_quats, log_scales=c.lr_scales,
                  opacity_logits=c.lr_opacity, sh_dc=c.lr_sh_dc, sh_rest=c.lr_sh_rest,
                  t_means=c.lr_t_means if c.temporal else 0.0, log_t_scales=c.lr_t_scales if c.temporal else 0.0)
        groups = [dict(params=[p], lr=lr[name], name=name) for name, p in self.model.parameters_by_name().items()]
        # fused: one kernel for all groups on the GPU (the foreach path took 2 ms at 4.5M Gaussians)
        return torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=self.device.type == "cuda")

    def _means_lr(self) -> float:
        c = self.config
        frac = min(self.progress, 1.0)
        return self.extent * math.exp((1 - frac) * math.log(c.lr_means) + frac * math.log(c.lr_means_final))

    # -- the loop ------------------------------------------------------------------------------

    def target(self, k: int) -> torch.Tensor:
        return self.frames[k].float() / 255.0

    def render(self, k: int, **kw):
        return rasterize(**self.model.render_inputs(), viewmat=self.viewmats[k], K=self.K, width=self.width,
                         height=self.height, t=self.times[k], **kw)

    def step(self) -> None:
        c = self.config
        k = self.sampler.sample()
        image, _, meta = self.render(k)
        meta["means2d"].retain_grad()
        target = self.target(k)
        loss = (1 - c.ssim_weight) * (image - target).abs().mean() + c.ssim_weight * (1 - ssim(image, target))
        loss.backward()
        self.sampler.update(k, float(psnr(image.detach(), target)))
        if self.progress < c.densify_stop_fraction:
            self.densifier.observe(meta)
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = self._means_lr()
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        self.iteration += 1
        if self.densifier.due(self.iteration, self.progress) and not self.densifier.capped:
            self.densifier.step(self.model, self.optimizer)
        elif self.iteration % (10 * c.densify_interval) == 0:
            self.densifier.prune(self.model, self.optimizer)
            self.densifier.reset_stats(len(self.model), self.device)
        if c.opacity_reset_interval and self.iteration % c.opacity_reset_interval == 0 \
                and self.progress < c.densify_stop_fraction:
            self.densifier.reset_opacity(self.model, self.optimizer)

    @torch.no_grad()
    def clip_psnr(self) -> list[float]:
        """PSNR of every frame, rendered at its time: [T] floats."""
        return [float(psnr(self.render(k)[0], self.target(k))) for k in range(self.num_frames)]

    def run(self, checkpoint: Path | None = None, log_csv: Path | None = None, progress=None) -> FitResult:
        """Train to `config.iterations`. `progress(dict)` is called every log interval."""
        c = self.config
        start = time.perf_counter() - self.elapsed
        next_eval = next_ckpt = 0.0
        try:
            while self.iteration < c.iterations:
                now = time.perf_counter() - start
                self.progress = max(self.iteration / c.iterations, now / c.max_seconds if c.max_seconds > 0 else 0.0)
                self.step()
                now = time.perf_counter() - start
                out_of_time = 0 < c.max_seconds <= now
                if self.iteration % c.log_interval == 0 or self.iteration == c.iterations or out_of_time:
                    clip = None
                    if now >= next_eval or self.iteration == c.iterations or out_of_time:
                        clip = float(np.mean(self.clip_psnr()))
                        next_eval = now + c.eval_interval_s
                    row = self._row(now, clip)
                    self.history.append(row)
                    if log_csv is not None:
                        _append_csv(log_csv, row)
                    if progress is not None:
                        progress(row)
                if checkpoint is not None and now >= next_ckpt:
                    self.elapsed = now
                    self.save_checkpoint(checkpoint)
                    next_ckpt = now + c.checkpoint_interval_s
                if out_of_time:
                    self.notes.append(f"stopped at the {c.max_seconds:.0f} s budget after {self.iteration} iterations")
                    break
        except KeyboardInterrupt:
            if checkpoint is not None:
                self.elapsed = time.perf_counter() - start
                self.save_checkpoint(checkpoint)
            raise
        self.elapsed = time.perf_counter() - start
        final = self.history[-1]["clip_psnr"] if self.history and self.history[-1]["clip_psnr"] != "" \
            else float(np.mean(self.clip_psnr()))
        return FitResult(self.model, self.cameras, float(final), self.iteration, self.elapsed, self.history,
                         list(self.notes))

    def _row(self, now: float, clip: float | None) -> dict:
        seen = self.sampler.psnr[self.sampler.psnr > 0]
        if self.device.type == "cuda":
            memory = torch.cuda.max_memory_allocated(self.device) / 2**20
        else:
            import resource

            memory = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        return dict(iteration=self.iteration, wall_s=round(now, 3),
                    train_psnr=round(float(seen.mean()), 3) if len(seen) else "",
                    clip_psnr="" if clip is None else round(clip, 3), gaussians=len(self.model),
                    memory_mb=round(memory, 1))

    # -- checkpoints ---------------------------------------------------------------------------

    def save_checkpoint(self, path: Path) -> None:
        state = dict(
            iteration=self.iteration, elapsed=self.elapsed, history=self.history, notes=self.notes,
            params={k: v.detach().cpu() for k, v in self.model.parameters_by_name().items()},
            sh_degree=self.model.sh_degree, optimizer=self.optimizer.state_dict(),
            sampler=self.sampler.state_dict(), densifier={k: (v.cpu() if torch.is_tensor(v) else v)
                                                          for k, v in self.densifier.state_dict().items()},
            config=self.config, extent=self.extent,
        )
        tmp = Path(f"{path}.tmp")
        torch.save(state, tmp)
        os.replace(tmp, path)

    def load_checkpoint(self, path: Path) -> None:
        state = torch.load(path, map_location="cpu", weights_only=False)
        self.model.replace({k: v.to(self.device) for k, v in state["params"].items()})
        self.model.sh_degree = state["sh_degree"]
        self.optimizer = self._optimizer()
        self.optimizer.load_state_dict(state["optimizer"])
        self.sampler.load_state_dict(state["sampler"])
        densifier = state["densifier"]
        densifier["grad_sum"] = densifier["grad_sum"].to(self.device)
        densifier["seen"] = densifier["seen"].to(self.device)
        self.densifier.load_state_dict(densifier)
        self.iteration, self.elapsed = state["iteration"], state["elapsed"]
        self.history, self.notes, self.extent = state["history"], state["notes"], state["extent"]


def _append_csv(path: Path, row: dict) -> None:
    new = not path.exists()
    with open(path, "a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        if new:
            writer.writeheader()
        writer.writerow(row)
