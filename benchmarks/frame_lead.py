"""Where a captured frame's time goes as bench_raster times it (`--tomgs-graph`): each phase between
device syncs, split by CUDA events into the GPU's wait for the host (from the phase's start until the
graph's replay reaches the GPU) and the replay with what follows it. bench_raster's f+b counts both.

    python benchmarks/frame_lead.py --size 1920x1080 --n 5M --variant temporal --iters 20 [--host]

Forward: FrameGraph.__call__ (checks, set_frame, the forward replay, FrameCounts). Backward:
loss.backward() (autograd, the loss's gradient ops, the incoming gradients' copies, the backward replay,
AccumulateGrad). `--host` adds the host's time in each part of a frame (perf_counter around FrameGraph's
steps and the functions captured.py calls, over the same frames). CUDA only.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from unittest import mock

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_raster import parse_count, parse_size, t_values  # noqa: E402
from profile_raster import scene_step  # noqa: E402

from tomgs.render import captured  # noqa: E402
from tomgs.render.captured import FrameGraph  # noqa: E402

# what FrameGraph does on the host in a replayed frame: (owner, attribute) timed by --host; those a tomgs
# lacks are left out (before session 30 a call checked its time with _check_scalars: A/B runs time both)
HOST_PARTS = [(FrameGraph, name) for name in ("__call__", "_camera", "_storage_of_cloud", "_release_outputs",
                                              "_release_grads", "_fit_capacity", "_run_forward", "_run_backward")]
HOST_PARTS += [(captured, name) for name in ("_check_scalars", "_check_time", "wrap", "launch", "FrameCounts",
                                             "scope")]
HOST_PARTS += [(captured._Replayed, "apply"), (torch.Tensor, "backward")]


def timed_parts(totals: dict) -> list:
    """mock patches wrapping each of HOST_PARTS that this tomgs has so that it adds its host seconds to
    totals[name]."""
    patches = []
    for owner, name in HOST_PARTS:
        original = getattr(owner, name, None)
        if original is None:
            continue
        label = f"{getattr(owner, '__name__', owner)}.{name}"

        def timer(*args, _original=original, _label=label, **kwargs):
            start = time.perf_counter()
            try:
                return _original(*args, **kwargs)
            finally:
                totals[_label] = totals.get(_label, 0.0) + time.perf_counter() - start
        patched = staticmethod(timer) if isinstance(owner.__dict__.get(name), staticmethod) else timer
        if name == "apply":  # a classmethod of autograd.Function
            patched = classmethod(lambda cls, *args, _original=original, _label=label: timer(*args, _original=_original,
                                                                                         _label=_label))
        patches.append(mock.patch.object(owner, name, patched))
    return patches


def frame_parts(size: str, n: int, variant: str, iters: int, host: bool) -> dict:
    """Medians over `iters` frames at each of bench_raster's times of the variant, in ms: per phase
    (forward, backward) the GPU's wait for the host before the replay (`lead`), the replay and what
    follows it (`replay`), their sum as bench_raster's events see it (`phase`), the host's time
    from the phase's start until the replay was called (`host_to_replay`), until the frame's autograd
    node was entered (`host_to_node`) and, in the forward, until FrameGraph's checks were done."""
    width, height = parse_size(size)
    dev = torch.device("cuda")
    _, scene = scene_step(width, height, n, variant)  # bench_raster's scene, its inputs requiring grad
    P = scene["P"]
    viewmat, K = scene["camera"]
    gen = torch.Generator(device=dev).manual_seed(1)
    w_image = torch.rand(height, width, 3, device=dev, generator=gen)
    w_alpha = torch.rand(height, width, 1, device=dev, generator=gen)
    graph = FrameGraph(**P, width=width, height=height)
    replays = []  # (GPU event, host time) just before each replay
    stamps = {}  # name -> host time at which a frame entered that step (the first time)
    events = []  # made before a frame's timed region (making one costs the host ~60 us on an H100 machine)
    replay = torch.cuda.CUDAGraph.replay

    def marked(self):
        replays.append((event(), time.perf_counter()))
        replay(self)

    def stamped(name: str, step):
        def entry(*args):
            stamps.setdefault(name, time.perf_counter())
            return step(*args)
        return entry

    def event():
        e = events.pop()
        e.record()
        return e

    def frame(t: float) -> dict | None:
        for v in P.values():
            v.grad = None
        replays.clear()
        stamps.clear()
        events[:] = [torch.cuda.Event(enable_timing=True) for _ in range(6)]
        graphs = graph._graphs
        torch.cuda.synchronize()
        w0, e0 = time.perf_counter(), event()
        image, alpha, counts = graph(viewmat, K, t)
        e1 = event()
        torch.cuda.synchronize()
        loss = (image * w_image).sum() + (alpha * w_alpha).sum()
        torch.cuda.synchronize()
        w2, e2 = time.perf_counter(), event()
        loss.backward()
        e3 = event()
        torch.cuda.synchronize()
        if counts.overflowed or graph._graphs is not graphs:  # captured in the call: not a replayed frame
            return None
        (rf, hf), (rb, hb) = replays
        return dict(forward_lead=e0.elapsed_time(rf), forward_replay=rf.elapsed_time(e1),
                    forward_phase=e0.elapsed_time(e1), forward_host_to_replay=(hf - w0) * 1e3,
                    backward_lead=e2.elapsed_time(rb), backward_replay=rb.elapsed_time(e3),
                    backward_phase=e2.elapsed_time(e3), backward_host_to_replay=(hb - w2) * 1e3,
                    forward_host_to_checked=(stamps["checked"] - w0) * 1e3,
                    forward_host_to_node=(stamps["forward"] - w0) * 1e3,
                    backward_host_to_node=(stamps["backward"] - w2) * 1e3)

    samples = []
    node = captured._Replayed
    with mock.patch.object(torch.cuda.CUDAGraph, "replay", marked), \
            mock.patch.object(FrameGraph, "_fit_capacity", stamped("checked", FrameGraph._fit_capacity)), \
            mock.patch.object(node, "forward", staticmethod(stamped("forward", node.forward))), \
            mock.patch.object(node, "backward", staticmethod(stamped("backward", node.backward))):
        for t in t_values(variant, 8):
            for _ in range(3):  # captures and the bound's growth at a new time
                frame(t)
            samples += [s for s in (frame(t) for _ in range(iters)) if s is not None]
        if host:
            totals = {}
            for patch in timed_parts(totals):
                patch.start()
            try:
                kept = sum(frame(0.5) is not None for _ in range(iters))
            finally:
                mock.patch.stopall()
            print(f"\nhost ms per frame in each part (nested parts overlap), {kept} of {iters} frames replayed:")
            for label, seconds in sorted(totals.items(), key=lambda kv: -kv[1]):
                print(f"  {seconds / iters * 1e3:7.3f}  {label}")
    result = {key: statistics.median(s[key] for s in samples) for key in samples[0]}
    result.update(size=size, n=n, variant=variant, frames=len(samples))
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--n", default="5M")
    ap.add_argument("--variant", default="temporal", choices=["static", "temporal"])
    ap.add_argument("--iters", type=int, default=20, help="frames timed at each time")
    ap.add_argument("--host", action="store_true", help="also print the host's time in each part of a frame")
    ap.add_argument("--json", type=Path, help="write the medians here")
    args = ap.parse_args()
    result = frame_parts(args.size, parse_count(args.n), args.variant, args.iters, args.host)
    print(f"\n{args.size} {args.n} {args.variant}, medians over {result['frames']} frames (ms):")
    for phase in ("forward", "backward"):
        print(f"  {phase:8s} phase {result[phase + '_phase']:.3f} = GPU waits for the host "
              f"{result[phase + '_lead']:.3f} + replay and after {result[phase + '_replay']:.3f}; "
              f"host to the replay {result[phase + '_host_to_replay']:.3f}")
    print(f"  host: the call's checks done at {result['forward_host_to_checked']:.3f}, its autograd node's forward "
          f"entered at {result['forward_host_to_node']:.3f}; autograd's engine entered the backward node "
          f"{result['backward_host_to_node']:.3f} ms after backward() was called")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
