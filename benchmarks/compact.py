"""Size beside error: fits of DAVIS clips at each quality level, their Gaussians and scene bytes beside
PSNR / SSIM / LPIPS and the paper's figures.

    python benchmarks/compact.py ../shared/data/davis --clips camel,cows,kite-surf --minutes 2 \
        --qualities default,max --lpips ../shared/data/lpips --out $OUT
    python benchmarks/compact.py --smoke --out /tmp/compact_smoke     # CPU: a tiny synthetic clip

For each clip and quality: poses from the built-in tracker with the DAVIS masks and a fit whose whole
wall time, poses included, is the budget (`tomgs fit --budget`: training takes what the rest leaves;
`--quality` as given), then over every frame PSNR, SSIM (and LPIPS with --lpips), the Gaussians kept,
the scene file's bytes, and from the fit's CSV the full-clip PSNR and the Gaussians at each mark
(MARKS seconds of the whole fit, reading and poses included) and at every round of the quality rule.
Writes <out>/<clip>-<quality>.ply/.csv/.psnr.png, compact.json and compact.md.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from davis import PAPER, psnr_at  # noqa: E402
from tomgs.io import read_video  # noqa: E402
from tomgs.metrics import LPIPS, evaluate  # noqa: E402
from tomgs.train import fit, output_paths, preset  # noqa: E402
from tomgs.train.sparsify import QUALITY_RULES, QualityRule  # noqa: E402

MARKS = (60, 120, 300)  # seconds of the whole fit at which the curve is read


def gaussians_at(csv_path: Path, seconds: float, offset: float = 0.0):
    """Gaussians of the last CSV row at or before `seconds` of the fit's wall time (training seconds
    shifted by `offset`); None if none by then."""
    count = None
    for row in csv.DictReader(open(csv_path)):
        if offset + float(row["wall_s"]) <= seconds:
            count = int(row["gaussians"])
    return count


def rounds(csv_path: Path, offset: float = 0.0) -> list[list]:
    """[[fit seconds, Gaussians, full-clip PSNR], ...]: every full-clip measurement of the CSV (the quality
    rule's rounds among them), for the curve of PSNR against Gaussians."""
    rows = list(csv.DictReader(open(csv_path)))
    every = max((int(r["clip_frames"] or 0) for r in rows), default=0)
    return [[round(offset + float(r["wall_s"]), 2), int(r["gaussians"]), float(r["clip_psnr"])]
            for r in rows if r["clip_psnr"] and int(r["clip_frames"] or 0) == every]


def smoke_clip(root: Path) -> str:
    """A tiny clip folder under `root` (the demo scene's 6 frames at 64x36 as PNGs, no masks): its name."""
    import cv2

    from tomgs.demo import demo_scene
    from tomgs.sequence import render_sequence

    gaussians, cams = demo_scene(num_frames=6, width=64, height=36)
    images = root / "demo" / "images"
    images.mkdir(parents=True)
    for k, (_, image, _) in enumerate(render_sequence(gaussians, cams, background=(0.05, 0.05, 0.08))):
        rgb = (image.numpy() * 255 + 0.5).clip(0, 255).astype(np.uint8)
        cv2.imwrite(str(images / f"{k:05d}.png"), rgb[..., ::-1])
    return "demo"


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", type=Path, nargs="?", help="folder holding <clip>/images and <clip>/masks")
    ap.add_argument("--clips", default="camel,cows,kite-surf")
    ap.add_argument("--qualities", default="default,max", help="TrainConfig.quality levels, comma separated")
    ap.add_argument("--minutes", type=float, default=2.0, help="wall-clock budget of each fit, poses included")
    ap.add_argument("--out", type=Path, default=Path("bench_out/compact"))
    ap.add_argument("--set", action="append", default=[], help="a TrainConfig override, e.g. --set sparsify_rounds=8")
    ap.add_argument("--tag", default="", help="a name for this run's files (sweeps)")
    ap.add_argument("--lpips", type=Path, help="LPIPS weights (alexnet-lpips-v0.1.npz or its folder)")
    ap.add_argument("--rule", help="per_halving,in_all (dB): replaces the quality rule of every level but max (sweeps)")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--smoke", action="store_true", help="CPU: a tiny synthetic clip, 20-s fits, identity poses")
    args = ap.parse_args(argv)
    poses = "auto"
    if args.smoke:
        args.root = Path(tempfile.mkdtemp(prefix="compact_smoke_"))
        args.clips, args.device, poses = smoke_clip(args.root), "cpu", "identity"
        args.minutes = min(args.minutes, 1 / 3)  # 20-s fits at most
    if args.root is None:
        ap.error("give the clips' folder (or --smoke)")
    if args.rule:
        per_halving, in_all = (float(v) for v in args.rule.split(","))
        for name, rule in QUALITY_RULES.items():
            if rule is not None:
                QUALITY_RULES[name] = QualityRule(per_halving, in_all)
    args.out.mkdir(parents=True, exist_ok=True)
    device = torch.device(args.device)
    overrides = {k: json.loads(v) for k, v in (s.split("=", 1) for s in args.set)}
    lpips = LPIPS(args.lpips, device=device) if args.lpips else None
    rows = []
    suffix = f"-{args.tag}" if args.tag else ""
    for clip in args.clips.split(","):
        masks = args.root / clip / "masks"
        began = time.perf_counter()
        video = read_video(args.root / clip / "images", masks=masks if masks.is_dir() else None)
        read_s = time.perf_counter() - began  # decoding the frames, outside the fit here
        for quality in args.qualities.split(","):
            # a full-clip PSNR every 10 s (at most 10% of the run: Trainer.run), so the curve is read near each mark
            config = preset("default", **{"quality": quality, "max_seconds": args.minutes * 60, "eval_interval_s": 10.0,
                                          **overrides})
            scene = args.out / f"{clip}-{quality}{suffix}.ply"
            started = time.perf_counter() - read_s  # the budget counts the reading, as `tomgs fit` does
            result = fit(video, scene, config, device=device, poses=poses, overwrite=True, started=started)
            report = evaluate(result.model, result.cameras, video.frames, device=device, lpips=lpips)
            paths = output_paths(scene)
            before = read_s + sum(v for k, v in result.phase_seconds.items() if k in ("read", "poses", "init"))
            paper = PAPER.get(clip, {})
            ended = time.perf_counter() - started
            row = dict(clip=clip, quality=quality, frames=len(video), psnr=report.mean_psnr, ssim=report.mean_ssim,
                       lpips=report.mean_lpips, gaussians=len(result.model), scene_bytes=scene.stat().st_size,
                       paper_psnr=paper.get("psnr"), paper_ssim=paper.get("ssim"), paper_lpips=paper.get("lpips"),
                       wall_s=round(ended, 2), before_train_s=round(before, 2),
                       iterations=result.iterations, steps_per_s=round(result.iterations / max(result.seconds, 1e-9), 1),
                       **{f"psnr_{m}s": psnr_at(paths["csv"], m, before) if m <= ended + 1 else None for m in MARKS},
                       **{f"gaussians_{m}s": gaussians_at(paths["csv"], m, before) if m <= ended + 1 else None
                          for m in MARKS},
                       curve=rounds(paths["csv"], before), notes=result.notes)
            print(json.dumps({k: v for k, v in row.items() if k not in ("curve", "notes")}), flush=True)
            rows.append(row)
            (args.out / f"compact{suffix}.json").write_text(json.dumps(rows, indent=1) + "\n")
            del result, report
            if device.type == "cuda":
                torch.cuda.empty_cache()
    fmt = lambda v: "-" if v is None else (f"{v:.3f}" if isinstance(v, float) and v < 1 else  # noqa: E731
                                          f"{v:.2f}" if isinstance(v, float) else f"{v:,}" if isinstance(v, int) else str(v))
    head = ["clip", "quality", "gaussians", "scene_bytes", "psnr", "paper_psnr", "ssim", "paper_ssim", "lpips",
            "paper_lpips", *(f"psnr_{m}s" for m in MARKS), *(f"gaussians_{m}s" for m in MARKS), "wall_s"]
    table = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    table += ["| " + " | ".join(fmt(r[h]) for h in head) + " |" for r in rows]
    text = "\n".join(table)
    (args.out / f"compact{suffix}.md").write_text(text + "\n")
    print(text)
    return rows


if __name__ == "__main__":
    main()
