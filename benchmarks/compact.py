"""Size beside error: DAVIS clips fitted at each quality level (`tomgs fit --quality`), their Gaussians and
scene bytes beside PSNR / SSIM / LPIPS and the paper's figures.

    python -m benchmarks.compact <clips> --clips camel,cows,kite-surf --minutes 2 --qualities default,max \\
        --lpips <weights> --out <out>
    python -m benchmarks.compact --smoke        # a tiny synthetic clip on the CPU

For each clip and quality: poses from the built-in tracker with the DAVIS masks and a fit whose whole wall
time, reading and poses included, is the budget (`tomgs fit --budget`: training takes what the rest leaves),
then over every frame PSNR, SSIM (and LPIPS with --lpips), the Gaussians kept, the scene file's bytes, and
from the fit's log the full-clip PSNR and the Gaussians at each of MARKS seconds of the whole fit and at
every full-clip measurement (the quality rule's rounds among them: `curve`), and the growth stages from the
fit's notes. `--rule per_halving,in_all[,per_gaussian]` replaces the prices of every level but max (a sweep). Writes
<out>/<clip>-<quality>.ply/.csv/.psnr.png and the table as compact.md and compact.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import torch

import tomgs
from tomgs.train import fit, output_paths, preset
from tomgs.train.sparsify import QUALITY_RULES

if __package__:
    from .common import PAPER, clip_parser, log_rows, markdown_table, parse_clip_args, psnr_at, start_clip_run, \
        write_report
else:  # run as a file (python benchmarks/compact.py): Python puts this folder first on sys.path
    from common import PAPER, clip_parser, log_rows, markdown_table, parse_clip_args, psnr_at, start_clip_run, \
        write_report

MARKS = (60, 120, 300)  # seconds of the whole fit at which the curve is read


def gaussians_at(rows: list[dict], seconds: float, offset: float = 0.0):
    """Gaussians of the last log row at or before `seconds` of the whole fit (the log's training seconds
    shifted by `offset`); None if none by then."""
    count = None
    for row in rows:
        if offset + float(row["wall_s"]) <= seconds:
            count = int(row["gaussians"])
    return count


def curve(rows: list[dict], offset: float = 0.0) -> list[list]:
    """[[seconds of the whole fit, Gaussians, full-clip PSNR], ...]: every measurement over all the frames."""
    every = max((int(r["clip_frames"] or 0) for r in rows), default=0)
    return [[round(offset + float(r["wall_s"]), 2), int(r["gaussians"]), float(r["clip_psnr"])]
            for r in rows if r["clip_psnr"] and int(r["clip_frames"] or 0) == every]


def parse_args(argv=None) -> argparse.Namespace:
    ap = clip_parser(__doc__, "compact", 2.0, "12-s fits")
    ap.add_argument("--qualities", default="default,max", help="quality levels, comma separated")
    ap.add_argument("--rule", help="per_halving,in_all[,per_gaussian]: the prices of every level but max (sweeps; "
                                   "tomgs.train.sparsify.QualityRule)")
    return parse_clip_args(ap, argv, smoke_minutes=0.2)


def main(argv=None) -> list[dict]:
    args = parse_args(argv)
    out, device, overrides, lpips, env = start_clip_run(args, "compact", argv)
    if args.rule:
        prices = dict(zip(("per_halving", "in_all", "per_gaussian"), (float(v) for v in args.rule.split(","))))
        for name, rule in QUALITY_RULES.items():
            if rule is not None:
                QUALITY_RULES[name] = dataclasses.replace(rule, **prices)
    suffix = f"-{args.tag}" if args.tag else ""
    rows = []
    for clip in args.clips.split(","):
        began = time.perf_counter()
        video = tomgs.read_video(args.root / clip / "images", masks=args.root / clip / "masks")
        read_s = time.perf_counter() - began
        for quality in args.qualities.split(","):
            # a full-clip PSNR every 10 s (at most 10% of the run: Trainer.run), so the curve is read near each mark
            config = preset("default", **{"quality": quality, "max_seconds": args.minutes * 60, "eval_interval_s": 10.0,
                                          **overrides})
            scene = out / f"{clip}-{quality}{suffix}.ply"
            started = time.perf_counter() - read_s  # the budget counts the reading, as `tomgs fit` does
            result = fit(video, scene, config, device=device, poses=args.poses, overwrite=True, started=started)
            ended = time.perf_counter() - started
            report = tomgs.evaluate(result.model, result.cameras, video.frames, device=device, lpips=lpips)
            log = log_rows(output_paths(scene)["csv"])
            before = read_s + sum(v for k, v in result.phase_seconds.items() if k in ("read", "poses", "init"))
            paper = PAPER.get(clip, {})
            row = dict(clip=clip, quality=quality, frames=len(video), gaussians=len(result.model),
                       scene_bytes=scene.stat().st_size, psnr=report.mean_psnr, ssim=report.mean_ssim,
                       lpips=report.mean_lpips, paper_psnr=paper.get("psnr"), paper_ssim=paper.get("ssim"),
                       paper_lpips=paper.get("lpips"), wall_s=ended, before_train_s=before,
                       iterations=result.iterations, steps_per_s=result.iterations / max(result.seconds, 1e-9),
                       **{f"psnr_{m}s": psnr_at(log, m, before)[0] if m <= ended + 1 else None for m in MARKS},
                       **{f"gaussians_{m}s": gaussians_at(log, m, before) if m <= ended + 1 else None for m in MARKS},
                       curve=curve(log, before), notes=result.notes)
            print(json.dumps({k: v for k, v in row.items() if k not in ("curve", "notes")}, default=str), flush=True)
            rows.append(row)
            del result, report
            if device.type == "cuda":
                torch.cuda.empty_cache()
    head = ["clip", "quality", "gaussians", "scene_bytes", "psnr", "paper_psnr", "ssim", "paper_ssim", "lpips",
            "paper_lpips", *(f"psnr_{m}s" for m in MARKS), *(f"gaussians_{m}s" for m in MARKS), "wall_s"]
    write_report(out, f"compact{suffix}", "compact: size beside error", env,
                 markdown_table(head, [[r[h] for h in head] for r in rows]), rows)
    return rows


if __name__ == "__main__":
    main()
