"""Training steps per second with the step replayed from a CUDA graph (TrainConfig.captured_step) and
without it (the eager, deferred step), and where a step's time goes: wall time against the GPU's kernel
time (torch profiler, Warp's kernels and the graphs' included).

    python -m benchmarks.train_step .clips/camel .clips/kite-surf --caps 300000 1000000 5000000 --out $OUT
    python -m benchmarks.train_step .clips/camel --caps 1000000 --fit-iters 3000 --out $OUT
    python -m benchmarks.train_step --smoke          # CPU: the demo scene's tiny clip, a few steps each way

Speed (per clip and cap): a Trainer of `cap` Gaussians (identity cameras, cap / frames points per frame,
each alive around its frame, as benchmarks/profilers/fit.py starts), densification off, seeded: --warm
steps, then --steps timed between device syncs, eager and captured in turn (two rounds, the quicker of
each kept), then --profile steps of each under the profiler. A fit (--fit-iters): `Trainer.run` of that
many iterations at the cap with the default schedule (densification from the start's cap / 2), seeded,
each way; its final clip PSNR, wall time, captures and dropped steps. Writes <out>/train_step.{md,json}.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from tomgs.cameras import Cameras, intrinsics
from tomgs.train import Trainer, preset

if __package__:
    from .common import demo_frames, environment, kernel_times, markdown_table, output_folder, write_report
else:  # run as a file: Python puts this folder first on sys.path
    from common import demo_frames, environment, kernel_times, markdown_table, output_folder, write_report

NO_POINTS = np.zeros((0, 3)), np.zeros((0, 3), np.float32)
# a GPU's defaults, also on a CPU (--smoke), where the captured step needs them
GPU_STEP = dict(sparse_adam=True, alive_index=False)


def clip_frames(path: Path) -> np.ndarray:
    """uint8 [T,H,W,3] of a DAVIS clip folder (images/) or a video."""
    from tomgs.io import read_video

    source = path / "images" if (path / "images").exists() else path
    return read_video(source).frames


def identity_cameras(frames: np.ndarray) -> Cameras:
    T, H, W = frames.shape[:3]
    return Cameras.create(np.repeat(np.eye(4)[None], T, 0), intrinsics(1.2 * max(W, H), W, H), W, H)


def trainer_at(frames, cameras, cap: int, captured: bool, device: torch.device, **overrides) -> Trainer:
    """A Trainer of about `cap` Gaussians, densification off (the loop itself is measured)."""
    T = len(frames)
    config = preset("default", init_points_per_frame=max(1, cap // T), max_gaussians=10**9, densify_start_fraction=2.0,
                    log_interval=10**9, eval_interval_s=1e9, captured_step=captured, seed=0, **GPU_STEP, **overrides)
    return Trainer(frames, cameras, *NO_POINTS, config, device)


def timed_steps(trainer: Trainer, steps: int, sync) -> float:
    """Steps per second over `steps` steps, between device syncs."""
    sync()
    began = time.perf_counter()
    for _ in range(steps):
        trainer.step()
    sync()
    return steps / (time.perf_counter() - began)


def kernel_ms(trainer: Trainer, steps: int) -> float:
    """GPU kernel milliseconds per step (torch profiler)."""
    return sum(kernel_times(trainer.step, steps).values())


def speed(frames, cameras, cap: int, args, device: torch.device) -> dict:
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    trainers = {mode: trainer_at(frames, cameras, cap, mode == "captured", device) for mode in ("eager", "captured")}
    for trainer in trainers.values():
        for _ in range(args.warm):
            trainer.step()
    rates = {mode: 0.0 for mode in trainers}
    for _ in range(2):  # interleaved rounds: a clock or a neighbour's load touches both alike
        for mode, trainer in trainers.items():
            rates[mode] = max(rates[mode], timed_steps(trainer, args.steps, sync))
    out = dict(cap=cap, gaussians=len(trainers["eager"].model), steps_per_s={m: round(r, 1) for m, r in rates.items()},
               ratio=round(rates["captured"] / rates["eager"], 3))
    captured = trainers["captured"].captured
    out.update(captures=captured.captures, dropped=captured.dropped, rows=captured.rows, keys=captured.keys)
    if device.type == "cuda" and args.profile:
        out["ms_per_step"] = {mode: dict(wall=round(1e3 / rates[mode], 3), kernels=round(kernel_ms(t, args.profile), 3))
                              for mode, t in trainers.items()}
        out["peak_gpu_mb"] = round(torch.cuda.max_memory_allocated(device) / 2**20)
    return out


def fit(frames, cameras, cap: int, iterations: int, device: torch.device) -> dict:
    out = {}
    for mode in ("eager", "captured"):
        config = preset("default", iterations=iterations, max_gaussians=cap, log_interval=10**9, eval_interval_s=1e9,
                        captured_step=mode == "captured", seed=0, compact_pixels=0.0, **GPU_STEP)
        trainer = Trainer(frames, cameras, *NO_POINTS, config, device)
        result = trainer.run()
        out[mode] = dict(clip_psnr=round(result.clip_psnr, 3), seconds=round(result.seconds, 2),
                         steps_per_s=round(result.iterations / result.seconds, 1), gaussians=len(result.model))
        if trainer.captured is not None:
            out[mode].update(captures=trainer.captured.captures, dropped=trainer.captured.dropped)
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("clips", type=Path, nargs="*", help="DAVIS clip folders (images/) or videos")
    ap.add_argument("--caps", type=int, nargs="+", default=[300_000, 1_000_000, 5_000_000])
    ap.add_argument("--warm", type=int, default=30, help="untimed steps first (captures, kernel loads)")
    ap.add_argument("--steps", type=int, default=300, help="steps timed per round")
    ap.add_argument("--profile", type=int, default=30, help="steps profiled for the kernel time (0: none)")
    ap.add_argument("--fit-iters", type=int, default=0, help="also fit this many iterations each way, at each cap")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--out", type=Path, help="folder for train_step.md and .json (default bench_out/train_step)")
    ap.add_argument("--smoke", action="store_true", help="a tiny CPU run of the whole script (tests)")
    args = ap.parse_args(argv)
    if args.smoke:
        frames = np.stack(list(demo_frames(3, 32, 18)))
        clips = {"smoke": (frames, identity_cameras(frames))}
        args.caps, args.warm, args.steps, args.profile = [600], 3, 3, 0
        args.fit_iters = args.fit_iters or 12
        device = torch.device("cpu")
    else:
        device = torch.device(args.device)
        clips = {}
        for path in args.clips:
            frames = clip_frames(path)
            clips[path.name] = (frames, identity_cameras(frames))
    results = {}
    for name, (frames, cameras) in clips.items():
        for cap in args.caps:
            row = speed(frames, cameras, cap, args, device)
            if args.fit_iters:
                row["fit"] = fit(frames, cameras, cap, args.fit_iters, device)
            results[f"{name}@{cap}"] = row
            print(name, json.dumps(row), flush=True)
    rows = [[key, row["gaussians"], row["steps_per_s"]["eager"], row["steps_per_s"]["captured"], row["ratio"],
             row["captures"], row["dropped"]] for key, row in results.items()]
    body = markdown_table(["clip@cap", "Gaussians", "eager steps/s", "captured steps/s", "ratio", "captures",
                           "dropped"], rows)
    write_report(output_folder(args.out, args.smoke, "train_step"), "train_step",
                 "train_step: steps per second, captured against eager", environment(device, "train_step", argv),
                 body, results)
    return results


if __name__ == "__main__":
    main()
