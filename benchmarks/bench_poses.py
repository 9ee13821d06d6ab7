"""Camera-pose benchmark: the built-in tracker on real clips (DAVIS layout).

For each sequence folder (<seq>/images/*.jpg, optional <seq>/masks/*.png) it reports the median
reprojection error of background track observations after the final bundle adjustment, the
estimated focal length, and the wall time, also scaled to seconds per 100 frames.

    python benchmarks/bench_poses.py [DATA ...] [--max-side 854] [--no-masks] [--focal F]

DATA defaults to ../shared/data/davis (every sequence in it); a path may also be one sequence.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tomgs.io import read_video  # noqa: E402
from tomgs.poses import estimate_cameras  # noqa: E402


def sequences(paths):
    for p in map(Path, paths):
        if (p / "images").is_dir():
            yield p
        else:
            yield from sorted(q for q in p.iterdir() if (q / "images").is_dir())


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", nargs="*", default=[str(Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "davis")])
    ap.add_argument("--max-side", type=int, default=854)
    ap.add_argument("--no-masks", action="store_true", help="find moving content by flow residuals instead")
    ap.add_argument("--focal", type=float, default=None)
    ap.add_argument("--frames", default=None, help="frame range, e.g. 0:50")
    args = ap.parse_args()

    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"masks: {'flow residuals' if args.no_masks else 'given'}, max side {args.max_side}")
    print("| sequence | frames | size | mode | focal px | reproj median px (kept) | reproj median px (all) "
          "| rejected | points | s | s / 100 frames |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    errs, rates = [], []
    for seq in sequences(args.data):
        masks = None if args.no_masks or not (seq / "masks").is_dir() else seq / "masks"
        video = read_video(seq / "images", frames=args.frames, max_side=args.max_side, masks=masks)
        t0 = time.perf_counter()
        cams, pts, _, rep = estimate_cameras(video, focal=args.focal)
        dt = time.perf_counter() - t0
        per100 = dt / len(video) * 100
        errs.append((rep.reproj_px, rep.reproj_all_px))
        rates.append(per100)
        T, H, W = video.frames.shape[:3]
        print(f"| {seq.name} | {T} | {W}x{H} | {rep.mode} | {rep.focal:.0f} | {rep.reproj_px:.3f} | "
              f"{rep.reproj_all_px:.3f} | {100 * rep.rejected:.1f}% | {len(pts)} | {dt:.1f} | {per100:.1f} |", flush=True)
        if os.environ.get("BENCH_VERBOSE"):
            print("   ", rep.notes, {k: round(v, 2) for k, v in rep.timings.items()}, flush=True)
    e = np.array(errs)
    print(f"| **median** | | | | | {np.median(e[:, 0]):.3f} | {np.median(e[:, 1]):.3f} | | | | {np.median(rates):.1f} |")


if __name__ == "__main__":
    main()
