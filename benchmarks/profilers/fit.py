"""Where a training step's time goes at millions of Gaussians (GPU): kernels per name from the torch
profiler (Warp's included) against wall time per step.

    python -m benchmarks.profilers.fit ../shared/data/davis/camel --points-per-frame 50000
    python -m benchmarks.profilers.fit ../shared/data/davis/camel --scene bench_out/davis/camel.ply --fps --host
    python -m benchmarks.profilers.fit <clip> --device cpu --points-per-frame 200 --iters 2   # a dry run

Without --scene, poses are identity and the model starts with points-per-frame x frames Gaussians (each
alive around its frame), the regime a long fit reaches in size. With --scene, a fitted scene and its
cameras train on: the regime at the end of a real fit, where the share of Gaussians alive at a frame's
time (printed) decides how much of the per-Gaussian work is wasted. Densification is off in both: the
loop itself is measured. --host adds cProfile's top functions (where the host, not the GPU, sets the
pace: early in a fit, light clips).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

import tomgs
from tomgs.cameras import intrinsics
from tomgs.train import Trainer, preset

from ..common import host_profile, kernel_times, scene_fps, sync


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("clip", type=Path, help="a DAVIS clip folder (images/) or a video")
    ap.add_argument("--points-per-frame", type=int, default=50_000)
    ap.add_argument("--scene", type=Path, help="a scene fitted to this clip: profile training on from it")
    ap.add_argument("--iters", type=int, default=40)
    ap.add_argument("--device", default="cuda", help="cuda (the profile), or cpu for a dry run")
    ap.add_argument("--host", action="store_true", help="also print the Python functions that cost host time")
    ap.add_argument("--alive-index", choices=["auto", "on", "off"], default="auto",
                    help="train from the alive index's rows (auto: where it pays, tomgs.render.alive.pays_on); for A/B")
    ap.add_argument("--fps", action="store_true",
                    help="with --scene: also the scene's render speed (benchmarks.common.scene_fps)")
    args = ap.parse_args(argv)
    source = args.clip / "images" if (args.clip / "images").exists() else args.clip
    video = tomgs.read_video(source)
    T, H, W = video.frames.shape[:3]
    device = torch.device(args.device)
    index = {"auto": None, "on": True, "off": False}[args.alive_index]
    config = preset("default", init_points_per_frame=args.points_per_frame, max_gaussians=10**9,
                    densify_start_fraction=2.0, log_interval=10**9, eval_interval_s=1e9, alive_index=index)
    no_points = np.zeros((0, 3)), np.zeros((0, 3), np.float32)
    if args.scene is not None:
        scene = tomgs.load_scene(args.scene, device=device)
        extent = float(scene.info.get("extent", 1.0))
        trainer = Trainer(video.frames, scene.cameras, *no_points, config, device, initial=(scene.model, extent))
    else:
        cams = tomgs.Cameras.create(np.repeat(np.eye(4)[None], T, 0), intrinsics(1.2 * max(W, H), W, H), W, H)
        trainer = Trainer(video.frames, cams, *no_points, config, device)
    alive = []
    with torch.no_grad():
        for k in range(T):
            meta = trainer.render(k)[2]
            alive.append((int(meta["n_alive"]), int(meta["n_visible"])))
    n = len(trainer.model)
    alive_share, visible_share = (np.mean([a[i] for a in alive]) / n for i in (0, 1))
    print(f"{n:,} Gaussians, {T} frames at {W}x{H}; per frame {alive_share:.1%} alive, {visible_share:.1%} "
          f"alive and in view (mean over frames)")
    for _ in range(10):
        trainer.step()
    sync(device)
    start = time.perf_counter()
    for _ in range(args.iters):
        trainer.step()
    sync(device)
    wall = (time.perf_counter() - start) / args.iters * 1e3
    if args.fps and args.scene is not None:
        fps = scene_fps(args.scene, device)
        print(f"render: {fps['fps']:.1f} fps kept, {fps['fps_call']:.1f} in whole calls, over {T} frames")
    if device.type != "cuda":
        print(f"wall {wall:.2f} ms per iteration (no kernel profile on {device})")
    else:
        per_kernel = kernel_times(trainer.step, args.iters)
        gpu = sum(per_kernel.values())
        print(f"wall {wall:.2f} ms per iteration, GPU kernels {gpu:.2f} ms (gap {wall - gpu:.2f} ms)")
        for name, ms in sorted(per_kernel.items(), key=lambda kv: -kv[1])[:25]:
            print(f"  {ms:8.3f} ms  {name}")
    if args.host:
        print(f"\nhost time per iteration, top functions (cumulative over {args.iters} iterations):")
        host_profile(trainer.step, args.iters, device)


if __name__ == "__main__":
    main()
