"""Phone videos, the users' clips: each clip fitted under a wall-clock budget as `tomgs fit VIDEO -o X.ply
--budget B` fits it, then measured over every frame; one table.

    python -m benchmarks.phone ../shared/data/phone/{dog,juggle,blocks,cat}.mp4 --minutes 2 \\
        --lpips <weights> --out <out>
    python -m benchmarks.phone CLIP --minutes 1 --set share_opacity=true --tag shared   # an ablation
    python -m benchmarks.phone --smoke          # a 6-frame synthetic clip on the CPU, seconds

Each clip: the fit (poses from the built-in tracker, as `tomgs fit` runs them, unless --poses), then
PSNR / SSIM (/ LPIPS with --lpips) of every frame. The table gives the clip, budget, quality, Gaussians,
PSNR / SSIM / LPIPS, the worst frame's PSNR, iterations and steps a second, the seconds before the first
step (reading, poses, init, compile), the cameras the tracker found (method, focal, fixed or not), and
the fit's notes on growth and the quality rounds. `--set name=value` overrides a `tomgs.TrainConfig`
setting; --tag names a run's files. Writes <out>/<clip>[-tag].ply / .csv / .psnr.png, and the table as
phone[-tag].md / .json (with each frame's PSNR).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

import tomgs
from tomgs.train import fit, output_paths, preset

if __package__:
    from .common import environment, log_rows, markdown_table, output_folder, smoke_clip_folder, write_report
else:  # run as a file: Python puts this folder first on sys.path
    from common import environment, log_rows, markdown_table, output_folder, smoke_clip_folder, write_report

BEFORE_TRAINING = ("read", "poses", "init", "compile")  # the phases before the first step


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("clips", type=Path, nargs="*", help="videos (or frame folders)")
    ap.add_argument("--minutes", type=float, default=2.0, help="wall-clock budget of each fit, poses included")
    ap.add_argument("--quality", default="default", choices=("compact", "default", "max"))
    ap.add_argument("--set", action="append", default=[], help="a TrainConfig override (JSON value)")
    ap.add_argument("--poses", default="auto", help="auto (the built-in tracker), identity, or a cameras file")
    ap.add_argument("--tag", default="", help="a name for this run's files (ablations)")
    ap.add_argument("--lpips", type=Path, help="LPIPS weights (alexnet-lpips-v0.1.npz or its folder)")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--out", type=Path, default=None, help="default bench_out/phone")
    ap.add_argument("--smoke", action="store_true", help="a 6-frame synthetic clip on the CPU, 30 iterations")
    args = ap.parse_args(argv)
    if args.smoke:
        args.device, args.poses = "cpu", "identity"
        args.set = [*args.set, "iterations=30", "stop_at_iterations=true", "eval_interval_s=1e9"]
    elif not args.clips:
        ap.error("give at least one clip (or --smoke)")
    return args


def camera_summary(notes: list[str]) -> str:
    """The tracker's note ("poses: ...") without its prefix, or '-'."""
    return next((n.split(":", 1)[1].strip() for n in notes if n.startswith("poses:")), "-")


def note_about(notes: list[str], start: str) -> str:
    return next((n for n in notes if n.startswith(start)), "-")


def main(argv=None) -> list[dict]:
    args = parse_args(argv)
    out = output_folder(args.out, args.smoke, "phone")
    if args.smoke:
        args.clips = [smoke_clip_folder(out / "clips", "smoke") / "images"]
    device = torch.device(args.device)
    overrides = {k: json.loads(v) for k, v in (s.split("=", 1) for s in args.set)}
    lpips = tomgs.LPIPS(args.lpips, device=device) if args.lpips else None
    env = environment(device, "phone", argv)
    config = preset("default", **{"quality": args.quality, "max_seconds": args.minutes * 60, **overrides})
    rows = []
    for clip in args.clips:
        name = (Path(clip).parent.name if Path(clip).name == "images" else Path(clip).stem) + (f"-{args.tag}" if args.tag else "")
        scene = out / f"{name}.ply"
        began = time.perf_counter()
        result = fit(clip, scene, config, device=device, poses=args.poses, overwrite=True, started=began,
                     progress=lambda r: print(f"  {name} it {r['iteration']} {r['wall_s']:.0f}s train {r['train_psnr']} "
                                              f"clip {r['clip_psnr']} N {r['gaussians']}", flush=True))
        wall = time.perf_counter() - began
        video = tomgs.read_video(clip, max_side=max(result.cameras.width, result.cameras.height))
        report = tomgs.evaluate(result.model, result.cameras, video.frames, device=device, lpips=lpips)
        frame_psnr = [float(p) for p in report.psnr]
        log = log_rows(output_paths(scene)["csv"])
        before = sum(result.phase_seconds.get(k, 0.0) for k in BEFORE_TRAINING)
        row = dict(clip=name, frames=len(video), size=f"{result.cameras.width}x{result.cameras.height}",
                   minutes=args.minutes, quality=args.quality, gaussians=len(result.model), psnr=report.mean_psnr,
                   ssim=report.mean_ssim, lpips=report.mean_lpips, worst_frame_psnr=min(frame_psnr),
                   iterations=result.iterations, steps_per_s=result.iterations / max(result.seconds, 1e-9),
                   first_step_s=before, wall_s=wall, cameras=camera_summary(result.notes),
                   growth=note_about(result.notes, "growth in stages"),
                   rounds=note_about(result.notes, f"quality {args.quality}"), overrides=overrides,
                   phases=result.phase_seconds, notes=result.notes, frame_psnr=frame_psnr,
                   curve=[[float(r["wall_s"]), r["train_psnr"], r["clip_psnr"], int(r["gaussians"])] for r in log])
        print(json.dumps({k: v for k, v in row.items() if k not in ("frame_psnr", "curve")}, default=str), flush=True)
        rows.append(row)
    head = ["clip", "frames", "size", "minutes", "quality", "gaussians", "psnr", "ssim", "lpips", "worst_frame_psnr",
            "iterations", "steps_per_s", "first_step_s", "cameras"]
    body = [markdown_table(head, [[r[h] for h in head] for r in rows]), ""]
    body += [f"- {r['clip']}: {r['growth']}; {r['rounds']}" for r in rows]
    write_report(out, "phone" + (f"-{args.tag}" if args.tag else ""), "phone: the users' clips", env,
                 "\n".join(body), rows)
    return rows


if __name__ == "__main__":
    main()
