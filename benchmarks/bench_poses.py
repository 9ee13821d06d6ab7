"""Camera-pose benchmark: the built-in tracker on real clips (DAVIS layout) or synthetic clips.

Real clips: for each sequence folder (<seq>/images/*.jpg, optional <seq>/masks/*.png) it reports
the median reprojection error of background track observations after the final bundle
adjustment, the estimated focal length, and the wall time, also scaled to seconds per 100 frames.

    python benchmarks/bench_poses.py [DATA ...] [--max-side 854] [--no-masks] [--focal F]

DATA defaults to ../shared/data/davis (every sequence in it); a path may also be one sequence.

Synthetic clips (tomgs.poses.synthetic, known cameras): each case runs in its own process so that
its peak host memory is its own; frames are rendered as the tracker reads them (their rendering
time is subtracted) unless --hold, which renders them all first into one uint8 array as
read_video gives them. Reports time, peak host memory (RSS, and above what the process held
before the tracker started), peak GPU memory, trajectory error (fraction of the path, after a
similarity alignment), rotation error (degrees) and focal error, and writes them as JSON.

    python benchmarks/bench_poses.py --synthetic orbit:300:1920x1080 orbit:900:1920x1080 \\
        orbit:300:1080x1920 --device cuda --json poses_bench.json

A case is PATH:FRAMES:WxH with PATH orbit or pan (the camera path).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
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


def real_clips(args):
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
        cams, pts, _, rep = estimate_cameras(video, focal=args.focal, device=args.device)
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


def rss_gb() -> float:
    """Current resident set size of this process (GB), from /proc."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e9


def one_case(case: str, args) -> dict:
    """Run the tracker on one synthetic case in this process; the figures as a dict."""
    import torch

    from tomgs.poses.synthetic import make_clip, orbit, pan, trajectory_errors

    path, T, size = case.split(":")
    W, H = map(int, size.split("x"))
    T = int(T)
    focal = 0.9 * max(W, H)  # a phone's main camera: ~65 degrees across the long side
    c2w = orbit(T, strafe=2.4) if path == "orbit" else pan(T, yaw_deg=20, pitch_deg=6)
    clip = make_clip(c2w, width=W, height=H, focal=focal, mover=True, seed=0, lazy=not args.hold)
    frames, masks = clip.frames, None if args.no_masks else clip.masks
    if args.hold:
        frames, masks = np.stack(list(frames)), None if masks is None else np.stack(list(masks))
    base = rss_gb()
    cuda = args.device == "cuda"
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    calls = []
    kw = {} if args.device is None else {"device": args.device}
    t0 = time.perf_counter()
    cams, pts, _, rep = estimate_cameras(frames, masks, focal=args.focal, progress=lambda d, t: calls.append(
        time.perf_counter()), **kw)
    render_s = 0.0 if args.hold else clip.frames.clip.seconds
    dt = time.perf_counter() - t0 - render_s
    traj, rot = trajectory_errors(cams.c2w, clip.c2w)
    gaps = np.diff([t0] + calls) if calls else np.array([dt])
    return dict(case=case, frames=T, width=W, height=H, device=args.device or "auto", held=bool(args.hold),
                masks=masks is not None, seconds=round(dt, 2), render_seconds=round(render_s, 2),
                peak_rss_gb=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6, 3),
                rss_before_gb=round(base, 3), frames_uint8_gb=round(T * H * W * 3 / 1e9, 3),
                peak_gpu_gb=round(torch.cuda.max_memory_allocated() / 1e9, 3) if cuda else None,
                trajectory_err=round(float(traj), 5), rotation_err_deg=round(float(rot), 4),
                focal_err=round(abs(cams.focal / focal - 1), 4), mode=rep.mode, reproj_px=round(rep.reproj_px, 3),
                points=len(pts), longest_silence_s=round(float(gaps.max()), 2),
                keyframes=None if rep.keyframes is None else len(rep.keyframes),
                timings={k: round(v, 2) for k, v in rep.timings.items()},
                notes=rep.notes)


def synthetic(args):
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, device {args.device or 'auto'}, "
          f"masks: {'flow residuals' if args.no_masks else 'given'}, frames {'held' if args.hold else 'streamed'}")
    print("| case | s | peak RSS GB (before) | GPU GB | trajectory % path | rotation deg | focal % | keyframes "
          "| longest silence s |")
    print("|---|---|---|---|---|---|---|---|---|")
    results = []
    for case in args.synthetic:
        cmd = [sys.executable, __file__, "--one-case", case] + [a for a in sys.argv[1:] if a not in args.synthetic
                                                                and a != "--synthetic"]
        out = subprocess.run(cmd, capture_output=True, text=True)
        if out.returncode != 0:
            print(f"| {case} | failed: {out.stderr.strip().splitlines()[-1:]} |", flush=True)
            continue
        r = json.loads(out.stdout.strip().splitlines()[-1])
        results.append(r)
        gpu = "-" if r["peak_gpu_gb"] is None else f"{r['peak_gpu_gb']:.2f}"
        print(f"| {case} | {r['seconds']:.1f} | {r['peak_rss_gb']:.2f} ({r['rss_before_gb']:.2f}) | {gpu} | "
              f"{100 * r['trajectory_err']:.2f} | {r['rotation_err_deg']:.2f} | {100 * r['focal_err']:.1f} | "
              f"{r['keyframes']} | {r['longest_silence_s']:.1f} |", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", nargs="*", default=[str(Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "davis")])
    ap.add_argument("--max-side", type=int, default=854)
    ap.add_argument("--no-masks", action="store_true", help="find moving content by flow residuals instead")
    ap.add_argument("--focal", type=float, default=None)
    ap.add_argument("--frames", default=None, help="frame range, e.g. 0:50")
    ap.add_argument("--synthetic", nargs="+", default=None, metavar="PATH:FRAMES:WxH",
                    help="synthetic cases instead of DATA, e.g. orbit:900:1920x1080 orbit:300:1080x1920")
    ap.add_argument("--device", default=None, help="cuda or cpu for the tracker's heavy parts (default: cuda if seen)")
    ap.add_argument("--hold", action="store_true", help="synthetic: hold all frames in memory as uint8 first")
    ap.add_argument("--json", default=None, help="synthetic: write the figures here")
    ap.add_argument("--one-case", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one_case:
        print(json.dumps(one_case(args.one_case, args)))
    elif args.synthetic:
        synthetic(args)
    else:
        real_clips(args)


if __name__ == "__main__":
    main()
