"""Fit TOM-GS to DAVIS clips and report quality against run time (issue 4).

    python benchmarks/davis.py ../shared/data/davis --clips camel,cows,kite-surf --minutes 10

For each clip: poses from the built-in tracker with the DAVIS masks, a fit under a wall-clock
budget, then PSNR/SSIM over every frame (the peers' protocol), the Gaussian count, the PSNR the
fit had reached at 1, 2, 5 and 10 minutes (from its CSV), and the render speed of the result.
Writes <out>/<clip>.ply, .csv, .psnr.png and a markdown table <out>/davis.md.
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import torch

import tomgs
from tomgs.io import read_video
from tomgs.metrics import evaluate
from tomgs.render import render_sequence
from tomgs.train import fit, output_paths, preset

PAPER_PSNR = {"camel": 35.28, "cows": 30.28, "kite-surf": 43.90}


def psnr_at(csv_path: Path, seconds: float):
    """Full-clip PSNR measured last at or before `seconds` of wall time (None if not reached)."""
    best = None
    for row in csv.DictReader(open(csv_path)):
        if row["clip_psnr"] and float(row["wall_s"]) <= seconds:
            best = float(row["clip_psnr"])
    return best


def render_fps(scene_path: Path, device, repeats: int = 3) -> float:
    """Frames per second of `tomgs render`'s path (render_sequence: only Gaussians alive near each
    frame's time are projected), images left on the GPU; the clip is rendered `repeats` times."""
    scene = tomgs.load_scene(scene_path, device=device)
    inputs = {k: v.detach() for k, v in scene.model.render_inputs().items()}
    frames = list(range(len(scene.cameras)))
    for _ in render_sequence(inputs, scene.cameras, frames[:8], device=device, to_cpu=False):  # warm-up
        pass
    torch.cuda.synchronize(device)
    start = time.perf_counter()
    for _ in range(repeats):
        for _ in render_sequence(inputs, scene.cameras, frames, device=device, to_cpu=False):
            pass
    torch.cuda.synchronize(device)
    return repeats * len(frames) / (time.perf_counter() - start)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", type=Path, help="folder holding <clip>/images and <clip>/masks")
    ap.add_argument("--clips", default="camel,cows,kite-surf")
    ap.add_argument("--minutes", type=float, default=10.0, help="wall-clock budget of each fit")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--out", type=Path, default=Path("bench_out/davis"))
    ap.add_argument("--set", action="append", default=[], help="a TrainConfig override, e.g. --set max_gaussians=2000000")
    ap.add_argument("--poses", default="auto", help="auto (tracker with the DAVIS masks) or identity (ablation)")
    ap.add_argument("--tag", default="", help="a name for this run's row and files (ablations, sweeps)")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    device = torch.device("cuda")
    overrides = {k: json.loads(v) for k, v in (s.split("=", 1) for s in args.set)}
    config = preset(args.preset, **{"iterations": 200_000, "max_seconds": args.minutes * 60, **overrides})
    rows = []
    for clip in args.clips.split(","):
        video = read_video(args.root / clip / "images", masks=args.root / clip / "masks")
        name = f"{clip}-{args.tag}" if args.tag else clip
        scene = args.out / f"{name}.ply"
        start = time.perf_counter()
        result = fit(video, scene, config, device=device, poses=args.poses, overwrite=True,  # a rerun replaces its own
                     progress=lambda r: print(f"  {clip} it {r['iteration']} {r['wall_s']:.0f}s train {r['train_psnr']} "
                                              f"clip {r['clip_psnr']} N {r['gaussians']}", flush=True))
        wall = time.perf_counter() - start
        report = evaluate(result.model, result.cameras, video.frames, device=device)
        paths = output_paths(scene)
        row = dict(clip=name, frames=len(video), psnr=report.mean_psnr, ssim=report.mean_ssim,
                   gaussians=len(result.model), iterations=result.iterations, fit_s=result.seconds, wall_s=wall,
                   fps=render_fps(scene, device), paper=PAPER_PSNR.get(clip),
                   **{f"psnr_{m}min": psnr_at(paths["csv"], 60 * m) for m in (1, 2, 5, 10)})
        print(json.dumps(row), flush=True)
        rows.append(row)
    fmt = lambda v: "-" if v is None else (f"{v:.2f}" if isinstance(v, float) else str(v))  # noqa: E731
    head = ["clip", "frames", "psnr", "ssim", "paper", "psnr_1min", "psnr_2min", "psnr_5min", "psnr_10min",
            "gaussians", "iterations", "fit_s", "fps"]
    table = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    table += ["| " + " | ".join(fmt(r[h]) for h in head) + " |" for r in rows]
    text = "\n".join(table)
    (args.out / f"davis{'-' + args.tag if args.tag else ''}.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
