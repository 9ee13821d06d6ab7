"""How fast a fitted scene renders its clip, by way of rendering: `tomgs.rasterize` frame by frame
(each frame waits for its counts) against `render_sequence` pipelined or not (frames that do not
wait for their counts), with the alive index or without (issue 15: render FPS of fitted scenes).

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
from unittest import mock

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

import tomgs  # noqa: E402
from tomgs import alive  # noqa: E402
from tomgs.render import rasterize, render_sequence  # noqa: E402


def render_modes(inputs: dict, cams, device: torch.device, built: alive.AliveIndex) -> dict:
    """Name -> a callable rendering every frame of `cams` from `inputs` (rasterize's keyword
    arguments of one cloud, on `device`), images left there: rasterize frame by frame, and
    render_sequence waiting or pipelined, with the alive index or without, and pipelined with `built`
    (the scene's, built beforehand: the frames alone, what a longer clip's frames cost, the build aside)."""
    frames = list(range(len(cams)))
    viewmats, Ks = cams.viewmats(device), cams.Ks(device)

    def each_frame():
        for k in frames:
            rasterize(**inputs, viewmat=viewmats[k], K=Ks[k], width=cams.width, height=cams.height,
                      t=float(cams.times[k]))

    def sequence(pipelined: bool | None, index: bool | None):
        def run():
            for _ in render_sequence(inputs, cams, frames, device=device, to_cpu=False, pipelined=pipelined,
                                     alive_index=index):
                pass
        return run

    modes = {"rasterize": each_frame}
    for pipelined in (False, True):
        for index in (False, True):
            name = f"sequence{' pipelined' if pipelined else ''}{' index' if index else ''}"
            modes[name] = sequence(pipelined, index)
    indexed = sequence(True, True)

    def prebuilt():
        with mock.patch.object(alive, "index_of", lambda *args, **kwargs: built):
            indexed()
    modes["sequence pipelined index prebuilt"] = prebuilt
    modes["default"] = sequence(None, None)  # render_sequence as `tomgs render` calls it (not timed)
    return modes


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
    best = {mode: math.inf for mode in modes if mode != "default"}
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
                    "of the pipelined render_sequence with the alive index and without")
    args = ap.parse_args()
    device = torch.device(args.device)
    if args.profile and device.type != "cuda":
        ap.error("--profile times kernels on a CUDA device")
    scene = tomgs.load_scene(args.scene, device=device)
    inputs = {k: v.detach() for k, v in scene.model.render_inputs().items()}
    cams = scene.cameras
    build, index = built_index(inputs, cams, device, args.repeats)
    modes = render_modes(inputs, cams, device, index)
    best = fastest_turns(modes, args.repeats, device)
    alive_counts = [int(scene.model.alive_at(t).sum()) for t in cams.times]
    listed = [len(scene.model) if rows is None else len(rows)
              for rows in (index.rows(k) for k in range(len(cams)))]
    out = dict(scene=str(args.scene), gaussians=len(scene.model), frames=len(cams), size=[cams.width, cams.height],
               alive_share=round(sum(alive_counts) / len(alive_counts) / max(len(scene.model), 1), 4),
               indexed_share=round(sum(listed) / max(len(listed), 1) / max(len(scene.model), 1), 4),
               index_build_ms=round(build, 2),
               fps={mode: round(len(cams) / seconds, 1) for mode, seconds in best.items()})
    if args.profile:
        from profile_raster import kernel_times

        out["gpu_ms_per_frame"], out["gpu_ms_per_frame_total"] = {}, {}
        for mode in ("sequence pipelined", "sequence pipelined index"):
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
