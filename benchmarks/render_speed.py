"""How fast a fitted scene renders its clip, by way of rendering: `tomgs.rasterize` frame by frame (each
frame waits for its counts) against `render_sequence` (frames that do not wait, from the alive index's
rows), its frames issued from Python or replayed from a captured frame, in one call or from a
`tomgs.ClipRenderer` kept across calls.

    python -m benchmarks.render_speed scene.ply --repeats 5 --profile --out <out>
    python -m benchmarks.render_speed --smoke          # the demo scene on the CPU, seconds

Images stay on the device; the modes take turns and each mode's quickest turn counts. --profile adds
the GPU time per frame by kernel of the kept renderers' frames (CUDA). Writes render_speed.md / .json.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import torch

import tomgs
from tomgs.render import alive

if __package__:
    from .common import environment, fastest, kernel_times, markdown_table, output_folder, render_modes, \
        smoke_scene, sync, write_report
else:  # run as a file: Python puts this folder first on sys.path
    from common import environment, fastest, kernel_times, markdown_table, output_folder, render_modes, \
        smoke_scene, sync, write_report


def built_index(inputs: dict, cams, device: torch.device, repeats: int) -> tuple[float, alive.AliveIndex]:
    """(milliseconds of the quickest of `repeats` builds, the index): the scene's alive index over its frames."""
    best = math.inf
    for _ in range(repeats + 1):  # the first loads what the build runs
        sync(device)
        start = time.perf_counter()
        index = alive.index_of(inputs["opacities"], inputs["t_means"], inputs["t_scales"], list(cams.times))
        sync(device)
        best = min(best, time.perf_counter() - start)
    return best * 1e3, index


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path, nargs="?")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None, help="default bench_out/render_speed")
    ap.add_argument("--profile", action="store_true", help="also the GPU time per frame by kernel (torch profiler), "
                    "of the kept renderers' frames, issued from Python and replayed")
    ap.add_argument("--smoke", action="store_true", help="the demo scene (8 frames at 48x27) on the CPU, one turn")
    args = ap.parse_args(argv)
    out = output_folder(args.out, args.smoke, "render_speed")
    if args.smoke:
        args.scene, args.device, args.repeats = smoke_scene(out / "smoke.ply"), "cpu", 1
    elif args.scene is None:
        ap.error("a scene file is required (or --smoke)")
    device = torch.device(args.device)
    if args.profile and device.type != "cuda":
        ap.error("--profile times kernels on a CUDA device")
    scene = tomgs.load_scene(args.scene, device=device)
    inputs = {k: v.detach() for k, v in scene.model.render_inputs().items()}
    cams = scene.cameras
    build, index = built_index(inputs, cams, device, args.repeats)
    modes, kept = render_modes(inputs, cams, device)
    with torch.no_grad():
        best = fastest(modes, args.repeats, device)
    alive_counts = [int(scene.model.alive_at(t).sum()) for t in cams.times]
    listed = [len(scene.model) if rows is None else len(rows) for rows in (index.rows(k) for k in range(len(cams)))]
    result = dict(scene=str(args.scene), gaussians=len(scene.model), frames=len(cams), size=[cams.width, cams.height],
                  alive_share=round(sum(alive_counts) / len(alive_counts) / max(len(scene.model), 1), 4),
                  indexed_share=round(sum(listed) / max(len(listed), 1) / max(len(scene.model), 1), 4),
                  index_build_ms=round(build, 2),
                  fps={mode: round(len(cams) / seconds, 1) for mode, seconds in best.items()},
                  kept_captures=kept.graph.captures if kept.graph else 0)
    if args.profile:
        result["gpu_ms_per_frame"], result["gpu_ms_per_frame_total"] = {}, {}
        for mode in ("kept eager", "kept"):
            with torch.no_grad():
                per_kernel = kernel_times(modes[mode], 1)
            result["gpu_ms_per_frame"][mode] = {name: round(ms / len(cams), 4) for name, ms in
                                                sorted(per_kernel.items(), key=lambda kv: -kv[1])[:16]}
            result["gpu_ms_per_frame_total"][mode] = round(sum(per_kernel.values()) / len(cams), 4)
    body = (f"{args.scene}: {result['gaussians']:,} Gaussians, {result['frames']} frames of "
            f"{cams.width}x{cams.height}, {result['alive_share']:.1%} alive at a frame ({result['indexed_share']:.1%} "
            f"listed by the index, built in {result['index_build_ms']} ms); frames per second, the quickest of "
            f"{args.repeats} turns:\n\n"
            + markdown_table(list(result["fps"]), [list(result["fps"].values())]))
    if args.profile:
        totals = result["gpu_ms_per_frame_total"]
        body += "\n\nGPU ms a frame: " + ", ".join(f"{mode} {ms}" for mode, ms in totals.items())
    write_report(out, "render_speed", "render_speed: a fitted scene's clip", environment(device, "render_speed", argv),
                 body, result)
    return result


if __name__ == "__main__":
    main()
