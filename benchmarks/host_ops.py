"""Host work per `tomgs.rasterize` forward + backward: torch ops, Warp launches and Python time.

Runs the scene of bench_raster.py (training path: every Gaussian input requires grad, the camera
does not) at a tiny size, where the kernels cost next to nothing, so what is measured is what the
host spends issuing a frame. Per iteration it reports

- torch ops: top-level aten calls (torch.profiler, CPU activity), split into forward (rasterize)
  and backward (loss.backward(), the loss's backward and AccumulateGrad included), with their names;
- Warp launches: tomgs.runtime.launch calls, direct wp.launch calls, radix sorts and full Warp
  arrays built (wp.from_torch, ~20 us each on a GPU machine's CPU);
- host wall time: forward and backward, median of --iters (no profiler attached);
- what the forward issues AFTER its one host sync (the intersection count, read by
  tomgs.render.frame._read_flags): torch ops, launches and host wall time from the sync to the forward's
  end. On a GPU all of it is on the critical path: the device idles until it is issued;
- Python time per stage: cProfile's cumulative time of tomgs' stage functions.

    python benchmarks/host_ops.py                      # CPU, 32x32, 64 Gaussians, temporal
    python benchmarks/host_ops.py --device cuda --size 854x480 --n 1M --variant temporal

On a GPU the wall times include no device waits but the one host sync of the forward (the
intersection count), and a real scene's kernels may be longer than the host's issue time.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import statistics
import sys
import time
from collections import Counter
from pathlib import Path

import torch
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_raster import camera, make_scene, parse_count, parse_size, temporal_scales  # noqa: E402

import tomgs  # noqa: E402
from tomgs import runtime  # noqa: E402
from tomgs.render import frame as render  # noqa: E402

# the functions whose cumulative Python time makes a stage (file suffix, function name)
STAGES = [
    ("render/frame.py", "rasterize"), ("render/frame.py", "_check_scalars"), ("inputs.py", "prepare_inputs"),
    ("render/frame.py", "_project_frame"), ("render/frame.py", "forward"), ("render/frame.py", "_write_keys"), ("render/frame.py", "_bin"),
    ("render/frame.py", "backward"), ("runtime.py", "__call__"), ("runtime.py", "wrap"), ("runtime.py", "indexable"),
    ("runtime.py", "scope"), ("runtime.py", "sort_pairs"), ("render/frame.py", "_kernels"),
]


# the profiler range that holds what the forward issues after its host sync
AFTER_SYNC = "host_ops: after the sync"
PHASES = ("before the sync", "after the sync", "backward")


class Phases:
    """Counts Warp launches per phase of a frame (PHASES) by patching tomgs.runtime.Launches, wp.launch,
    the radix sort (tomgs.render.sort_pairs) and wp.from_torch, and marks the forward's host sync by patching
    tomgs.render.frame._read_flags: from its return to `forward_done` the phase is "after the sync", and
    with `ranges` set that stretch is a profiler range (AFTER_SYNC) that `top_level_ops` splits on."""

    def __init__(self):
        self.counts = {phase: Counter() for phase in PHASES}
        self.seconds = 0.0  # time inside launches (on a CPU this includes running the kernel)
        self.phase = PHASES[0]
        self.ranges = False
        self.synced_at = None  # perf_counter when the last forward's sync returned
        self._range = None
        recorded, direct, sort = runtime.Launches.__call__, wp.launch, render.sort_pairs
        from_torch, read_flags = wp.from_torch, render._read_flags

        def counted(name, fn):
            def call(*args, **kwargs):
                self.counts[self.phase][name] += 1
                t0 = time.perf_counter()
                try:
                    return fn(*args, **kwargs)
                finally:
                    self.seconds += time.perf_counter() - t0
            return call

        def synced(*args, **kwargs):
            stats = read_flags(*args, **kwargs)
            self.synced_at = time.perf_counter()
            self.phase = PHASES[1]
            if self.ranges:
                self._range = torch.profiler.record_function(AFTER_SYNC).__enter__()
            return stats

        runtime.Launches.__call__ = counted("recorded launch", recorded)
        wp.launch = counted("wp.launch", direct)
        render.sort_pairs = counted("radix sort", sort)
        wp.from_torch = counted("wp.from_torch", from_torch)
        render._read_flags = synced

    def forward_starts(self) -> None:
        self.phase = PHASES[0]

    def forward_done(self) -> None:
        if self._range is not None:
            self._range.__exit__(None, None, None)
            self._range = None
        self.phase = PHASES[2]

    def clear(self) -> None:
        for counts in self.counts.values():
            counts.clear()
        self.seconds = 0.0


def top_level_ops(prof) -> dict[str, Counter]:
    """Counters of aten op names called directly (not from inside another aten op), by phase (PHASES):
    backward: under an autograd engine node; after the sync: inside the AFTER_SYNC range; the rest is
    the forward before its sync."""
    ops = {phase: Counter() for phase in PHASES}
    for evt in prof.events():
        if not evt.name.startswith("aten::"):
            continue
        parent, phase, nested = evt.cpu_parent, PHASES[0], False
        while parent is not None:
            if parent.name.startswith("aten::"):
                nested = True
                break
            if parent.name.startswith("autograd::engine::evaluate_function"):
                phase = PHASES[2]
            elif parent.name == AFTER_SYNC:
                phase = PHASES[1]
            parent = parent.cpu_parent
        if not nested:
            ops[phase][evt.name] += 1
    return ops


def stage_times(profiler: cProfile.Profile, iters: int) -> dict[str, float]:
    """Cumulative microseconds per iteration of the STAGES functions (cProfile adds its own overhead)."""
    stats = pstats.Stats(profiler).stats
    out = {}
    for (filename, _, name), (_, _, _, cumulative, _) in stats.items():
        for suffix, wanted in STAGES:
            if name == wanted and filename.endswith(suffix) and "tomgs" in filename:
                key = f"{suffix[:-3]}.{name}"
                out[key] = out.get(key, 0.0) + cumulative / iters * 1e6
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", default="32x32")
    ap.add_argument("--n", default="64")
    ap.add_argument("--variant", default="temporal", choices=["static", "temporal"])
    ap.add_argument("--iters", type=int, default=200)
    ap.add_argument("--json", default=None, help="also write the figures to this file")
    args = ap.parse_args(argv)
    width, height = parse_size(args.size)
    n = parse_count(args.n)
    dev = torch.device(args.device)
    cuda = dev.type == "cuda"
    sync = torch.cuda.synchronize if cuda else (lambda: None)

    P = make_scene(n, 0, dev)
    P["t_scales"] = (temporal_scales(P["opacities"], 0.1) if args.variant == "temporal"
                     else torch.full((n,), 1e3, device=dev))
    for v in P.values():
        v.requires_grad_(True)
    viewmat, K = camera(width, height, dev)
    w_img = torch.rand(height, width, 3, device=dev)
    w_alpha = torch.rand(height, width, 1, device=dev)

    phases = Phases()

    def forward(t=0.5):
        phases.forward_starts()
        out = tomgs.rasterize(P["means"], P["quats"], P["scales"], P["opacities"], P["colors"], P["t_means"],
                              P["t_scales"], viewmat, K, width, height, t)
        phases.forward_done()
        return out

    def backward(out):
        img, alpha, _ = out
        ((img * w_img).sum() + (alpha * w_alpha).sum()).backward()

    def step():
        for v in P.values():
            v.grad = None
        backward(forward())

    for _ in range(10):
        step()
    sync()

    # host wall time, no profiler attached
    fwd_us, bwd_us, after_us = [], [], []
    for _ in range(args.iters):
        for v in P.values():
            v.grad = None
        sync()
        t0 = time.perf_counter()
        out = forward()
        t1 = time.perf_counter()
        backward(out)
        t2 = time.perf_counter()
        sync()
        fwd_us.append((t1 - t0) * 1e6)
        bwd_us.append((t2 - t1) * 1e6)
        after_us.append((t1 - phases.synced_at) * 1e6)

    phases.clear()
    phases.ranges = True
    ops_iters = 5
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        for _ in range(ops_iters):
            step()
        sync()
    phases.ranges = False
    ops = top_level_ops(prof)
    # the loss (2 x mul, 2 x sum, add, the backward's seed) is the benchmark's, not the rasterizer's
    loss_fwd = Counter({"aten::mul": 2, "aten::sum": 2, "aten::add": 1, "aten::ones_like": 1})
    ops[PHASES[0]] -= Counter({k: v * ops_iters for k, v in loss_fwd.items()})
    ops = {phase: Counter({k: v / ops_iters for k, v in counts.items()}) for phase, counts in ops.items()}
    launches = {phase: {k: v / ops_iters for k, v in counts.items()} for phase, counts in phases.counts.items()}

    phases.clear()
    profiler = cProfile.Profile()
    profiler.enable()
    for _ in range(args.iters):
        step()
    sync()
    profiler.disable()
    stages = stage_times(profiler, args.iters)

    fwd_ops = ops[PHASES[0]] + ops[PHASES[1]]
    result = dict(
        device=str(dev), size=args.size, n=n, variant=args.variant, iters=args.iters,
        fwd_us=statistics.median(fwd_us), bwd_us=statistics.median(bwd_us), after_sync_us=statistics.median(after_us),
        fwd_ops=sum(fwd_ops.values()), after_sync_ops=sum(ops[PHASES[1]].values()),
        bwd_ops=sum(ops[PHASES[2]].values()),
        launches=launches, launch_us=phases.seconds / args.iters * 1e6, stages_us=stages,
        op_names={phase: dict(counts.most_common()) for phase, counts in ops.items()},
    )
    print(f"{dev} {args.size} N={n:,} {args.variant}, median of {args.iters}:")
    print(f"  host wall: forward {result['fwd_us']:.0f} us (after its sync {result['after_sync_us']:.0f} us), "
          f"backward (with the loss's) {result['bwd_us']:.0f} us, total {result['fwd_us'] + result['bwd_us']:.0f} us")
    print(f"  torch ops per frame: forward {result['fwd_ops']:g} (after its sync {result['after_sync_ops']:g}), "
          f"backward {result['bwd_ops']:g} (the loss's 5 ops and its backward's seed excluded; its backward's ops "
          f"included)")
    print("  Warp launches (and full Warp arrays built) per frame:")
    for phase in PHASES:
        print(f"    {phase}: {sum(v for k, v in launches[phase].items() if k != 'wp.from_torch'):g} "
              f"{launches[phase]}")
    for phase in PHASES:
        print(f"  ops {phase}: {', '.join(f'{k[6:]} {v:g}' for k, v in ops[phase].most_common())}")
    print(f"  Python time per stage (cProfile, cumulative us per frame, inflated by the profiler; launches "
          f"{result['launch_us']:.0f} us incl. CPU kernels):")
    for name, us in stages.items():
        print(f"    {us:8.1f}  {name}")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
