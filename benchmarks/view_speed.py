"""How fast `tomgs view` answers: time to first picture and updates per second while scrubbing.

    python -m benchmarks.view_speed SCENE [--layer L ...] [--device auto] [--out <out>]
    python -m benchmarks.view_speed --smoke       # the demo scene on the CPU, seconds

Starts the viewer as `tomgs view` does (no browser needed) and reports
- first picture: from the start (scene loaded from disk, server started) to the first frame's splats
  handed to viser, the moment a browser that connects gets its first picture;
- scrubbing: every frame of the clip shown once in a shuffled order (seeded), as a slider dragged
  back and forth asks for them: per update the time to build the payload (alive Gaussians, baked
  opacity, covariances, colours: tomgs.viewer.server.ViewScene.frame) and to pack and queue it for the
  clients (viser's set_gaussians), their sum as updates per second, and the splats per update.
The browser's own sorting and drawing are not included: they run on the viewer's machine.
Writes view_speed.md / .json.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from tomgs.viewer import open_viewer

if __package__:
    from .common import environment, markdown_table, output_folder, smoke_scene, write_report
else:  # run as a file: Python puts this folder first on sys.path
    from common import environment, markdown_table, output_folder, smoke_scene, write_report


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", nargs="?")
    parser.add_argument("--layer", action="append", default=[])
    parser.add_argument("--device", default="auto")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="default bench_out/view_speed")
    parser.add_argument("--smoke", action="store_true", help="the demo scene (8 frames at 48x27) on the CPU")
    args = parser.parse_args(argv)
    out = output_folder(args.out, args.smoke, "view_speed")
    if args.smoke:
        args.scene, args.device = str(smoke_scene(out / "smoke.ply")), "cpu"
    elif args.scene is None:
        parser.error("a scene file is required (or --smoke)")

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
    }
    body = (f"{args.scene}: {result['gaussians']:,} Gaussians, {result['frames']} frames, server side (the "
            "browser draws)\n\n"
            + markdown_table(["first picture s", "updates/s while scrubbing", "update ms, median / p95",
                              "build ms", "pack and queue ms", "splats per update"],
                             [[first, result["updates_per_s"],
                               f"{result['update_ms_median']:.1f} / {result['update_ms_p95']:.1f}",
                               result["build_ms_median"], result["send_ms_median"],
                               f"{result['splats_per_update_mean']:,.0f}"]]))
    write_report(out, "view_speed", "view_speed: how fast tomgs view answers",
                 environment(viewer.view.device, "view_speed", argv), body, result)
    return result


if __name__ == "__main__":
    main()
