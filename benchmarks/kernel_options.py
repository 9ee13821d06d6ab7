"""Which Warp launch option pays for a frame's kernels, measured before it goes into a decorator.

Each variant rebuilds named kernels of the frame (projection, binning, raster) with Warp's per-kernel
options (`cuda_max_registers`, `launch_bounds`, `grid_stride`) in a module of their own, puts them where
tomgs.render launches them, and times one fwd+bwd of bench_raster's random scene by kernel (torch
profiler). Variants run in turns, `--rounds` times, so that a drift of the GPU's clocks shows as a
spread between rounds rather than as a difference between variants.

    python benchmarks/kernel_options.py --size 1920x1080 --n 5M --variant temporal \\
        base project_forward:cuda_max_registers=40 "project_forward:launch_bounds=256,4+write_tile_keys:grid_stride=0"

A variant is `base` (the kernels as they are) or `+`-joined `kernel:option=value` settings; a rebuilt
kernel keeps its decorator's options but those its variant names (`launch_bounds` and
`cuda_max_registers` replace each other: Warp takes one of the two). Register
counts: `cuobjdump --dump-resource-usage` on the cubins of WARP_CACHE_PATH after the run.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import sys
from pathlib import Path

import torch
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_raster import parse_count, parse_size  # noqa: E402
from profile_raster import kernel_times, scene_step  # noqa: E402

from tomgs.kernels import binning, project, raster, raster_batched  # noqa: E402

MODULES = (project, binning, raster, raster_batched)
OPTIONS = ("cuda_max_registers", "launch_bounds", "grid_stride")
EXCLUSIVE = {"cuda_max_registers": "launch_bounds", "launch_bounds": "cuda_max_registers"}
WARP_SUFFIX = re.compile(r"_[0-9a-f]{8}_cuda_kernel_forward")  # a module's hash: differs for a rebuilt kernel


def frame_kernels() -> dict[str, object]:
    """{kernel name: the module that holds it} for every Warp kernel a frame may launch."""
    return {name: module for module in MODULES for name, value in vars(module).items() if isinstance(value, wp.Kernel)}


def parse_option(kernel: str, text: str) -> tuple[str, object]:
    name, _, value = text.partition("=")
    if name not in OPTIONS or not value:
        raise SystemExit(f"{kernel}: expected one of {', '.join(OPTIONS)} as option=value, not {text!r}")
    if name == "grid_stride":
        return name, value not in ("0", "false", "False")
    numbers = tuple(int(v) for v in value.split(","))
    return name, numbers if name == "launch_bounds" and len(numbers) > 1 else numbers[0]


def parse_variant(spec: str, known: dict) -> dict[str, dict]:
    """{kernel name: {option: value}} of a variant spec ({} for `base`)."""
    if spec == "base":
        return {}
    settings: dict[str, dict] = {}
    for part in spec.split("+"):
        kernel, _, option = part.partition(":")
        if kernel not in known:
            raise SystemExit(f"unknown kernel {kernel!r}; a frame's kernels: {', '.join(sorted(known))}")
        settings.setdefault(kernel, {}).update([parse_option(kernel, option)])
    return settings


class Patched:
    """The variant's kernels in place of the module's own while inside the `with`."""

    def __init__(self, settings: dict[str, dict], known: dict):
        self.swaps = []
        for kernel, options in settings.items():
            module = known[kernel]
            original = getattr(module, kernel)
            dropped = {EXCLUSIVE.get(name) for name in options}
            kept = {name: value for name, value in original.options.items() if name in OPTIONS and name not in dropped}
            rebuilt = wp.kernel(original.func, module="unique", enable_backward=False, **{**kept, **options})
            self.swaps.append((module, kernel, original, rebuilt))

    def apply(self) -> None:
        for module, name, _, rebuilt in self.swaps:
            setattr(module, name, rebuilt)

    def restore(self) -> None:
        for module, name, original, _ in self.swaps:
            setattr(module, name, original)

    def __enter__(self):
        self.apply()

    def __exit__(self, *exc):
        self.restore()


def image_and_grads(step, params: dict) -> dict[str, torch.Tensor]:
    """One step's image and the gradients it alone gives each input."""
    for p in params.values():
        p.grad = None
    image = step()
    return dict(image=image, **{name: p.grad.clone() for name, p in params.items()})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("variants", nargs="+", help="`base` or kernel:option=value[+kernel:option=value...]")
    ap.add_argument("--size", default="854x480")
    ap.add_argument("--n", default="1M")
    ap.add_argument("--variant", default="static", choices=["static", "temporal"])
    ap.add_argument("--iters", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", default=None, help="JSON of every round's kernel times (default: print only)")
    args = ap.parse_args()
    known = frame_kernels()
    variants = {spec: parse_variant(spec, known) for spec in args.variants}
    width, height = parse_size(args.size)
    step, scene = scene_step(width, height, parse_count(args.n), args.variant)
    patched = {spec: Patched(settings, known) for spec, settings in variants.items()}
    outputs = {}
    for spec in variants:  # compile and warm up each variant before any is timed; keep what it computes
        with patched[spec]:
            for _ in range(3):
                step()
            outputs[spec] = image_and_grads(step, scene["P"])
    torch.cuda.synchronize()
    for spec in variants:  # an option changes the speed, never the image or the gradients
        differs = {k: float((v - outputs[args.variants[0]][k]).abs().max()) for k, v in outputs[spec].items()}
        print(f"{spec}: largest difference from {args.variants[0]} " +
              ", ".join(f"{k} {d:.3g}" for k, d in differs.items() if d) if any(differs.values())
              else f"{spec}: image and gradients equal to {args.variants[0]}'s")
    rounds: dict[str, list[dict]] = {spec: [] for spec in variants}
    for _ in range(args.rounds):
        for spec in variants:
            with patched[spec]:
                step()
                times = kernel_times(step, args.iters)
                rounds[spec].append({WARP_SUFFIX.sub("", name): ms for name, ms in times.items()})
    print(f"\n{args.size} N={args.n} {args.variant}: GPU ms per fwd+bwd by kernel, median of {args.rounds} rounds "
          f"(min-max)")
    names = sorted({k for runs in rounds.values() for r in runs for k in r},
                   key=lambda k: -statistics.median(r.get(k, 0.0) for r in rounds[args.variants[0]]))
    for spec, runs in rounds.items():
        totals = [sum(r.values()) for r in runs]
        print(f"\n{spec}: kernels {statistics.median(totals):.3f} ms ({min(totals):.3f}-{max(totals):.3f})")
        for name in names[:16]:
            times = [r.get(name, 0.0) for r in runs]
            print(f"  {statistics.median(times):8.3f} ({min(times):.3f}-{max(times):.3f})  {name[:90]}")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(dict(args=vars(args), cache=os.environ.get("WARP_CACHE_PATH"),
                                                  rounds=rounds), indent=1))


if __name__ == "__main__":
    main()
