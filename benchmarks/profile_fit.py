"""Where a training iteration's time goes at millions of Gaussians (GPU): kernels per name from the
torch profiler (Warp's included) against wall time per iteration.

    python benchmarks/profile_fit.py ../shared/data/davis/camel --points-per-frame 50000
    python benchmarks/profile_fit.py ../shared/data/davis/camel --scene bench_out/davis/camel.ply

Without --scene, poses are identity and the model starts with points-per-frame x frames Gaussians
(each alive around its frame), the regime a long fit reaches in size. With --scene, a fitted scene
and its cameras train on: the regime at the end of a real fit, where the share of Gaussians alive
at a frame's time (printed) decides how much of the per-Gaussian work is wasted.
Densification is off in both: the loop itself is measured. --host-parts splits a step's host time by
part (where the host, not the GPU, sets the pace: early in a fit, light clips).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from davis import render_fps  # noqa: E402
from profile_raster import TILE_ORDERS, add_tiles_option, host_profile, kernel_times  # noqa: E402

import tomgs
from tomgs.cameras import Cameras, intrinsics
from tomgs.io import read_video
from tomgs.render.frame import _Rasterize
from tomgs.train import Trainer, preset


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("clip", type=Path, help="a DAVIS clip folder (images/) or a video")
    ap.add_argument("--points-per-frame", type=int, default=50_000)
    ap.add_argument("--scene", type=Path, help="a scene fitted to this clip: profile training on from it")
    ap.add_argument("--iters", type=int, default=40)
    ap.add_argument("--device", default="cuda", help="cuda (the profile), or cpu for a dry run of the script")
    ap.add_argument("--host", action="store_true", help="also print the Python functions that cost host time")
    ap.add_argument("--alive-index", choices=["auto", "on", "off"], default="auto",
                    help="train from the alive index's rows (auto: where it pays, tomgs.render.alive.pays_on); for A/B")
    ap.add_argument("--host-parts", action="store_true",
                    help="also print a step's host time by part (the frame's issue, the backward, Adam, ...)")
    ap.add_argument("--raster", choices=["auto", "batched", "per-pixel"], default="auto",
                    help="the compositing kernel pair (auto: batched on CUDA); for A/B timings in one command")
    ap.add_argument("--fps", action="store_true",
                    help="with --scene: also time render_sequence over every frame (the quickest of 5 passes)")
    add_tiles_option(ap)
    args = ap.parse_args()
    _Rasterize.batched = {"auto": None, "batched": True, "per-pixel": False}[args.raster]
    _Rasterize.ordered_tiles = TILE_ORDERS[args.tiles]
    source = args.clip / "images" if (args.clip / "images").exists() else args.clip
    video = read_video(source)
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
        cams = Cameras.create(np.repeat(np.eye(4)[None], T, 0), intrinsics(1.2 * max(W, H), W, H), W, H)
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
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    for _ in range(10):
        trainer.step()
    sync()
    start = time.perf_counter()
    for _ in range(args.iters):
        trainer.step()
    sync()
    wall = (time.perf_counter() - start) / args.iters * 1e3
    if args.fps and args.scene is not None:
        fps = render_fps(args.scene, device)
        print(f"render: {fps['fps']:.1f} fps kept, {fps['fps_call']:.1f} in whole calls, over {T} frames "
              f"({args.raster} kernels)")
    if device.type != "cuda":
        print(f"wall {wall:.2f} ms per iteration (no kernel profile on {device})")
        return
    per_kernel = kernel_times(trainer.step, args.iters)
    gpu = sum(per_kernel.values())
    print(f"wall {wall:.2f} ms per iteration, GPU kernels {gpu:.2f} ms (gap {wall - gpu:.2f} ms)")
    for name, ms in sorted(per_kernel.items(), key=lambda kv: -kv[1])[:25]:
        print(f"  {ms:8.3f} ms  {name}")
    if args.host_parts:
        host, parts = host_parts(trainer, args.iters)
        print(f"\nhost time per iteration {host:.2f} ms, by part:")
        for name, ms in parts.items():
            print(f"  {ms:8.3f} ms  {name}")
    if args.host:
        print(f"\nhost time per iteration, top functions (cumulative over {args.iters} iterations):")
        host_profile(trainer.step, args.iters)


def host_parts(trainer, iters: int) -> tuple[float, dict]:
    """(host ms per step, {part: host ms per step}) over `iters` steps of `trainer` (CUDA): the wall time
    of each part of `Trainer.step`, taken around the methods it calls. A pipelined step has no sync
    inside, so while the host is the slower side (the queue never fills) these are host times; where
    the GPU is slower they include waits. No profiler: no inflation of Python's calls."""
    spent: dict[str, float] = {}
    saved = []

    def timed(owner, name: str, label: str) -> None:
        original = getattr(owner, name)

        def wrapper(*args, **kwargs):
            began = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                spent[label] = spent.get(label, 0.0) + time.perf_counter() - began

        saved.append((owner, name, original, name in vars(owner)))
        setattr(owner, name, wrapper)

    for owner, name, label in (
            (trainer, "render", "the frame's forward (issue)"),
            (torch.Tensor, "backward", "the backward (autograd and its launches)"),
            (trainer.optimizer, "step", "Adam"),
            (trainer, "_loss_and_psnr", "the loss's forward, with the sampler's PSNR"),
            (trainer, "loss", "the loss's forward"),  # a step that calls them apart (older trees)
            (trainer, "_psnr", "the sampler's PSNR"),
            (trainer.sampler, "sample", "drawing the frame"),
            (trainer, "target", "the target frame"),
            (trainer.densifier, "step_post_backward", "the densifier"),
            (trainer, "flush_measurements", "handing PSNRs to the sampler")):
        if hasattr(owner, name):
            timed(owner, name, label)
    try:
        torch.cuda.synchronize()
        began = time.perf_counter()
        for _ in range(iters):
            trainer.step()
        host = (time.perf_counter() - began) / iters * 1e3
        torch.cuda.synchronize()
    finally:
        for owner, name, original, own in reversed(saved):
            if own:
                setattr(owner, name, original)
            else:
                delattr(owner, name)
    parts = {label: seconds / iters * 1e3 for label, seconds in sorted(spent.items(), key=lambda kv: -kv[1])}
    parts["the rest of Trainer.step"] = host - sum(parts.values())
    return host, parts


if __name__ == "__main__":
    main()
