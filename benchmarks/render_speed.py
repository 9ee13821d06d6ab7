"""How fast a fitted scene renders its clip, by way of rendering: `tomgs.rasterize` frame by frame
(each frame waits for its counts) against `render_sequence` (frames that do not wait for their
counts, from the alive index's rows), its frames issued from Python or replayed from a captured
frame, in one call or from a `ClipRenderer` kept across calls (issue 15: render FPS of fitted scenes).

    python benchmarks/render_speed.py scene.ply --repeats 3 --json speed.json

Images stay on the device; the modes take turns and each mode's quickest turn counts.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

import tomgs  # noqa: E402
from tomgs.render import alive  # noqa: E402
from tomgs.render.frame import rasterize  # noqa: E402
from tomgs.render.sequence import ClipRenderer, render_sequence  # noqa: E402


def render_modes(inputs: dict, cams, device: torch.device) -> tuple[dict, ClipRenderer]:
    """(name -> a callable rendering every frame of `cams` from `inputs` (rasterize's keyword
    arguments of one cloud, on `device`), images left there:
    - rasterize: frame by frame, each waiting for its counts;
    - sequence waiting: render_sequence, frames waiting for their counts;
    - sequence eager / sequence: a call of render_sequence as sessions 24-30 made it (pipelined frames
      of the alive index, issued from Python) / as it is (the index's rows through a captured frame),
      each call building its index (and capture);
    - kept eager / kept: the same from a ClipRenderer kept across calls (index made once, in the
      untimed turn, and the capture made at the third turn, tomgs.render.sequence.REPLAY_FRAMES, where the
      clip has fewer than 64 frames): what the frames alone cost;
    the kept renderer that replays)."""
    frames = list(range(len(cams)))
    viewmats, Ks = cams.viewmats(device), cams.Ks(device)

    def each_frame():
        for k in frames:
            rasterize(**inputs, viewmat=viewmats[k], K=Ks[k], width=cams.width, height=cams.height,
                      t=float(cams.times[k]))

    def run(renderer_of):
        def go():
            for _ in renderer_of().frames(frames, to_cpu=False):
                pass
        return go

    def waiting():
        for _ in render_sequence(inputs, cams, frames, device=device, to_cpu=False, pipelined=False):
            pass

    kept_eager = ClipRenderer(inputs, cams, device=device, replay=False)
    kept = ClipRenderer(inputs, cams, device=device)
    return {"rasterize": each_frame, "sequence waiting": waiting,
            "sequence eager": run(lambda: ClipRenderer(inputs, cams, device=device, replay=False)),
            "sequence": run(lambda: ClipRenderer(inputs, cams, device=device)),
            "kept eager": run(lambda: kept_eager), "kept": run(lambda: kept)}, kept


def built_index(inputs: dict, cams, device: torch.device, repeats: int) -> tuple[float, alive.AliveIndex]:
    """(milliseconds of the quickest of `repeats` builds, the index): the scene's alive index over its frames."""
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    best = math.inf
    for _ in range(repeats + 1):  # the first loads what the build runs
        sync()
        start = time.perf_counter()
        index = alive.index_of(inputs["opacities"], inputs["t_means"], inputs["t_scales"], list(cams.times))
        sync()
        best = min(best, time.perf_counter() - start)
    return best * 1e3, index


def fastest_turns(modes: dict, repeats: int, device: torch.device) -> dict[str, float]:
    """Seconds of each mode's quickest turn over `repeats` turns, the modes taking turns (a shared
    machine's load hits all alike), after one untimed turn (kernels loaded, the keys' bounds set)."""
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    best = {mode: math.inf for mode in modes}
    with torch.no_grad():
        for turn in range(repeats + 1):
            for mode in best:
                sync()
                start = time.perf_counter()
                modes[mode]()
                sync()
                if turn:
                    best[mode] = min(best[mode], time.perf_counter() - start)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--profile", action="store_true", help="also the GPU time per frame by kernel (torch profiler), "
                    "of the kept renderers' frames, issued from Python and replayed")
    args = ap.parse_args()
    device = torch.device(args.device)
    if args.profile and device.type != "cuda":
        ap.error("--profile times kernels on a CUDA device")
    scene = tomgs.load_scene(args.scene, device=device)
    inputs = {k: v.detach() for k, v in scene.model.render_inputs().items()}
    cams = scene.cameras
    build, index = built_index(inputs, cams, device, args.repeats)
    modes, kept = render_modes(inputs, cams, device)
    best = fastest_turns(modes, args.repeats, device)
    alive_counts = [int(scene.model.alive_at(t).sum()) for t in cams.times]
    listed = [len(scene.model) if rows is None else len(rows)
              for rows in (index.rows(k) for k in range(len(cams)))]
    out = dict(scene=str(args.scene), gaussians=len(scene.model), frames=len(cams), size=[cams.width, cams.height],
               alive_share=round(sum(alive_counts) / len(alive_counts) / max(len(scene.model), 1), 4),
               indexed_share=round(sum(listed) / max(len(listed), 1) / max(len(scene.model), 1), 4),
               index_build_ms=round(build, 2),
               fps={mode: round(len(cams) / seconds, 1) for mode, seconds in best.items()},
               kept_captures=kept.graph.captures if kept.graph else 0)
    if args.profile:
        from profile_raster import kernel_times

        out["gpu_ms_per_frame"], out["gpu_ms_per_frame_total"] = {}, {}
        for mode in ("kept eager", "kept"):
            with torch.no_grad():
                per_kernel = kernel_times(modes[mode], 1)
            out["gpu_ms_per_frame"][mode] = {name: round(ms / len(cams), 4)
                                             for name, ms in sorted(per_kernel.items(), key=lambda kv: -kv[1])[:16]}
            out["gpu_ms_per_frame_total"][mode] = round(sum(per_kernel.values()) / len(cams), 4)
    print(json.dumps(out, indent=1))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
