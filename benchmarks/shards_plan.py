"""Where temporal shards stop scaling: a model of a sharded fit (docs/multi-gpu.md) for 1..R ranks.

    python -m benchmarks.shards_plan                                  # the defaults below (H100/H200 guesses)
    python -m benchmarks.shards_plan --measured bench_out/shards/shards.json --budget 300
    python -m benchmarks.shards_plan --smoke     # the two-H200 run in benchmarks/results, its merge cost put in

Weak scaling, the question: a clip of `frames_per_rank` x R frames on R GPUs in the same
wall-clock budget. Each phase's time follows what it is made of, from per-rank figures that the
arguments give (or --measured fills from benchmarks/shards.py's JSON: steps per second per rank, the
union's Gaussians, the share of Gaussians alive in more than one stretch, the phases of rank 0):

    serial on rank 0   decoding the whole clip (R x frames) for the poses, the poses (R x frames),
                       writing the scene (R x Gaussians per rank)
    parallel           each rank decodes its stretch and starts its Trainer (constant in R)
    phase 1            steps of one rank: what is left of the budget x (1 - refine share)
    merge              all_gather of the owned rows: every rank receives R x G x D x 4 bytes
    refinement         per step: a rank's step, plus an all_reduce of the shared rows' gradients
                       (S x (D + 1) x 4 bytes; ring: 2 (R-1)/R of it over the slowest link, plus
                       2 (R-1) latencies), for the refine share of the training time
    memory             phase 1: a rank's cloud; the merge: the union's rows (R x G x D x 4 bytes) on
                       every GPU for a moment; refinement: a rank's part (its own and the shared ones
                       alive in its stretch) with gradients and Adam moments (4 x part x D x 4 bytes)

Quality: a rank's training steps per frame of its stretch against a one-GPU fit of one stretch in
the same budget (the goal's reference), turned into dB with the one-GPU curve's slope (dB per doubling
of training steps, --db-per-doubling: read it off a one-GPU CSV), less what the merge itself costs
(--merge-db, from benchmarks/shards.py once measured). Refinement steps count as training
steps times --refine-value (a data-parallel step of the union trains every rank's frames once). The
table says, per R: the phases, steps per frame, the predicted gap to the reference, the GPU memory of
a rank's Gaussians at its peak, and which limit binds first (serial share, memory, all_reduce over
step time).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

if __package__:
    from .common import ROOT, environment, output_folder, write_report
else:  # run as a file: Python puts this folder first on sys.path
    from common import ROOT, environment, output_folder, write_report

GIB = 2**30
# the per-rank figures of a two-H200 run and the merge's own cost measured there (benchmarks/README.md)
MEASURED = ROOT / "benchmarks" / "results" / "shards_h200x2.json"
MEASURED_MERGE_DB = 0.39


def model(args, ranks: int, reference_steps: float | None = None) -> dict:
    """One row of the table: a fit of ranks x frames_per_rank frames on `ranks` GPUs; its quality gap
    to `reference_steps` training steps per rank (one GPU on one stretch: `model(args, 1)`'s)."""
    frames = ranks * args.frames_per_rank
    pixels = args.width * args.height
    per_host = min(ranks, args.gpus_per_host)
    link = args.nvlink_gbs if ranks <= args.gpus_per_host else args.network_gbs  # the slowest link of the ring
    serial = (args.decode_s_per_mpx * frames * args.source_pixels / 1e6  # rank 0 decodes everything for the poses
              + args.pose_setup_s + args.pose_s_per_mpx * frames * pixels / 1e6)
    if ranks == 1:
        serial -= args.decode_s_per_mpx * frames * args.source_pixels / 1e6  # one decode: the fit's own
    parallel = args.decode_s_per_mpx * args.frames_per_rank * args.source_pixels / 1e6 + args.init_s
    union = ranks * args.gaussians_per_rank
    save = args.save_s + args.save_s_per_million * union / 1e6
    row_bytes = 4 * args.floats_per_gaussian
    merge = (0.0 if ranks == 1 else
             (ranks - 1) / ranks * union * row_bytes / (link * 1e9) + 2 * (ranks - 1) * args.latency_s)
    evaluate = (2 if ranks > 1 else 1) * args.frames_per_rank * args.render_s  # before and after refining
    left = args.budget - serial - parallel - merge - evaluate - save - args.startup_s * (ranks > 1)
    share = args.refine_share if ranks > 1 else 0.0
    phase1 = max(left, 0.0) * (1 - share)
    refine = max(left, 0.0) * share
    shared = args.shared_fraction * min(1.0, (ranks - 1) / max(args.shared_ranks, 1)) * union if ranks > 1 else 0
    allreduce = (0.0 if ranks == 1 else
                 2 * (ranks - 1) / ranks * shared * (row_bytes + 4) / (link * 1e9) + 2 * (ranks - 1) * args.latency_s)
    step = 1.0 / args.steps_per_s
    refine_step = step * args.union_render_factor + allreduce
    steps = phase1 / step + args.refine_value * refine / refine_step
    reference = steps if reference_steps is None else reference_steps
    gap = args.db_per_doubling * math.log2(max(steps, 1e-9) / max(reference, 1e-9))
    gap -= args.merge_db if ranks > 1 else 0.0
    part = args.gaussians_per_rank * (1 + (args.shared_fraction if ranks > 1 else 0.0))
    memory = max(4 * part * row_bytes, union * row_bytes if ranks > 1 else 0.0) / GIB
    limits = []
    if (serial + save) > 0.25 * args.budget:
        limits.append(f"serial {100 * (serial + save) / args.budget:.0f}% of the budget")
    if memory + args.frames_gib_per_rank > args.gpu_gib:
        limits.append(f"{memory:.0f} GiB > GPU")
    if ranks > 1 and allreduce > step:
        limits.append(f"all_reduce {1000 * allreduce:.0f} ms > a step")
    if left <= 0:
        limits.append("no time left to train")
    return dict(ranks=ranks, hosts=math.ceil(ranks / per_host), frames=frames, serial_s=serial, parallel_s=parallel,
                merge_s=merge, phase1_s=phase1, refine_s=refine, allreduce_ms=1000 * allreduce, save_s=save,
                steps=steps, steps_per_frame=steps / args.frames_per_rank, gap_db=gap, gpu_gib=memory,
                limits="; ".join(limits) or "-")


def table(rows: list[dict]) -> str:
    head = ("| ranks | hosts | frames | serial s | per-rank start s | merge s | phase 1 s | refine s | all_reduce ms "
            "| save s | steps/frame | gap dB | GiB/GPU | binds |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        lines.append(f"| {r['ranks']} | {r['hosts']} | {r['frames']:,} | {r['serial_s']:.1f} | {r['parallel_s']:.1f} "
                     f"| {r['merge_s']:.2f} | {r['phase1_s']:.0f} | {r['refine_s']:.0f} | {r['allreduce_ms']:.1f} "
                     f"| {r['save_s']:.1f} | {r['steps_per_frame']:.1f} | {r['gap_db']:+.2f} | {r['gpu_gib']:.1f} "
                     f"| {r['limits']} |")
    return "\n".join(lines)


def fill_from(path: Path, args) -> None:
    """Per-rank figures from benchmarks/shards.py's JSON: the sharded case's steps/s, Gaussians, frames."""
    data = json.loads(path.read_text())
    if "env" in data:  # shards.py's report: the run's command and commit beside it
        data = data["results"]
    results = data["results"]
    sharded = results.get(f"full_{data['gpus']}gpu")
    if sharded is None:
        raise SystemExit(f"{path}: no sharded case to read per-rank figures from")
    per_rank = sharded["shards"]["per_rank"]
    args.steps_per_s = sum(r["steps_per_s"] for r in per_rank) / len(per_rank)
    args.frames_per_rank = max(r["frames"] for r in per_rank)
    args.gaussians_per_rank = sharded["gaussians"] / len(per_rank)
    args.budget = data["budget_s"]
    print(f"from {path}: {args.steps_per_s:.1f} steps/s per rank, {args.frames_per_rank} frames and "
          f"{args.gaussians_per_rank:,.0f} Gaussians per rank, budget {args.budget:.0f} s")


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    a = ap.add_argument
    a("--measured", type=Path, default=None, help="benchmarks/shards.py's shards.json: per-rank figures from it")
    a("--budget", type=float, default=300.0, help="the wall-clock budget of every fit, seconds")
    a("--frames-per-rank", type=int, default=300)
    a("--width", type=int, default=854)
    a("--height", type=int, default=480)
    a("--source-pixels", type=float, default=854 * 480, help="pixels of a decoded source frame")
    a("--steps-per-s", type=float, default=60.0, help="a rank's phase-1 steps per second (measured)")
    a("--gaussians-per-rank", type=float, default=2.5e6)
    a("--floats-per-gaussian", type=int, default=16, help="stored floats per Gaussian: 16 at SH 0, 59 at SH 3")
    a("--shared-fraction", type=float, default=0.3,
      help="of the union, the Gaussians alive in more than one stretch once there are --shared-ranks or more")
    a("--shared-ranks", type=int, default=2)
    a("--refine-share", type=float, default=0.15, help="of the training time (tomgs.train.multigpu.shards.REFINE_FRACTION)")
    a("--refine-value", type=float, default=0.8, help="a refinement step's worth in training steps")
    a("--union-render-factor", type=float, default=1.3, help="a refinement step's time over a phase-1 step's")
    a("--db-per-doubling", type=float, default=0.8, help="the one-GPU curve's slope: dB per doubling of steps")
    a("--merge-db", type=float, default=0.0,
      help="dB the merge itself costs at equal steps (benchmarks/shards.py: sharded vs the parts alone, less the time)")
    a("--decode-s-per-mpx", type=float, default=0.01, help="decoding, seconds per megapixel (tomgs.train.plan)")
    a("--pose-s-per-mpx", type=float, default=0.007, help="the tracker, seconds per megapixel (GPU)")
    a("--pose-setup-s", type=float, default=5.0)
    a("--init-s", type=float, default=5.0, help="a rank's Trainer start (kernels, initial cloud)")
    a("--startup-s", type=float, default=8.0, help="spawning the ranks, CUDA and NCCL start")
    a("--render-s", type=float, default=0.003, help="one full-frame render for a measurement")
    a("--save-s", type=float, default=0.5)
    a("--save-s-per-million", type=float, default=0.3)
    a("--gpus-per-host", type=int, default=8)
    a("--nvlink-gbs", type=float, default=300.0, help="all_reduce bus bandwidth inside a host, GB/s")
    a("--network-gbs", type=float, default=25.0, help="between hosts (200 Gb/s per host), GB/s")
    a("--latency-s", type=float, default=20e-6, help="per hop of a ring collective")
    a("--gpu-gib", type=float, default=139.0)
    a("--frames-gib-per-rank", type=float, default=0.4, help="a rank's uint8 frames on its GPU")
    a("--ranks", default="1,2,4,8,16,32,64")
    a("--out", default=None, help="default bench_out/shards_plan")
    a("--smoke", action="store_true", help=f"--measured {MEASURED.relative_to(ROOT)} --merge-db {MEASURED_MERGE_DB}")
    args = ap.parse_args(argv)
    if args.smoke:
        args.measured, args.merge_db = MEASURED, MEASURED_MERGE_DB
    out = output_folder(args.out, args.smoke, "shards_plan")
    if args.measured is not None:
        fill_from(args.measured, args)
    reference = model(args, 1)["steps"]  # one GPU on one stretch: the goal's reference
    rows = [model(args, int(r), reference) for r in args.ranks.split(",")]
    write_report(out, "shards_plan", "shards_plan: where temporal shards stop scaling (a model)",
                 environment("cpu", "shards_plan", argv), table(rows),
                 dict(args={k: str(v) for k, v in vars(args).items()}, rows=rows))
    return rows


if __name__ == "__main__":
    main()
