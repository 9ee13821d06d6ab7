"""What the alive index (`tomgs.render.alive`) saves: a training step and a rendered clip with and without it, on
a DAVIS-like synthetic cloud where a chosen share of the Gaussians is alive at each frame (each Gaussian
alive over that share of the clip, centres uniform in time, scattered in front of a fixed camera over
noise frames).

    python -m benchmarks.alive_index --device cpu --gaussians 100000 --size 160x90
    python -m benchmarks.alive_index --device cuda --gaussians 4000000 --size 854x480
    python -m benchmarks.alive_index --smoke       # 2,000 Gaussians, 8 frames at 32x18 on the CPU

Reports per mode the training step (ms, steps/s), the frame rate of rasterize over every Gaussian
against render_sequence's modes (as render_speed.py times them), the rows a frame renders against
those alive, and the index's rebuilds and size. Densification is off: the loop itself is measured.
The modes take turns and the quickest turn of each counts, so a shared machine's load hits both alike.
Writes alive_index.md / .json.
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch

import tomgs
from tomgs.cameras import intrinsics
from tomgs.train import Trainer, preset

if __package__:
    from .common import environment, fastest, markdown_table, output_folder, parse_size, render_modes, \
        write_report
else:  # run as a file: Python puts this folder first on sys.path
    from common import environment, fastest, markdown_table, output_folder, parse_size, render_modes, write_report


def cloud(n: int, share: float, device: torch.device, seed: int = 0) -> tomgs.GaussianModel:
    """n Gaussians 2-6 units in front of the camera, each alive over `share` of the clip."""
    g = torch.Generator().manual_seed(seed)
    depth = 2 + 4 * torch.rand(n, generator=g)
    xy = (torch.rand(n, 2, generator=g) - 0.5) * depth[:, None] * 1.2
    points = torch.cat([xy, depth[:, None]], 1)
    a = 0.5
    sigma = share / 2 / math.sqrt(2 * math.log(255 * a))  # alive window: share of the clip
    t_means = torch.rand(n, generator=g) * (1 + share) - share / 2
    colors = torch.rand(n, 3, generator=g)
    model = tomgs.GaussianModel.from_points(points, colors, t_means, sigma, max_sh_degree=0, opacity=a,
                                            sizes=depth * 2.0 / math.sqrt(n))
    return model.to(device)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--gaussians", type=int, default=200_000)
    ap.add_argument("--alive", type=float, default=0.15, help="share of the clip each Gaussian is alive over")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--size", default="160x90", help="WxH")
    ap.add_argument("--steps", type=int, default=10, help="steps per timed turn")
    ap.add_argument("--repeats", type=int, default=3, help="turns per mode (the quickest counts)")
    ap.add_argument("--sparse-adam", choices=("auto", "on", "off"), default="auto")
    ap.add_argument("--threads", type=int, default=1, help="torch's CPU threads (a shared machine: 1, or every "
                    "small op waits ~8 ms for a busy core)")
    ap.add_argument("--out", default=None, help="default bench_out/alive_index")
    ap.add_argument("--smoke", action="store_true", help="2,000 Gaussians, 8 frames at 32x18 on the CPU, one turn")
    args = ap.parse_args(argv)
    if args.smoke:
        args.device, args.gaussians, args.frames, args.size, args.steps, args.repeats = "cpu", 2000, 8, "32x18", 2, 1
    out = output_folder(args.out, args.smoke, "alive_index")
    device = torch.device(args.device)
    threads = torch.get_num_threads()
    torch.set_num_threads(args.threads)
    try:
        result = measure(args, argv, out, device)
    finally:
        torch.set_num_threads(threads)  # a caller in this process keeps its own
    return result


def measure(args, argv, out, device: torch.device) -> dict:
    """The measurement of `main` (`argv` its arguments), with torch's CPU threads set."""
    width, height = parse_size(args.size)
    T = args.frames
    frames = np.random.default_rng(0).integers(0, 256, (T, height, width, 3), dtype=np.uint8)
    cams = tomgs.Cameras.create(np.repeat(np.eye(4)[None], T, 0), intrinsics(1.2 * max(width, height), width, height),
                                width, height)
    sparse = None if args.sparse_adam == "auto" else args.sparse_adam == "on"
    result = dict(gaussians=args.gaussians, alive_share=args.alive, frames=T, size=[width, height])
    trainers = {}
    for use in (False, True):
        config = preset("default", iterations=10**6, densify_start_fraction=2.0, log_interval=10**9,
                        eval_interval_s=1e9, sparse_adam=sparse, alive_index=use)
        trainer = Trainer(frames, cams, np.zeros((0, 3)), np.zeros((0, 3), np.float32), config, device,
                          initial=(cloud(args.gaussians, args.alive, device), 4.0))
        for _ in range(3):  # kernels loaded, the index built
            trainer.step()
        trainers["index" if use else "all"] = trainer

    def steps_of(trainer):
        def go():
            for _ in range(args.steps):
                trainer.step()
        return go

    best = fastest({mode: steps_of(trainer) for mode, trainer in trainers.items()}, args.repeats, device)
    for mode, trainer in trainers.items():
        row = dict(step_ms=round(best[mode] / args.steps * 1e3, 2), steps_per_s=round(args.steps / best[mode], 2))
        if mode == "index":
            index = trainer.alive.index
            rendered = [len(trainer.model) if index.rows(k) is None else len(index.rows(k)) for k in range(T)]
            alive = [int(trainer.model.alive_at(t).sum()) for t in trainer.times]
            row.update(rows_share=round(float(np.mean(rendered)) / len(trainer.model), 4),
                       alive_share_measured=round(float(np.mean(alive)) / len(trainer.model), 4),
                       buckets=index.num_buckets, entries_per_gaussian=round(index.entries / len(trainer.model), 2),
                       index_mb=round(index.nbytes / 2**20, 1), rebuilds=trainer.alive.rebuilds)
        result[mode] = row
    # rendering every frame: rasterize over every Gaussian against render_sequence's modes (render_speed.py)
    inputs = {k: v.detach() for k, v in cloud(args.gaussians, args.alive, device).render_inputs().items()}
    with torch.no_grad():
        seconds = fastest(render_modes(inputs, cams, device)[0], args.repeats, device)
    result["render_fps"] = {mode: round(T / s, 1) for mode, s in seconds.items()}
    body = (f"{args.gaussians:,} Gaussians each alive over {args.alive:.0%} of {T} frames at {width}x{height}; "
            f"the index lists {result['index']['rows_share']:.1%} of the rows a frame "
            f"({result['index']['alive_share_measured']:.1%} alive)\n\n"
            + markdown_table(["training step", "ms", "steps/s"],
                             [[mode, result[mode]["step_ms"], result[mode]["steps_per_s"]] for mode in trainers])
            + "\n\nframes per second:\n\n"
            + markdown_table(list(result["render_fps"]), [list(result["render_fps"].values())]))
    write_report(out, "alive_index", "alive_index: what the alive index saves",
                 environment(device, "alive_index", argv), body, result)
    return result


if __name__ == "__main__":
    main()
