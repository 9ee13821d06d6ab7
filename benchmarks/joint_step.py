"""The joint refinement's step (a sharded fit's: tomgs.train.multigpu.joint) on one process, timed.

    python -m benchmarks.joint_step --out $OUT/after                                    # the code imported
    PYTHONPATH=/path/to/old/checkout python benchmarks/joint_step.py --out $OUT/before
    python -m benchmarks.joint_step --smoke                                              # CPU, seconds

A part of a union as a rank holds it: the demo scene at --size, its Gaussians copied with jittered
positions and colours up to --gaussians (so that there is something to fit), --shared of them shared
with other ranks (their gradients go through the all_reduce); the rank's --frames frames of the demo
clip. A process group of one rank (NCCL on a GPU, gloo on a CPU): the all_reduce runs with its full
buffer, without another GPU's traffic, which is the same for every version of the step. --warm steps
first (kernels, allocator), then --steps timed: steps/s, and the PSNR of every frame before and after.
Works with the refinement before it became the Trainer's (tomgs.train.multigpu.shards.refine) and after
(joint_trainer + refine_jointly), whichever the imported tomgs has.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

if __package__:
    from .common import demo_frames, demo_model, environment, markdown_table, output_folder, parse_size, write_report
else:  # run as a file (with an older checkout's tomgs): Python puts this folder first on sys.path
    from common import demo_frames, demo_model, environment, markdown_table, output_folder, parse_size, write_report

RATES = dict(means=1.6e-6, quats=1e-3, log_scales=5e-3, opacity_logits=5e-2, sh_dc=2.5e-3, sh_rest=2.5e-3 / 20,
             t_means=1e-3, log_t_scales=2e-2)  # where phase 1's schedule ends, about


def grown(model, count: int, seed: int):
    """`model` with its rows copied (positions jittered by 1% of their spread, colours by 0.3) up to `count`."""
    from tomgs.model import GaussianModel

    g = torch.Generator().manual_seed(seed)
    params = {k: v.detach() for k, v in model.parameters_by_name().items()}
    picks = torch.randint(0, len(model), (count,), generator=g)
    rows = {k: v[picks].clone() for k, v in params.items()}
    spread = params["means"].std(0)
    rows["means"] += 0.01 * spread * torch.randn(rows["means"].shape, generator=g)
    rows["sh_dc"] += 0.3 * torch.randn(rows["sh_dc"].shape, generator=g)
    return GaussianModel(**rows, sh_degree=model.sh_degree)


def part_of(count: int, shared: float):
    """A Halo of `count` rows, every 1/`shared`-th of them shared with other ranks."""
    from tomgs.train.multigpu.shards import Halo

    rows = torch.arange(count)
    every = max(1, round(1 / shared)) if shared > 0 else count + 1
    positions = rows[::every] if shared > 0 else rows[:0]
    return Halo(0, rows, positions, torch.arange(len(positions)), len(positions), torch.zeros(count, dtype=torch.long))


def run(args) -> dict:
    import torch.distributed as dist

    from tomgs.metrics import frame_psnr
    from tomgs.train import TrainConfig

    device = torch.device(args.device)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())  # NCCL's group needs its index
    width, height = parse_size(args.size)
    model, cams = demo_model(args.frames, width, height)
    frames = np.stack(list(demo_frames(args.frames, width, height, device=args.device)))
    model = grown(model, args.gaussians, seed=0).to(device)
    part = part_of(len(model), args.shared)
    config = TrainConfig(log_interval=10**9)
    with tempfile.TemporaryDirectory() as folder:
        if device.type == "cuda":
            torch.cuda.set_device(device)
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo", init_method=f"file://{folder}/store",
                                rank=0, world_size=1)
        try:
            before = float(np.mean(frame_psnr(model, torch.as_tensor(frames, device=device), cams, device)))
            version, refine = refiner(model, part, frames, cams, config, device)
            refine(args.warm)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            began = time.perf_counter()
            steps, fitted = refine(args.steps)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            seconds = time.perf_counter() - began
            after = float(np.mean(frame_psnr(fitted, torch.as_tensor(frames, device=device), cams, device)))
        finally:
            dist.destroy_process_group()
    return dict(version=version, gaussians=len(model), shared=part.total, frames=args.frames, size=args.size,
                steps=steps, seconds=round(seconds, 3), steps_per_s=round(steps / seconds, 2),
                psnr_before=round(before, 3), psnr_after=round(after, 3), device=str(device),
                gpu=torch.cuda.get_device_name(device) if device.type == "cuda" else None)


def refiner(model, part, frames, cams, config, device):
    """(which version, refine(steps) -> (steps taken, the refined model)) for the tomgs imported."""
    import tomgs.train.multigpu.shards as shards

    if hasattr(shards, "refine"):  # before: the refinement's own loop
        held = torch.as_tensor(frames, device=device)

        def refine_old(steps):
            return shards.refine(model, part, held, cams, config, RATES, device, steps=steps).steps, model
        return "refine", refine_old
    from tomgs.train.multigpu.joint import joint_trainer, refine_jointly

    trainer = joint_trainer(model, frames, cams, config, RATES, 1.0, device, seed=0)

    def refine_new(steps):
        return refine_jointly(trainer, part, steps=steps).steps, trainer.model
    return "trainer", refine_new


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--gaussians", type=int, default=2_000_000)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--size", default="854x480")
    ap.add_argument("--shared", type=float, default=0.2, help="the share of the part shared with other ranks")
    ap.add_argument("--warm", type=int, default=30)
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--smoke", action="store_true", help="CPU: 2,000 Gaussians, 4 frames of 48x27, 4 steps")
    ap.add_argument("--out", type=Path, default=None, help="the folder for joint_step.md and joint_step.json")
    args = ap.parse_args(argv)
    if args.smoke:
        args.gaussians, args.frames, args.size, args.warm, args.steps, args.device = 2000, 4, "48x27", 1, 4, "cpu"
    result = run(args)
    keys = ["version", "gaussians", "shared", "frames", "steps", "steps_per_s", "psnr_before", "psnr_after"]
    write_report(output_folder(args.out, args.smoke, "joint_step"), "joint_step", "The joint refinement's step",
                 environment(result["device"], "joint_step", argv), markdown_table(keys, [[result[k] for k in keys]]),
                 result)
    return result


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
