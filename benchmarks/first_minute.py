"""The first minute of a fit (issue 15): full-clip PSNR against the whole fit's wall time, start-up
included, for one schedule and its variants, each in a fresh process as a user's `tomgs fit` runs.

    python benchmarks/first_minute.py ../shared/data/davis/camel --minutes 5 --stop-s 75 \
        --variant base: --variant thr1e-4:grad_threshold=1e-4 --out $OUT

Each variant fits the clip (its DAVIS masks for the poses, as benchmarks/davis.py does) under the
schedule of a `--minutes` budget and is stopped after `--stop-s` seconds of the whole fit, so that
the first minute of a 5-minute schedule costs about a minute to see. Prints and writes, per variant,
the time spent before training (process start, imports, reading, poses, initialisation), the first
steps' time, and the PSNR curve against whole-fit seconds (<out>/first_minute.json).
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

MARKS = (30, 45, 60, 75)


def run_one(clip: Path, minutes: float, stop_s: float, overrides: dict, out: Path, device: str) -> None:
    """In this (fresh) process: fit until `stop_s` seconds after the process began, print a JSON line."""
    began = time.perf_counter()
    import torch

    from tomgs.io import read_video
    from tomgs.train import fit, preset
    from tomgs.train.checkpoint import FitInterrupted

    imported = time.perf_counter() - began
    config = preset("default", iterations=200_000, max_seconds=minutes * 60, eval_interval_s=5.0, **overrides)
    video = read_video(clip / "images", masks=clip / "masks")
    first = {}

    def progress(row):
        now = time.perf_counter() - began
        first.setdefault("offset", now - row["wall_s"])  # whole-process seconds before training began
        if now >= stop_s:
            raise KeyboardInterrupt

    try:
        fit(video, out / "scene.ply", config, device=torch.device(device), poses="auto", overwrite=True,
            progress=progress, started=began)
    except FitInterrupted:
        pass
    rows = list(csv.DictReader(open(out / "scene.csv")))
    offset = first["offset"]
    curve = [(round(offset + float(r["wall_s"]), 2), float(r["clip_psnr"]), int(r["gaussians"]))
             for r in rows if r["clip_psnr"]]
    steps = [(int(r["iteration"]), float(r["wall_s"])) for r in rows]
    print(json.dumps(dict(imported_s=round(imported, 2), before_train_s=round(offset, 2), first_row=steps[0],
                          curve=curve, steps_per_s=round(steps[-1][0] / max(steps[-1][1], 1e-9), 1))), flush=True)


def psnr_by(curve, seconds):
    best = None
    for t, value, _ in curve:
        if t <= seconds:
            best = value
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("clip", type=Path, help="a DAVIS clip folder (images/, masks/)")
    ap.add_argument("--minutes", type=float, default=5.0, help="the budget whose schedule runs")
    ap.add_argument("--stop-s", type=float, default=75.0, help="stop each fit this many seconds into it")
    ap.add_argument("--variant", action="append", default=[],
                    help="name:key=value,key=value (TrainConfig overrides; 'base:' for none)")
    ap.add_argument("--out", type=Path, default=Path("bench_out/first_minute"))
    ap.add_argument("--device", default="cuda", help="cuda; cpu only for a dry run of the script")
    ap.add_argument("--one", help=argparse.SUPPRESS)  # internal: run one variant in this process
    args = ap.parse_args()
    if args.one is not None:
        run_one(args.clip, args.minutes, args.stop_s, json.loads(args.one), args.out, args.device)
        return
    results = {}
    for spec in args.variant or ["base:"]:
        name, _, sets = spec.partition(":")
        overrides = {k: json.loads(v) for k, v in (s.split("=", 1) for s in sets.split(",") if s)}
        folder = args.out / name
        folder.mkdir(parents=True, exist_ok=True)
        done = subprocess.run([sys.executable, __file__, str(args.clip), "--minutes", str(args.minutes), "--stop-s",
                               str(args.stop_s), "--out", str(folder), "--device", args.device, "--one", json.dumps(overrides)],
                              capture_output=True, text=True)
        lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
        if done.returncode or not lines:
            print(f"{name}: failed (exit {done.returncode})\n{done.stderr[-3000:]}", flush=True)
            continue
        results[name] = dict(overrides=overrides, **json.loads(lines[-1]))
        r = results[name]
        marks = " ".join(f"{m}s {psnr_by(r['curve'], m)}" for m in MARKS)
        print(f"{name}: before training {r['before_train_s']} s, first row {r['first_row']}, {r['steps_per_s']} "
              f"steps/s; PSNR by {marks}; N at end {r['curve'][-1][2] if r['curve'] else '-'}", flush=True)
        if done.stderr.strip():
            print("  stderr: " + done.stderr.strip().replace("\n", "\n  ")[-800:], flush=True)
    (args.out / "first_minute.json").write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
