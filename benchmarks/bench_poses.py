"""Camera-pose benchmark: the built-in tracker on real clips (DAVIS layout) or synthetic clips.

Real clips: for each sequence folder (<seq>/images/*.jpg, optional <seq>/masks/*.png) it reports
the median reprojection error of background track observations after the final bundle
adjustment, the estimated focal length, and the wall time, also scaled to seconds per 100 frames.

    python -m benchmarks.bench_poses [DATA ...] [--max-side 854] [--no-masks] [--focal F]
    python -m benchmarks.bench_poses --smoke     # a 6-frame DAVIS-layout clip and a tiny synthetic orbit, CPU

DATA defaults to ../shared/data/davis (every sequence in it); a path may also be one sequence.

Synthetic clips (tomgs.poses.synthetic, known cameras): each case runs in its own process so that
its peak host memory is its own; frames are rendered as the tracker reads them (their rendering
time is subtracted) unless --hold, which renders them all first into one uint8 array as
read_video gives them. Reports time, peak host memory (RSS, and above what the process held
before the tracker started), peak GPU memory, trajectory error (fraction of the path, after a
similarity alignment), rotation error (degrees) and focal error.

    python -m benchmarks.bench_poses --synthetic orbit:300:1920x1080 orbit:900:1920x1080 \\
        orbit:300:1080x1920 --device cuda --out <out>

A case is PATH:FRAMES:WxH with PATH orbit or pan (the camera path). Writes bench_poses.md / .json.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from tomgs import estimate_cameras, read_video

if __package__:
    from .common import ROOT, environment, markdown_table, output_folder, smoke_clip_folder, write_report
else:  # run as a file (the synthetic cases are): Python puts this folder first on sys.path
    from common import ROOT, environment, markdown_table, output_folder, smoke_clip_folder, write_report


def sequences(paths):
    for p in map(Path, paths):
        if (p / "images").is_dir():
            yield p
        else:
            yield from sorted(q for q in p.iterdir() if (q / "images").is_dir())


def real_clips(args) -> tuple[str, list[dict]]:
    """(the markdown table, its rows) of the tracker on every sequence of args.data."""
    rows = []
    for seq in sequences(args.data):
        masks = None if args.no_masks or not (seq / "masks").is_dir() else seq / "masks"
        video = read_video(seq / "images", frames=args.frames, max_side=args.max_side, masks=masks)
        t0 = time.perf_counter()
        cams, pts, _, rep = estimate_cameras(video, focal=args.focal, device=args.device)
        dt = time.perf_counter() - t0
        T, H, W = video.frames.shape[:3]
        rows.append(dict(sequence=seq.name, frames=T, size=f"{W}x{H}", mode=rep.mode, focal_px=round(rep.focal),
                         reproj_px=rep.reproj_px, reproj_all_px=rep.reproj_all_px,
                         rejected=f"{100 * rep.rejected:.1f}%",
                         points=len(pts), seconds=dt, s_per_100_frames=dt / T * 100, notes=rep.notes,
                         timings={k: round(v, 2) for k, v in rep.timings.items()}))
        print(rows[-1], flush=True)
    head = ["sequence", "frames", "size", "mode", "focal_px", "reproj_px", "reproj_all_px", "rejected", "points",
            "seconds", "s_per_100_frames"]
    median = ["**median**", *[None] * 4, float(np.median([r["reproj_px"] for r in rows])),
              float(np.median([r["reproj_all_px"] for r in rows])), None, None, None,
              float(np.median([r["s_per_100_frames"] for r in rows]))]
    text = (f"{os.cpu_count()} CPUs, masks: {'flow residuals' if args.no_masks else 'given'}, max side "
            f"{args.max_side}; reprojection error: median over the background tracks' observations kept by the "
            "final bundle adjustment (all: every observation of those tracks)\n\n"
            + markdown_table(head, [[r[h] for h in head] for r in rows] + [median]))
    return text, rows


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


def synthetic(args) -> tuple[str, list[dict]]:
    """(the markdown table, its rows) of the tracker on each synthetic case, each in its own process."""
    results = []
    for case in args.synthetic:
        cmd = [sys.executable, __file__, "--one-case", case, "--max-side", str(args.max_side)]
        cmd += [flag for flag, on in (("--no-masks", args.no_masks), ("--hold", args.hold)) if on]
        cmd += [item for flag, value in (("--focal", args.focal), ("--device", args.device)) if value is not None
                for item in (flag, str(value))]
        out = subprocess.run(cmd, capture_output=True, text=True)
        if out.returncode != 0:
            raise SystemExit(f"{case} failed:\n{out.stderr[-3000:]}")
        results.append(json.loads(out.stdout.strip().splitlines()[-1]))
        print(results[-1], flush=True)
    head = ["case", "seconds", "peak_rss_gb", "rss_before_gb", "peak_gpu_gb", "trajectory_err", "rotation_err_deg",
            "focal_err", "keyframes", "longest_silence_s"]
    text = (f"device {args.device or 'auto'}, masks: {'flow residuals' if args.no_masks else 'given'}, frames "
            f"{'held' if args.hold else 'streamed'} (their rendering time left out); trajectory error as a share "
            "of the path after a similarity alignment\n\n"
            + markdown_table(head, [[r[h] for h in head] for r in results]))
    return text, results


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", nargs="*", default=[str(ROOT / ".." / "shared" / "data" / "davis")])
    ap.add_argument("--max-side", type=int, default=854)
    ap.add_argument("--no-masks", action="store_true", help="find moving content by flow residuals instead")
    ap.add_argument("--focal", type=float, default=None)
    ap.add_argument("--frames", default=None, help="frame range, e.g. 0:50")
    ap.add_argument("--synthetic", nargs="+", default=None, metavar="PATH:FRAMES:WxH",
                    help="synthetic cases instead of DATA, e.g. orbit:900:1920x1080 orbit:300:1080x1920")
    ap.add_argument("--device", default=None, help="cuda or cpu for the tracker's heavy parts (default: cuda if seen)")
    ap.add_argument("--hold", action="store_true", help="synthetic: hold all frames in memory as uint8 first")
    ap.add_argument("--out", default=None, help="default bench_out/bench_poses")
    ap.add_argument("--smoke", action="store_true",
                    help="a 6-frame DAVIS-layout clip of the demo scene, then a 10-frame synthetic orbit at 64x36 "
                         "(focal given), on the CPU")
    ap.add_argument("--one-case", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one_case:
        print(json.dumps(one_case(args.one_case, args)))
        return []
    out = output_folder(args.out, args.smoke, "bench_poses")
    env = environment(args.device or "cpu", "bench_poses", argv)
    if args.smoke:
        args.device, args.data = "cpu", [str(smoke_clip_folder(out / "clips", "smoke"))]
        text, rows = real_clips(args)
        args.synthetic, args.focal = ["orbit:10:64x36"], 0.9 * 64  # the synthetic clip's focal: no focal search
        synthetic_text, synthetic_rows = synthetic(args)
        text, rows = f"{text}\n\n{synthetic_text}", rows + synthetic_rows
    else:
        text, rows = synthetic(args) if args.synthetic else real_clips(args)
    write_report(out, "bench_poses", "bench_poses: the built-in tracker", env, text, rows)
    return rows


if __name__ == "__main__":
    main()
