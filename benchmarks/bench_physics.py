"""How fast the soft-body solver (`tomgs.edit.physics.simulate`) runs a tetrahedralised box, and whether
it keeps its volume: the first call (kernels loaded, the tets coloured) and a warm call, per device.

    python -m benchmarks.bench_physics --cells 12 --frames 80 --preset spin --devices cpu,cuda
    python -m benchmarks.bench_physics --smoke     # a 3-cell box, 5 frames, on the CPU

Writes bench_physics.md / .json.
"""

from __future__ import annotations

import argparse
import time

from tomgs.edit.physics import SimConfig, body_extent, box_tets, simulate_with_stats

if __package__:
    from .common import environment, markdown_table, output_folder, write_report
else:  # run as a file: Python puts this folder first on sys.path
    from common import environment, markdown_table, output_folder, write_report


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cells", type=int, default=12, help="cells per side; 6 tets per cell")
    parser.add_argument("--frames", type=int, default=80)
    parser.add_argument("--devices", default="cpu", help="comma-separated Warp devices, e.g. cpu,cuda")
    parser.add_argument("--preset", default="spin", choices=("spin", "drop"))
    parser.add_argument("--out", default=None, help="default bench_out/bench_physics")
    parser.add_argument("--smoke", action="store_true", help="3 cells a side, 5 frames, on the CPU")
    args = parser.parse_args(argv)
    if args.smoke:
        args.cells, args.frames, args.devices = 3, 5, "cpu"
    out = output_folder(args.out, args.smoke, "bench_physics")
    vertices, tets = box_tets((args.cells,) * 3)
    config = getattr(SimConfig, args.preset)(body_extent(vertices), frames=args.frames)
    rows = []
    for device in args.devices.split(","):
        for call in ("first", "warm"):
            start = time.perf_counter()
            result = simulate_with_stats(vertices, tets, config, device=device)
            seconds = time.perf_counter() - start
            rows.append(dict(device=device, call=call, seconds=seconds, frames_per_s=args.frames / seconds,
                             min_volume_ratio=result.min_volume_ratio, inverted_frames=len(result.inverted_frames),
                             final_speed=result.final_speed))
    body = (f"{args.preset}: {len(vertices)} vertices, {len(tets)} tets, {args.frames} frames x {config.substeps} "
            "substeps\n\n" + markdown_table(list(rows[0]), [list(r.values()) for r in rows]))
    write_report(out, "bench_physics", "bench_physics: the soft-body solver", environment("cpu", "bench_physics", argv),
                 body, rows)
    return rows


if __name__ == "__main__":
    main()
