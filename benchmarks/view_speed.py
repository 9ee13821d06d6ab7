"""How fast `tomgs view` answers: time to first picture and updates per second while scrubbing.

    python benchmarks/view_speed.py SCENE [--layer L ...] [--device auto] [--json view_speed.json]

Starts the viewer as `tomgs view` does (no browser needed) and reports
- first picture: from the start (scene loaded from disk, server started) to the first frame's splats
  handed to viser, the moment a browser that connects gets its first picture;
- scrubbing: every frame of the clip shown once in a shuffled order (seeded), as a slider dragged
  back and forth asks for them: per update the time to build the payload (alive Gaussians, baked
  opacity, covariances, colours: tomgs.viewer.server.ViewScene.frame) and to pack and queue it for the
  clients (viser's set_gaussians), their sum as updates per second, and the splats per update.
The browser's own sorting and drawing are not included: they run on the viewer's machine.
Prints a summary and writes the numbers as JSON.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tomgs.viewer.server import open_viewer  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene")
    parser.add_argument("--layer", action="append", default=[])
    parser.add_argument("--device", default="auto")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", default="view_speed.json")
    args = parser.parse_args()

    start = time.perf_counter()
    viewer = open_viewer(args.scene, args.layer, port=0, device=args.device, echo=lambda line: None)
    try:
        first = viewer.timings["first_payload"] - start
        numbers = viewer.view.cameras.frame_indices
        order = np.random.default_rng(args.seed).permutation(len(numbers))
        if order[0] == viewer.position:  # the frame shown already would cost nothing
            order = np.roll(order, 1)
        walls = []
        for k in order:
            began = time.perf_counter()
            viewer.show(int(numbers[k]))
            walls.append(time.perf_counter() - began)
        updates = viewer.timings["payloads"][1:]
    finally:
        viewer.stop()

    build = np.array([u["build_s"] for u in updates])
    send = np.array([u["send_s"] for u in updates])
    splats = np.array([u["splats"] for u in updates])
    result = {
        "scene": str(args.scene), "layers": args.layer, "device": str(viewer.view.device),
        "gaussians": len(viewer.view.scene.model), "frames": len(numbers), "updates": len(updates),
        "first_picture_s": first,
        "build_ms_median": 1e3 * float(np.median(build)), "send_ms_median": 1e3 * float(np.median(send)),
        "update_ms_median": 1e3 * float(np.median(walls)), "update_ms_p95": 1e3 * float(np.percentile(walls, 95)),
        "updates_per_s": float(1.0 / np.median(walls)), "splats_per_update_mean": float(splats.mean()),
        "python": platform.python_version(), "machine": platform.machine(),
    }
    if viewer.view.device.type == "cuda":
        import torch

        result["gpu"] = torch.cuda.get_device_name(viewer.view.device)
    print(f"{args.scene}: {result['gaussians']:,} Gaussians, {result['frames']} frames on {result['device']}\n"
          f"  first picture {first:.2f} s after start (load, server, first payload)\n"
          f"  scrubbing: {result['updates_per_s']:.1f} updates/s (median {result['update_ms_median']:.1f} ms: "
          f"build {result['build_ms_median']:.1f}, pack and queue {result['send_ms_median']:.1f}; "
          f"p95 {result['update_ms_p95']:.1f} ms), {result['splats_per_update_mean']:,.0f} splats per update")
    Path(args.json).write_text(json.dumps(result, indent=1))
    print(f"  written to {args.json}")


if __name__ == "__main__":
    main()
