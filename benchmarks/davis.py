"""Quality per minute on DAVIS clips: fit each clip under a wall-clock budget and report its PSNR against
the whole fit's wall time, its final PSNR / SSIM (/ LPIPS), and how fast its scene renders.

    python -m benchmarks.davis <clips> --clips camel,cows,kite-surf,blackswan,dog,car-shadow \\
        --minutes 5 --set max_gaussians=5000000 --lpips <weights> --profile --out <out>
    python -m benchmarks.davis --smoke          # a tiny synthetic clip on the CPU, seconds

(`python benchmarks/davis.py ...` runs the same.) For each clip: poses from the built-in tracker with
the DAVIS masks, a fit under the budget (the preset's schedules follow it), then PSNR/SSIM (and LPIPS
with --lpips) over every frame (the peers' protocol), the Gaussian count, the full-clip PSNR the fit
had reached at 30 s, 1, 2 and 5 minutes of the whole fit's wall time (reading and poses included),
when it passed the paper's figure, steps per second, and the render speed of the result: `fps`, a
`tomgs.ClipRenderer` kept across passes; `fps_call`, whole `render_sequence` calls as `tomgs render`
makes them. --profile adds the training step's kernels at the end of the fit (the fitted scene
training on, densification off; CUDA). `--set name=value` overrides a `tomgs.TrainConfig` setting
(the paper's ablations: `--set sampling='"uniform"'`, `--set opacity_reset_interval=3000`,
`--set temporal=false`, and `--poses identity`).
Writes <out>/<clip>.ply, .csv, .psnr.png, and the table as davis.md and davis.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

import tomgs
from tomgs.train import Trainer, fit, output_paths, preset

if __package__:
    from .common import PAPER, clip_parser, kernel_times, log_rows, markdown_table, parse_clip_args, psnr_at, \
        scene_fps, start_clip_run, sync, time_to, write_report
else:  # run as a file (python benchmarks/davis.py): Python puts this folder first on sys.path
    from common import PAPER, clip_parser, kernel_times, log_rows, markdown_table, parse_clip_args, psnr_at, \
        scene_fps, start_clip_run, sync, time_to, write_report

MARKS = (30, 60, 120, 300)  # seconds of the whole fit at which the curve is read


def step_profile(scene_path: Path, frames, device: torch.device, iters: int = 30) -> dict:
    """The training step at the end of a fit (CUDA): the fitted scene trains on, densification off; wall
    ms per step and GPU ms per kernel (the largest 12)."""
    import numpy as np

    scene = tomgs.load_scene(scene_path, device=device)
    config = preset("default", densify_start_fraction=2.0, log_interval=10**9, eval_interval_s=1e9)
    no_points = np.zeros((0, 3)), np.zeros((0, 3), np.float32)
    trainer = Trainer(frames, scene.cameras, *no_points, config, device,
                      initial=(scene.model, float(scene.info.get("extent", 1.0))))
    for _ in range(5):
        trainer.step()
    sync(device)
    start = time.perf_counter()
    for _ in range(iters):
        trainer.step()
    sync(device)
    wall = (time.perf_counter() - start) / iters * 1e3
    kernels = kernel_times(trainer.step, iters)
    top = dict(sorted(kernels.items(), key=lambda kv: -kv[1])[:12])
    return dict(wall_ms=wall, gpu_ms=sum(kernels.values()), kernels_ms=top)


def parse_args(argv=None) -> argparse.Namespace:
    ap = clip_parser(__doc__, "davis", 10.0, "40 iterations")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--profile", action="store_true", help="profile the training step at the end of each fit (CUDA)")
    args = parse_clip_args(ap, argv, smoke_minutes=1.0)
    if args.smoke:
        args.set = [*args.set, "iterations=40", "stop_at_iterations=true", "eval_interval_s=1e9"]
    return args


def main(argv=None) -> list[dict]:
    args = parse_args(argv)
    out, device, overrides, lpips, env = start_clip_run(args, "davis", argv)
    # a full-clip PSNR every 10 s (at most 10% of the run: Trainer.run), so the curve is read within 10 s
    # of each mark
    config = preset(args.preset, **{"iterations": 200_000, "max_seconds": args.minutes * 60, "eval_interval_s": 10.0,
                                    **overrides})
    suffix = f"-{args.tag}" if args.tag else ""
    rows = []
    for clip in args.clips.split(","):
        began = time.perf_counter()
        video = tomgs.read_video(args.root / clip / "images", masks=args.root / clip / "masks")
        read_s = time.perf_counter() - began  # decoding the frames, outside the fit here
        name = f"{clip}-{args.tag}" if args.tag else clip
        scene = out / f"{name}.ply"
        start = time.perf_counter()
        result = fit(video, scene, config, device=device, poses=args.poses, overwrite=True,  # a rerun replaces its own
                     progress=lambda r: print(f"  {clip} it {r['iteration']} {r['wall_s']:.0f}s train {r['train_psnr']} "
                                              f"clip {r['clip_psnr']} N {r['gaussians']}", flush=True))
        wall = time.perf_counter() - start
        report = tomgs.evaluate(result.model, result.cameras, video.frames, device=device, lpips=lpips)
        log = log_rows(output_paths(scene)["csv"])
        # the CSV counts seconds of training; the curve is read against the whole fit's wall time
        before = read_s + sum(v for k, v in result.phase_seconds.items() if k in ("read", "poses", "init"))
        paper = PAPER.get(clip, {})
        row = dict(clip=name, frames=len(video), psnr=report.mean_psnr, ssim=report.mean_ssim,
                   lpips=report.mean_lpips, paper_psnr=paper.get("psnr"), paper_ssim=paper.get("ssim"),
                   paper_lpips=paper.get("lpips"), gaussians=len(result.model), iterations=result.iterations,
                   steps_per_s=result.iterations / max(result.seconds, 1e-9), fit_s=result.seconds, wall_s=wall,
                   before_train_s=before, phases=result.phase_seconds, **scene_fps(scene, device),
                   notes=result.notes, paper_at_s=time_to(log, paper["psnr"], before) if paper else None,
                   **{f"psnr_{m}s": psnr_at(log, m, before)[0] for m in MARKS})
        if args.profile and device.type == "cuda":
            row["profile"] = step_profile(scene, video.frames, device)
        print(json.dumps(row, default=str), flush=True)
        rows.append(row)
    head = ["clip", "frames", "paper_psnr", *(f"psnr_{m}s" for m in MARKS), "paper_at_s", "psnr", "ssim",
            "paper_ssim", "lpips", "paper_lpips", "gaussians", "steps_per_s", "before_train_s", "fps", "fps_call"]
    body = [markdown_table(head, [[r[h] for h in head] for r in rows])]
    for r in rows:
        if "profile" in r:
            p = r["profile"]
            body += ["", f"{r['clip']}: training step at the end of the fit, {p['wall_ms']:.2f} ms wall, "
                         f"{p['gpu_ms']:.2f} ms of GPU kernels; largest: " +
                     ", ".join(f"{k.split('(')[0][:40]} {v:.2f}" for k, v in list(p["kernels_ms"].items())[:6])]
    write_report(out, f"davis{suffix}", "davis: quality per minute", env, "\n".join(body), rows)
    return rows


if __name__ == "__main__":
    main()
