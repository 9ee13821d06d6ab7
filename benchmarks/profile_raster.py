"""Where a frame's time goes: GPU time per kernel (torch profiler, which sees Warp's kernels too)
against the wall time of forward and backward, on the random scene of bench_raster.py.

    python benchmarks/profile_raster.py --size 854x480 --n 1M --variant static
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_raster import camera, make_scene, parse_count, parse_size, temporal_scales  # noqa: E402

import tomgs  # noqa: E402
from tomgs.render.frame import _Rasterize  # noqa: E402


# a kernel's name as reported: long enough to tell cub's sort kernels apart (their first 80 characters
# are the same namespace)
KEY_CHARS = 140


def kernel_times(step, iters: int) -> dict[str, float]:
    """GPU milliseconds per call of `step`, by kernel name (torch profiler; Warp's kernels included)."""
    acts = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    with torch.profiler.profile(activities=acts) as prof:
        for _ in range(iters):
            step()
        torch.cuda.synchronize()
    per_kernel = defaultdict(float)
    events = prof.key_averages()
    # a record_function range (Optimizer.step#SeenAdam.step, phase:...) also shows as a GPU range
    # spanning its kernels: counted once, by its kernels
    host_ranges = {evt.key for evt in events if evt.device_type == torch.autograd.DeviceType.CPU}
    for evt in events:
        if evt.device_type == torch.autograd.DeviceType.CUDA and evt.device_time_total > 0 \
                and evt.key not in host_ranges:
            per_kernel[evt.key[:KEY_CHARS]] += evt.device_time_total / iters / 1e3
    return dict(per_kernel)


def idle_gaps(phases, iters: int, top: int = 12) -> None:
    """Print where the GPU idles inside each phase: `phases` are callables run in turn, each between
    device syncs (as bench_raster times them); for every phase, the idle time before its first
    kernel, between its kernels (named by the kernel that waited) and the kernel time, per call."""
    acts = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    spans = []  # (phase, host start us, host end us)
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


def host_profile(step, iters: int, top: int = 25) -> None:
    """Print the Python functions that cost host time over `iters` calls of `step` (cProfile; a wait
    for the device shows up as the time of the call that waited, e.g. `tolist`)."""
    import cProfile
    import pstats

    profiler = cProfile.Profile()
    profiler.enable()
    for _ in range(iters):
        step()
    torch.cuda.synchronize()
    profiler.disable()
    pstats.Stats(profiler).sort_stats("tottime").print_stats(top)


# --tiles: which tile each raster block takes (tomgs.render.frame._Rasterize.ordered_tiles), for A/B timings
TILE_ORDERS = {"auto": None, "longest-first": True, "in-order": False}


def add_tiles_option(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--tiles", choices=list(TILE_ORDERS), default="auto",
                    help="which tile each raster block takes (auto: longest list first on CUDA); for A/B timings")


def scene_step(width: int, height: int, n: int, variant: str, t: float = 0.5):
    """(step, scene): one fwd+bwd of tomgs.rasterize at time t on bench_raster's random scene of n
    Gaussians (CUDA), its inputs requiring grad (gradients add up over steps), the loss a fixed random
    weighting of the image plus alpha; step() returns the image. scene: the inputs `P`, `forward`,
    () -> (image, loss), the step's forward alone, and `camera`, (viewmat, K)."""
    dev = torch.device("cuda")
    P = make_scene(n, 0, dev)
    P["t_scales"] = (temporal_scales(P["opacities"], 0.1) if variant == "temporal"
                     else torch.full((n,), 1e3, device=dev))
    viewmat, K = camera(width, height, dev)
    for v in P.values():
        v.requires_grad_(True)
    w = torch.rand(height, width, 3, device=dev)

    def forward():
        img, alpha, _ = tomgs.rasterize(P["means"], P["quats"], P["scales"], P["opacities"], P["colors"],
                                        P["t_means"], P["t_scales"], viewmat, K, width, height, t)
        return img, (img * w).sum() + alpha.sum()

    def step():
        img, loss = forward()
        loss.backward()
        return img.detach()

    return step, dict(P=P, forward=forward, camera=(viewmat, K))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--size", default="854x480")
    ap.add_argument("--n", default="1M")
    ap.add_argument("--variant", default="static", choices=["static", "temporal"])
    ap.add_argument("--iters", type=int, default=20)
    ap.add_argument("--host", action="store_true", help="also print the Python functions that cost host time")
    ap.add_argument("--gaps", action="store_true", help="also print where the GPU idles in the forward and the "
                    "backward, each between syncs as bench_raster times them")
    add_tiles_option(ap)
    args = ap.parse_args()
    _Rasterize.ordered_tiles = TILE_ORDERS[args.tiles]
    width, height = parse_size(args.size)
    n = parse_count(args.n)
    step, scene = scene_step(width, height, n, args.variant)

    for _ in range(5):
        step()
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(args.iters):
        step()
    torch.cuda.synchronize()
    wall = (time.perf_counter() - t0) / args.iters * 1e3

    per_kernel = kernel_times(step, args.iters)
    gpu = sum(per_kernel.values())
    print(f"\n{args.size} N={n:,} {args.variant}: wall {wall:.3f} ms per fwd+bwd, GPU kernels {gpu:.3f} ms "
          f"(gap {wall - gpu:.3f} ms = host overhead and syncs)")
    for name, ms in sorted(per_kernel.items(), key=lambda kv: -kv[1])[:18]:
        print(f"  {ms:8.3f} ms  {name}")
    if args.gaps:
        held = {}

        def forward():
            held["loss"] = scene["forward"]()[1]

        idle_gaps([("forward", forward), ("backward", lambda: held.pop("loss").backward())], args.iters)
    if args.host:
        print(f"\nhost time per fwd+bwd, top functions (cumulative over {args.iters} iterations):")
        host_profile(step, args.iters)


if __name__ == "__main__":
    main()
