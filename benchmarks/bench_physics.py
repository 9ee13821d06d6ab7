"""Time `tomgs.edit.physics.simulate` on a tetrahedralised box: first call (compile + colouring)
and a warm call, per device.

    PYTHONPATH=. python benchmarks/bench_physics.py --cells 20 --devices cpu,cuda
"""

from __future__ import annotations

import argparse
import time

from tomgs.edit.physics import SimConfig, body_extent, box_tets, simulate_with_stats


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, default=12, help="cells per side; 6 tets per cell")
    parser.add_argument("--frames", type=int, default=80)
    parser.add_argument("--devices", default="cpu", help="comma-separated Warp devices, e.g. cpu,cuda")
    parser.add_argument("--preset", default="spin", choices=("spin", "drop"))
    args = parser.parse_args()
    vertices, tets = box_tets((args.cells,) * 3)
    config = getattr(SimConfig, args.preset)(body_extent(vertices), frames=args.frames)
    print(f"{len(vertices)} vertices, {len(tets)} tets, {args.frames} frames x {config.substeps} substeps")
    for device in args.devices.split(","):
        for run in ("first", "warm"):
            start = time.perf_counter()
            result = simulate_with_stats(vertices, tets, config, device=device)
            seconds = time.perf_counter() - start
            print(f"{device:>6} {run:>5}: {seconds:7.2f} s  {args.frames / seconds:7.1f} frames/s  "
                  f"min V/V0 {result.min_volume_ratio:.3f}  inverted frames {len(result.inverted_frames)}  "
                  f"final speed {result.final_speed:.3f}")


if __name__ == "__main__":
    main()
