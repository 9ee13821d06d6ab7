"""Where the tracker's algebra should run for a short clip: `estimate_cameras` on DAVIS clips with its
bundle adjustment and registration on the CPU and on CUDA, in turns (issue 15: the poses are 6-8 s of
a fit's first minute on the H100).

    python benchmarks/pose_device.py ../shared/data/davis --clips camel,cows --turns 2
    python benchmarks/pose_device.py ../shared/data/davis --clips dog --devices cuda --warm-up

Each row is one call; the process's first call pays its start-up (CUDA context, handles, modules).
`--warm-up` runs `tomgs fit`'s start-up thread (tomgs.train.warm.WarmUp) beside the first call, as a
fit does, and reports the seconds the join then waits. `--ulp-noise K` reruns each call K more times
with every `index_add_` of the bundle adjustment perturbed by ~1 ulp (seeded): what summing in
another order (CUDA's atomics) does to the result.

    python benchmarks/pose_device.py ../shared/data/davis --clips dog --devices cpu --turns 1 --ulp-noise 3
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from tomgs.io import read_video
from tomgs.poses import estimate_cameras


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", type=Path, help="a folder of DAVIS clips (<clip>/images, <clip>/masks)")
    ap.add_argument("--clips", default="camel,cows,kite-surf")
    ap.add_argument("--devices", default="cpu,cuda")
    ap.add_argument("--turns", type=int, default=2)
    ap.add_argument("--warm-up", action="store_true", help="run a fit's warm-up thread beside the first call")
    ap.add_argument("--ulp-noise", type=int, default=0, help="also rerun with the BA's sums perturbed by ~1 ulp")
    args = ap.parse_args()
    warming = None
    if args.warm_up:
        from tomgs.train import preset
        from tomgs.train.warm import WarmUp

        warming = WarmUp(preset("default"), torch.device("cuda"))
    rows = []
    for clip in args.clips.split(","):
        video = read_video(args.root / clip / "images", masks=args.root / clip / "masks")
        for turn in range(args.turns):
            for device in args.devices.split(","):
                if device == "cuda":
                    torch.cuda.synchronize()
                began = time.perf_counter()
                _, points, _, report = estimate_cameras(video, method="auto", device=device)
                seconds = time.perf_counter() - began
                rows.append(dict(clip=clip, turn=turn, device=device, seconds=round(seconds, 3),
                                 points=len(points), summary=report.summary()))
                print(json.dumps(rows[-1]), flush=True)
                if warming is not None:
                    print(f"warm-up joined after the first call: waited {warming.join():.2f} s", flush=True)
                    warming = None
    exact_sum = torch.Tensor.index_add_
    for seed in range(1, args.ulp_noise + 1):
        noise = torch.Generator().manual_seed(seed)

        def index_add_one_ulp_off(self, dim, index, source, *a, **k):
            eps = torch.finfo(source.dtype).eps
            jitter = torch.randn(source.shape, generator=noise, dtype=source.dtype).to(source.device)
            return exact_sum(self, dim, index, source * (1 + eps * jitter), *a, **k)

        torch.Tensor.index_add_ = index_add_one_ulp_off
        try:
            for clip in args.clips.split(","):
                video = read_video(args.root / clip / "images", masks=args.root / clip / "masks")
                for device in args.devices.split(","):
                    _, points, _, report = estimate_cameras(video, method="auto", device=device)
                    print(json.dumps(dict(clip=clip, device=device, ulp_noise_seed=seed, points=len(points),
                                          summary=report.summary())), flush=True)
        finally:
            torch.Tensor.index_add_ = exact_sum
    print(f"torch threads {torch.get_num_threads()}")
    for clip in args.clips.split(","):
        best = {d: min(r["seconds"] for r in rows if r["clip"] == clip and r["device"] == d)
                for d in args.devices.split(",")}
        print(clip, "fastest turn, s:", best)


if __name__ == "__main__":
    main()
