"""Where a training iteration's time goes at millions of Gaussians (GPU): kernels per name from the
torch profiler (Warp's included) against wall time per iteration.

    python benchmarks/profile_fit.py ../shared/data/davis/camel --points-per-frame 50000

Poses are identity (the profile does not depend on them); the model starts with points-per-frame
x frames Gaussians, so the loop runs in the regime a long fit reaches.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from profile_raster import kernel_times  # noqa: E402

from tomgs.cameras import Cameras, intrinsics
from tomgs.io import read_video
from tomgs.train import Trainer, preset


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("clip", type=Path, help="a DAVIS clip folder (images/) or a video")
    ap.add_argument("--points-per-frame", type=int, default=50_000)
    ap.add_argument("--iters", type=int, default=40)
    args = ap.parse_args()
    source = args.clip / "images" if (args.clip / "images").exists() else args.clip
    video = read_video(source)
    T, H, W = video.frames.shape[:3]
    cams = Cameras.create(np.repeat(np.eye(4)[None], T, 0), intrinsics(1.2 * max(W, H), W, H), W, H)
    config = preset("default", init_points_per_frame=args.points_per_frame, densify_start_fraction=2.0, log_interval=10**9,
                    eval_interval_s=1e9)
    trainer = Trainer(video.frames, cams, np.zeros((0, 3)), np.zeros((0, 3), np.float32), config, torch.device("cuda"))
    print(f"{len(trainer.model):,} Gaussians, {T} frames at {W}x{H}")
    for _ in range(10):
        trainer.step()
    torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(args.iters):
        trainer.step()
    torch.cuda.synchronize()
    wall = (time.perf_counter() - start) / args.iters * 1e3
    per_kernel = kernel_times(trainer.step, args.iters)
    gpu = sum(per_kernel.values())
    print(f"wall {wall:.2f} ms per iteration, GPU kernels {gpu:.2f} ms (gap {wall - gpu:.2f} ms)")
    for name, ms in sorted(per_kernel.items(), key=lambda kv: -kv[1])[:22]:
        print(f"  {ms:8.3f} ms  {name}")


if __name__ == "__main__":
    main()
