"""What the alive index (tomgs.render.alive, issue 15) saves: a training step and a rendered frame with and
without it, on a DAVIS-like synthetic cloud where a chosen share of the Gaussians is alive at each
frame (each Gaussian alive over that share of the clip, centres uniform in time, scattered in front
of a fixed camera over noise frames).

    python benchmarks/alive_index.py --device cpu --gaussians 200000 --size 160x90
    python benchmarks/alive_index.py --device cuda --gaussians 4000000 --size 854x480

Prints per mode the training step (ms, steps/s), the frame rate of rasterize over every Gaussian
against render_sequence's frames issued from Python or replayed (render_speed.py), the rows a frame
renders against those alive, and the index's rebuilds and size. Densification is off: the loop itself
is measured. The modes take turns and the quickest turn of each counts, so a shared machine's load
hits both alike.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from render_speed import fastest_turns, render_modes  # noqa: E402

from tomgs.cameras import Cameras, intrinsics  # noqa: E402
from tomgs.model import GaussianModel  # noqa: E402
from tomgs.train import Trainer, preset  # noqa: E402


def cloud(n: int, share: float, frames: int, device: torch.device, seed: int = 0,
          by_time: bool = False) -> GaussianModel:
    """n Gaussians 2-6 units in front of the camera, each alive over `share` of the clip; `by_time`:
    stored in the order of their centres in time (a frame's alive rows then lie close together)."""
    g = torch.Generator().manual_seed(seed)
    depth = 2 + 4 * torch.rand(n, generator=g)
    xy = (torch.rand(n, 2, generator=g) - 0.5) * depth[:, None] * 1.2
    points = torch.cat([xy, depth[:, None]], 1)
    a = 0.5
    sigma = share / 2 / math.sqrt(2 * math.log(255 * a))  # alive window: share of the clip
    t_means = torch.rand(n, generator=g) * (1 + share) - share / 2
    colors = torch.rand(n, 3, generator=g)
    if by_time:
        order = t_means.argsort()
        depth, points, t_means, colors = depth[order], points[order], t_means[order], colors[order]
    model = GaussianModel.from_points(points, colors, t_means, sigma, max_sh_degree=0,
                                      opacity=a, sizes=depth * 2.0 / math.sqrt(n))
    return model.to(device)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--gaussians", type=int, default=200_000)
    ap.add_argument("--alive", type=float, default=0.15, help="share of the clip each Gaussian is alive over")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--size", default="160x90", help="WxH")
    ap.add_argument("--steps", type=int, default=10, help="steps per timed turn")
    ap.add_argument("--by-time", action="store_true", help="the cloud stored in the order of its centres in time")
    ap.add_argument("--repeats", type=int, default=3, help="turns per mode (the quickest counts)")
    ap.add_argument("--sparse-adam", choices=("auto", "on", "off"), default="auto")
    ap.add_argument("--threads", type=int, default=1, help="torch's CPU threads (a shared machine: 1, or every "
                    "small op waits ~8 ms for a busy core)")
    args = ap.parse_args()
    device = torch.device(args.device)
    torch.set_num_threads(args.threads)
    width, height = (int(v) for v in args.size.lower().split("x"))
    T = args.frames
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (T, height, width, 3), dtype=np.uint8)
    cams = Cameras.create(np.repeat(np.eye(4)[None], T, 0), intrinsics(1.2 * max(width, height), width, height),
                          width, height)
    sparse = None if args.sparse_adam == "auto" else args.sparse_adam == "on"
    out = dict(device=str(device), gaussians=args.gaussians, alive_share=args.alive, frames=T, size=[width, height],
               by_time=args.by_time)
    trainers = {}
    for use in (False, True):
        config = preset("default", iterations=10**6, densify_start_fraction=2.0, log_interval=10**9,
                        eval_interval_s=1e9, sparse_adam=sparse, alive_index=use)
        trainer = Trainer(frames, cams, np.zeros((0, 3)), np.zeros((0, 3), np.float32), config, device,
                          initial=(cloud(args.gaussians, args.alive, T, device, by_time=args.by_time), 4.0))
        for _ in range(3):  # kernels loaded, the index built
            trainer.step()
        trainers["index" if use else "all"] = trainer
    best = {mode: math.inf for mode in trainers}
    for _ in range(args.repeats):  # the modes take turns, the quickest turn counts (a shared machine)
        for mode, trainer in trainers.items():
            sync()
            start = time.perf_counter()
            for _ in range(args.steps):
                trainer.step()
            sync()
            best[mode] = min(best[mode], (time.perf_counter() - start) / args.steps)
    for mode, trainer in trainers.items():
        row = dict(step_ms=round(best[mode] * 1e3, 2), steps_per_s=round(1 / best[mode], 2))
        if mode == "index":
            index = trainer.alive.index
            rendered = [len(trainer.model) if index.rows(k) is None else len(index.rows(k)) for k in range(T)]
            alive = [int(trainer.model.alive_at(t).sum()) for t in trainer.times]
            row.update(rows_share=round(float(np.mean(rendered)) / len(trainer.model), 4),
                       alive_share_measured=round(float(np.mean(alive)) / len(trainer.model), 4),
                       buckets=index.num_buckets, entries_per_gaussian=round(index.entries / len(trainer.model), 2),
                       index_mb=round(index.nbytes / 2**20, 1), rebuilds=trainer.alive.rebuilds)
        out[mode] = row
    # rendering, all frames: rasterize over every Gaussian, each frame waiting for its counts, against
    # render_sequence's frames (the index's rows) issued from Python or replayed, per call or kept (render_speed)
    inputs = {k: v.detach() for k, v in cloud(args.gaussians, args.alive, T, device, by_time=args.by_time)
              .render_inputs().items()}
    best = fastest_turns(render_modes(inputs, cams, device)[0], args.repeats, device)
    out["render_fps"] = {mode: round(T / seconds, 1) for mode, seconds in best.items()}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
