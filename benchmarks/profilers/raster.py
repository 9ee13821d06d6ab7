"""Where a frame's time goes: GPU time per kernel (torch profiler, which sees Warp's kernels too) against
the wall time of forward and backward, on the random scene of benchmarks/bench_raster.py.

    python -m benchmarks.profilers.raster --size 854x480 --n 1M --variant static [--gaps] [--host]
    python -m benchmarks.profilers.raster --device cpu --size 64x48 --n 2000 --iters 2   # a dry run

On a CPU there is no kernel profile: only the wall time per forward + backward.
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict

import torch

import tomgs

from ..common import STATIC_T_SCALE, camera, host_profile, kernel_times, parse_count, parse_size, random_scene, \
    sync, temporal_scales


def idle_gaps(phases, iters: int, top: int = 12) -> None:
    """Print where the GPU idles inside each phase: `phases` are (name, callable) run in turn, each between
    device syncs (as bench_raster times them); for every phase, the idle time before its first kernel,
    between its kernels (named by the kernel that waited) and the kernel time, per call."""
    acts = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    with torch.profiler.profile(activities=acts) as prof:
        for _ in range(iters):
            for name, phase in phases:
                torch.cuda.synchronize()
                with torch.profiler.record_function(f"phase:{name}"):
                    phase()
                    torch.cuda.synchronize()
    events = prof.events()
    # a kernel is listed once per CPU op above it too: one entry per (start, end, name)
    kernels = sorted({(e.time_range.start, e.time_range.end, e.name) for e in events
                      if e.device_type == torch.autograd.DeviceType.CUDA and e.time_range.end > e.time_range.start
                      and not e.name.startswith("phase:")}, key=lambda k: k[0])
    spans = [(e.name[6:], e.time_range.start, e.time_range.end) for e in events if e.name.startswith("phase:")
             and e.device_type == torch.autograd.DeviceType.CPU]
    for name in dict.fromkeys(n for n, _, _ in spans):
        lead = busy = 0.0
        waits = defaultdict(float)
        for _, start, end in (s for s in spans if s[0] == name):
            inside = [k for k in kernels if start <= k[0] < end]
            if not inside:
                continue
            lead += inside[0][0] - start
            busy += sum(k[1] - k[0] for k in inside)
            done = inside[0][1]  # the latest kernel end so far
            for k_start, k_end, k_name in inside[1:]:
                if k_start > done:
                    waits[k_name[:60]] += k_start - done
                done = max(done, k_end)
        total_wait = sum(waits.values())
        first = next(s for s in spans if s[0] == name)
        listing = [f"{(k[0] - first[1]) / 1e3:.3f}+{(k[1] - k[0]) / 1e3:.3f} {k[2][:40]}" for k in kernels
                   if first[1] <= k[0] < first[2]]
        print(f"\nphase {name}, first call: kernel start+duration ms after the host start: " + "; ".join(listing))
        print(f"\nphase {name}: per call, host start -> first kernel {lead / iters / 1e3:.3f} ms, kernels "
              f"{busy / iters / 1e3:.3f} ms, idle between kernels {total_wait / iters / 1e3:.3f} ms; idle before:")
        for kernel, us in sorted(waits.items(), key=lambda kv: -kv[1])[:top]:
            print(f"  {us / iters / 1e3:8.3f} ms  {kernel}")


def scene_step(width: int, height: int, n: int, variant: str, device, t: float = 0.5):
    """(step, forward): one forward + backward of tomgs.rasterize at time t on bench_raster's random scene
    of n Gaussians (inputs requiring grad; gradients add up over steps), the loss a fixed random
    weighting of the image plus alpha; step() returns the image. forward() -> (image, loss) alone."""
    P = random_scene(n, 0, device)
    P["t_scales"] = (temporal_scales(P["opacities"], 0.1) if variant == "temporal"
                     else torch.full((n,), STATIC_T_SCALE, device=device))
    viewmat, K = camera(width, height, device)
    for v in P.values():
        v.requires_grad_(True)
    w = torch.rand(height, width, 3, device=device)

    def forward():
        img, alpha, _ = tomgs.rasterize(P["means"], P["quats"], P["scales"], P["opacities"], P["colors"],
                                        P["t_means"], P["t_scales"], viewmat, K, width, height, t)
        return img, (img * w).sum() + alpha.sum()

    def step():
        img, loss = forward()
        loss.backward()
        return img.detach()

    return step, forward


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda", help="cuda (the profile), or cpu for a dry run")
    ap.add_argument("--size", default="854x480")
    ap.add_argument("--n", default="1M")
    ap.add_argument("--variant", default="static", choices=["static", "temporal"])
    ap.add_argument("--iters", type=int, default=20)
    ap.add_argument("--host", action="store_true", help="also print the Python functions that cost host time")
    ap.add_argument("--gaps", action="store_true", help="also print where the GPU idles in the forward and the "
                    "backward, each between syncs as bench_raster times them (CUDA)")
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    width, height = parse_size(args.size)
    n = parse_count(args.n)
    step, forward = scene_step(width, height, n, args.variant, device)
    for _ in range(5):
        step()
    sync(device)
    t0 = time.perf_counter()
    for _ in range(args.iters):
        step()
    sync(device)
    wall = (time.perf_counter() - t0) / args.iters * 1e3
    per_kernel = kernel_times(step, args.iters) if device.type == "cuda" else {}
    gpu = sum(per_kernel.values())
    print(f"\n{args.size} N={n:,} {args.variant} on {device}: wall {wall:.3f} ms per fwd+bwd"
          + (f", GPU kernels {gpu:.3f} ms (gap {wall - gpu:.3f} ms = host overhead and syncs)" if per_kernel else ""))
    for name, ms in sorted(per_kernel.items(), key=lambda kv: -kv[1])[:18]:
        print(f"  {ms:8.3f} ms  {name}")
    if args.gaps and device.type == "cuda":
        held = {}

        def forward_phase():
            held["loss"] = forward()[1]

        idle_gaps([("forward", forward_phase), ("backward", lambda: held.pop("loss").backward())], args.iters)
    if args.host:
        print(f"\nhost time per fwd+bwd, top functions (cumulative over {args.iters} iterations):")
        host_profile(step, args.iters, device)


if __name__ == "__main__":
    main()
