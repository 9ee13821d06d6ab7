"""Several GPUs for long clips: the same clip fitted with 1 and with N GPUs for the same wall time.

    python -m benchmarks.shards --out $OUT                                  # nvidia-h200-x2, ~8 min
    python -m benchmarks.shards --tiny --out bench_out/shards_tiny          # CPU: 2 gloo ranks, 45 s fits
    python -m benchmarks.shards --smoke                                     # CPU: 8 iterations a fit, seconds

The clip: --clip (a video or a frame folder), or the demo scene (--synthetic FRAMES,WxH) made once in --work.
Every case is one fit (tomgs.train.fit, as `tomgs fit ... --budget B` runs it) in its own process, with
the same --budget (the whole command's wall time: reading, poses, training, merge and saving) and, on
a GPU, 100,000 iterations, so that every fit ends at its budget:

    half0 .. half{N-1}  one GPU each on its 1/N of the clip, side by side (CUDA_VISIBLE_DEVICES=r): what a
                        GPU reaches on that share alone, the goal's reference ("N GPUs fit N times the frames
                        to the same PSNR in the same time")
    full_1gpu           one GPU on the whole clip: what the extra GPUs are measured against
    full_{N}gpu         --gpus N on the whole clip (temporal shards, docs/multi-gpu.md)
    full_{N}gpu_r{F}    the same with a refinement fraction F (--refine, repeatable; 0: the union as merged)
    full_{N}gpu_o{K}    the same with stretches reaching K frames into their neighbours (--overlap)
    full_{N}gpu_fresh   the same with the refinement starting from a fresh Adam (--fresh-adam), not from each
                        Gaussian's phase-1 Adam state (the default since the refinement's first steps were seen
                        to knock converged Gaussians about: docs/multi-gpu.md)

Each scene is then rendered here at every frame it was fitted on and compared with the clip (float
renders, PSNR): mean PSNR; per-boundary PSNR (the frames within --near frames of each boundary between
the N stretches, the same frames for every case that has them, against the others); steps per second
per rank (phase 1 of a sharded fit: its ranks' own; one GPU: iterations over training seconds); plus
Gaussians, iterations, wall time and seconds per phase; and where the wall time went: each case's
timeline (a sharded fit's FitResult.timeline: the parent's and every rank's phases from the
command's start, process start-up, waits for rank 0, warm-up, merge, refinement, final measurement,
save, exit; a one-GPU fit's phases laid end to end) and budget_left_s (the budget less the time the
fit took to return), as a table per case at the end of shards.md. Writes WORK/<case>/result.json as each case
ends, and OUT/shards.json, OUT/shards.md (every case found in WORK) and each case's CSV logs to OUT.
Cases already in WORK are kept unless --redo: a run split over several commands (--cases) adds up.
The history of these runs: docs/notes/multi-gpu.md.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

if __package__:
    from .common import demo_video, environment, output_folder, parse_size, write_report
else:  # run as a file (each case is): Python puts this folder first on sys.path
    from common import demo_video, environment, output_folder, parse_size, write_report


def make_clip(work: Path, frames: int, size: str, device: str) -> Path:
    """The demo scene at `size` with `frames` frames (kept in `work`), as an MP4 rendered on `device`."""
    path = work / f"demo_{frames}_{size}.mp4"
    if not path.exists():
        began = time.perf_counter()
        demo_video(path, frames, *parse_size(size), device="cuda" if device == "cuda" else "cpu")
        print(f"made {path} in {time.perf_counter() - began:.0f} s", flush=True)
    return path


def cases(args, count: int) -> list[dict]:
    """The case specs: name, the fit's arguments, and the GPU(s) it runs on."""
    from tomgs.train.multigpu.shards import plan_stretches

    n = args.gpus
    out = []
    for s in plan_stretches(count, n):
        out.append(dict(name=f"half{s.rank}" if n == 2 else f"part{s.rank}", positions=[s.own_lo, s.own_hi], gpus=None,
                        visible=str(s.rank), group="halves", part=s.rank))
    out.append(dict(name="full_1gpu", positions=None, gpus=None, visible="0", group="full_1gpu"))
    out.append(dict(name=f"full_{n}gpu", positions=None, gpus=n, visible=",".join(map(str, range(n))),
                    group=f"full_{n}gpu"))
    for fraction in args.refine:
        out.append(dict(name=f"full_{n}gpu_r{fraction:g}", positions=None, gpus=n, refine=fraction,
                        visible=",".join(map(str, range(n))), group=f"full_{n}gpu_r{fraction:g}"))
    for frames in args.overlap:
        out.append(dict(name=f"full_{n}gpu_o{frames}", positions=None, gpus=n, overlap=frames,
                        visible=",".join(map(str, range(n))), group=f"full_{n}gpu_o{frames}"))
    if args.fresh_adam:
        out.append(dict(name=f"full_{n}gpu_fresh", positions=None, gpus=n, carry_adam=False,
                        visible=",".join(map(str, range(n))), group=f"full_{n}gpu_fresh"))
    return out


def run_group(specs: list[dict], args, clip: Path, work: Path) -> None:
    """Run specs side by side (one process each), each writing WORK/<name>/result.json."""
    procs = []
    for spec in specs:
        folder = work / spec["name"]
        if folder.exists():
            shutil.rmtree(folder)
        folder.mkdir(parents=True)
        spec = dict(spec, clip=str(clip), budget=args.budget, device=args.device, poses=args.poses,
                    max_side=args.max_side, frames_spec=_frames_spec(spec, args), folder=str(folder),
                    iterations=args.iterations, log_interval=args.log_interval)
        (folder / "spec.json").write_text(json.dumps(spec, indent=1))
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        if args.device == "cuda":
            env["CUDA_VISIBLE_DEVICES"] = spec["visible"]
        else:  # CPU processes side by side share the cores, as the ranks of a sharded fit do
            env["OMP_NUM_THREADS"] = str(max(1, (os.cpu_count() or 1) // len(specs)))
        log = open(folder / "fit.log", "w")
        print(f"{spec['name']}: started (GPU {spec['visible']})" if args.device == "cuda" else
              f"{spec['name']}: started", flush=True)
        procs.append((spec, subprocess.Popen([sys.executable, __file__, "--run-case", str(folder / "spec.json")],
                                             env=env, stdout=log, stderr=subprocess.STDOUT), log, time.perf_counter()))
    for spec, proc, log, began in procs:
        code = proc.wait()
        log.close()
        print(f"{spec['name']}: exit {code} after {time.perf_counter() - began:.0f} s", flush=True)
        if code != 0:
            print((work / spec["name"] / "fit.log").read_text()[-3000:], file=sys.stderr)


def _frames_spec(spec: dict, args) -> str | None:
    """The --frames of a case: a part's positions of the selected clip (source numbers when --frames
    selected a range of the source)."""
    if spec["positions"] is None:
        return args.frames
    lo, hi = spec["positions"]
    if args.frames is None:
        return f"{lo}:{hi}"
    from tomgs.io.video import parse_frames

    sel = parse_frames(args.frames)
    start, step = sel.start or 0, sel.step or 1
    return f"{start + lo * step}:{start + hi * step}:{step}"


def run_case(spec_path: Path) -> None:
    """One case, in this process: the fit (its own budget), then every frame of its scene measured."""
    spec = json.loads(spec_path.read_text())
    if spec["gpus"]:  # as `tomgs fit --gpus N` does: the ranks import while this process does
        from tomgs.train.multigpu import pool

        pool.start(spec["gpus"])
    import numpy as np
    import torch

    from tomgs.train import fit, preset
    from tomgs.train.phases import tomgs_started

    started = tomgs_started()
    folder = Path(spec["folder"])
    overrides = dict(max_seconds=spec["budget"])
    if spec.get("iterations"):  # beside the budget: whichever comes first
        overrides.update(iterations=spec["iterations"], stop_at_iterations=True)
    if spec.get("log_interval"):
        overrides["log_interval"] = spec["log_interval"]
    config = preset("default", **overrides)
    kwargs = dict(frames=spec["frames_spec"], max_side=spec["max_side"], poses=spec["poses"], device=spec["device"],
                  overwrite=True, started=started)
    scene = folder / "scene.ply"
    if spec["gpus"]:
        from tomgs.train.multigpu.launch import fit_shards

        extra = {k: spec[key] for k, key in (("refine_fraction", "refine"), ("overlap", "overlap"),
                                             ("carry_adam", "carry_adam")) if key in spec}
        result = fit_shards(spec["clip"], scene, config, gpus=spec["gpus"], **kwargs, **extra)
    else:
        result = fit(spec["clip"], scene, config, **kwargs)
    wall = time.perf_counter() - started
    frame_psnr, eval_s = evaluate(scene, spec["clip"], spec["device"])
    out = dict(name=spec["name"], group=spec["group"], part=spec.get("part"), frames_spec=spec["frames_spec"],
               budget_s=spec["budget"],
               wall_s=round(wall, 1), fit_psnr=round(result.clip_psnr, 3), psnr=round(float(np.mean(frame_psnr)), 3),
               frame_psnr=[round(p, 3) for p in frame_psnr], iterations=result.iterations,
               train_s=round(result.seconds, 1), phase_s={k: round(v, 1) for k, v in result.phase_seconds.items()},
               gaussians=len(result.model), peak_gpu_gib=None if result.peak_gpu_mb is None else
               round(result.peak_gpu_mb / 1024, 2), eval_s=round(eval_s, 1), shards=getattr(result, "shards", None),
               device=torch.cuda.get_device_name(0) if spec["device"] == "cuda" else "cpu")
    out["budget_left_s"] = round(spec["budget"] - wall, 2)  # when the fit returned, against its budget
    out["timeline"] = getattr(result, "timeline", None) or one_process_timeline(result.phase_seconds, wall)
    if out["shards"] is None:
        out["steps_per_s"] = [round(result.iterations / max(result.seconds, 1e-9), 2)]
    else:
        out["steps_per_s"] = [r["steps_per_s"] for r in out["shards"]["per_rank"]]
        out["refine_start"] = refine_start(folder, out["shards"]["per_rank"])
        out["shards"] = {k: v for k, v in out["shards"].items() if k != "frame_psnr"}
    (folder / "result.json").write_text(json.dumps(out, indent=1))


def refine_start(folder: Path, per_rank: list[dict]) -> dict:
    """The refinement's training PSNR row by row (the ranks' mean, from rank 0's CSV: [step, wall s,
    dB]) against where phase 1 left it (each rank's last phase-1 row, frame-weighted): the dip a fresh
    optimiser makes shows here. Also its lowest row and the first row back at phase 1's level."""
    import csv

    logs = [list(csv.DictReader(open(folder / f"scene.rank{r['rank']}.csv"))) for r in per_rank]
    ends = [[row for row in rows if int(row["iteration"]) <= r["iterations"] and row["train_psnr"] != ""][-1]
            for rows, r in zip(logs, per_rank)]
    weights = [r["own"][1] - r["own"][0] for r in per_rank]
    before = sum(w * float(row["train_psnr"]) for w, row in zip(weights, ends)) / sum(weights)
    curve = [[int(row["iteration"]) - per_rank[0]["iterations"], float(row["wall_s"]), float(row["train_psnr"])]
             for row in logs[0] if int(row["iteration"]) > per_rank[0]["iterations"] and row["train_psnr"] != ""]
    lowest = min(curve, key=lambda c: c[2]) if curve else None
    back = next((c[0] for c in curve if c[2] >= before), None)
    return dict(phase1_end_psnr=round(before, 3), curve=curve, lowest=lowest, back_at_step=back)


def one_process_timeline(seconds: dict, wall: float) -> dict:
    """A one-GPU fit's phases laid end to end after its start-up (what its wall time leaves of them),
    as a sharded fit's timeline has them (seconds since the command started)."""
    at = max(wall - sum(seconds.values()), 0.0)
    events = [dict(phase="start-up", start=0.0, end=round(at, 3))]
    for name, length in seconds.items():
        events.append(dict(phase=name, start=round(at, 3), end=round(at + length, 3)))
        at += length
    return dict(fit=events)


def evaluate(scene_path: Path, clip: str, device: str) -> tuple[list[float], float]:
    """PSNR of every frame the scene was fitted on, rendered at its camera and time."""
    import torch

    from tomgs.io.scene import load_scene
    from tomgs.io.video import read_video_for
    from tomgs.metrics import psnr
    from tomgs.render import rasterize

    began = time.perf_counter()
    dev = torch.device("cuda:0" if device == "cuda" else "cpu")
    scene = load_scene(scene_path, device=dev)
    frames = read_video_for(clip, scene.cameras)
    cams = scene.cameras
    viewmats, K = cams.viewmats(dev), torch.as_tensor(cams.K, dtype=torch.float32, device=dev)
    inputs = scene.model.render_inputs()
    out = []
    with torch.no_grad():
        for k in range(len(cams)):
            image = rasterize(**inputs, viewmat=viewmats[k], K=K, width=cams.width, height=cams.height,
                              t=float(cams.times[k]))[0]
            out.append(float(psnr(image, torch.as_tensor(frames[k], device=dev).float() / 255)))
    return out, time.perf_counter() - began


def summarize(work: Path, out: Path, args, count: int) -> dict:
    """Every case in WORK: the boundary split, the table, the goal's verdict."""
    import numpy as np

    from tomgs.train.multigpu.shards import plan_stretches

    stretches = plan_stretches(count, args.gpus)
    bounds = [s.own_lo for s in stretches[1:]]
    results = {}
    for path in sorted(work.glob("*/result.json")):
        r = json.loads(path.read_text())
        results[r["name"]] = r
        for csv in path.parent.glob("scene*.csv"):
            shutil.copy(csv, out / f"{r['name']}.{csv.name}")
    rows = []
    for name, r in results.items():
        offset = stretches[r["part"]].own_lo if r.get("part") is not None else 0  # a part's first frame
        psnr = np.asarray(r["frame_psnr"])
        positions = offset + np.arange(len(psnr))
        near = np.zeros(len(psnr), dtype=bool)
        per = []
        for b in bounds:
            close = np.abs(positions - (b - 0.5)) < args.near  # the frames within `near` of the cut
            near |= close
            per.append(round(float(psnr[close].mean()), 3) if close.any() else None)
        rows.append(dict(name=name, frames=len(psnr), psnr=r["psnr"], boundary=per, budget_left_s=r.get("budget_left_s"),
                         timeline=r.get("timeline"),
                         boundary_all=round(float(psnr[near].mean()), 3) if near.any() else None,
                         interior=round(float(psnr[~near].mean()), 3) if (~near).any() else None,
                         steps_per_s=r["steps_per_s"], iterations=r["iterations"], gaussians=r["gaussians"],
                         wall_s=r["wall_s"], phase_s=r["phase_s"], peak_gpu_gib=r["peak_gpu_gib"],
                         merged_before_refine=(r["shards"] or {}).get("merged_psnr_before_refine"),
                         refine_steps=(r["shards"] or {}).get("refine_steps"), refine_start=r.get("refine_start")))
    halves = [results[n] for n in results if results[n]["group"] == "halves"]
    reference = None
    if len(halves) == args.gpus:  # frame-weighted: the mean over the whole clip of the parts' frames
        reference = round(float(np.mean(np.concatenate([h["frame_psnr"] for h in halves]))), 3)
    sharded = results.get(f"full_{args.gpus}gpu")
    verdict = None
    if reference is not None and sharded is not None:
        gap = round(sharded["psnr"] - reference, 3)
        verdict = dict(reference_psnr=reference, sharded_psnr=sharded["psnr"], gap_db=gap, goal_met=gap >= -0.5)
    report = dict(clip=args.clip_path, frames=count, gpus=args.gpus, budget_s=args.budget, near=args.near,
                  boundaries=bounds, device=next(iter(results.values()))["device"] if results else None,
                  cases=rows, goal=verdict)
    write_report(out, "shards", "shards: N GPUs against one", args.env, markdown(report), dict(report, results=results))
    return report


def markdown(report: dict) -> str:
    lines = [f"# {report['gpus']} GPUs vs 1 for the same wall time ({report['budget_s']:.0f} s)", "",
             f"Clip: {report['clip']} ({report['frames']} frames); device: {report['device']}; boundaries at "
             f"{', '.join(map(str, report['boundaries']))}; boundary frames: within {report['near']} of one.", "",
             "| case | frames | PSNR | boundary PSNR (each) | boundary / interior | steps/s per rank | iterations | "
             "Gaussians | wall s | train s | merged before refine | refine steps |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in report["cases"]:
        each = ", ".join("-" if b is None else f"{b:.2f}" for b in r["boundary"])
        split = "-" if r["boundary_all"] is None else f"{r['boundary_all']:.2f} / {r['interior']:.2f}"
        rates = ", ".join(f"{s:.1f}" for s in r["steps_per_s"])
        before = "-" if r["merged_before_refine"] is None else f"{r['merged_before_refine']:.2f}"
        lines.append(f"| {r['name']} | {r['frames']} | {r['psnr']:.2f} | {each} | {split} | {rates} | "
                     f"{r['iterations']:,} | {r['gaussians']:,} | {r['wall_s']:.0f} "
                     f"| {r['phase_s'].get('train', 0):.0f} | {before} | "
                     f"{'-' if r['refine_steps'] is None else r['refine_steps']} |")
    lines += refine_markdown(report)
    lines += timeline_markdown(report)
    goal = report["goal"]
    if goal:
        lines += ["", f"Goal ({report['gpus']} GPUs fit {report['gpus']} times the frames to the same PSNR, within "
                      f"0.5 dB, in the same time): the parts alone {goal['reference_psnr']:.2f} dB, sharded "
                      f"{goal['sharded_psnr']:.2f} dB: {goal['gap_db']:+.2f} dB, "
                      f"{'met' if goal['goal_met'] else 'not met'}."]
    return "\n".join(lines) + "\n"


def refine_markdown(report: dict) -> list[str]:
    """The refinement's first rows per sharded case: its training PSNR (the ranks' mean, each row the
    mean of the steps since the last) against where phase 1 left it."""
    rows = [r for r in report["cases"] if r.get("refine_start") and r["refine_start"]["curve"]]
    if not rows:
        return []
    lines = ["", "Refinement start: training PSNR (ranks' mean) at the end of phase 1, the refinement's first "
                 "rows (step: dB), its lowest row, and the first row back at phase 1's level.", "",
             "| case | phase 1 end | first rows | lowest | back at step | last row |", "|---|---|---|---|---|---|"]
    for r in rows:
        s = r["refine_start"]
        first = ", ".join(f"{c[0]}: {c[2]:.2f}" for c in s["curve"][:6])
        low = s["lowest"]
        lines.append(f"| {r['name']} | {s['phase1_end_psnr']:.2f} | {first} | {low[0]}: {low[2]:.2f} | "
                     f"{'-' if s['back_at_step'] is None else s['back_at_step']} | "
                     f"{s['curve'][-1][0]}: {s['curve'][-1][2]:.2f} |")
    return lines


def timeline_markdown(report: dict) -> list[str]:
    """Each case's wall time phase by phase: every process's phases (the parent, each rank; a one-GPU
    fit's laid end to end), seconds since the command started, and where it ended against the budget."""
    lines = []
    for r in report["cases"]:
        if not r.get("timeline"):
            continue
        left = r.get("budget_left_s")
        lines += ["", f"### {r['name']}: timeline (s since the command started; budget {report['budget_s']:.0f} s"
                      + (f", returned {left:.1f} s before it)" if left is not None else ")"), "",
                  "| process | phase | start | end | s |", "|---|---|---|---|---|"]
        for process, events in sorted(r["timeline"].items(), key=lambda kv: (kv[0] != "parent", kv[0])):
            for e in events:
                lines.append(f"| {process} | {e['phase']} | {e['start']:.2f} | {e['end']:.2f} | "
                             f"{e['end'] - e['start']:.2f} |")
    return lines


def warm_up(args, work: Path) -> None:
    """Kernels compiled and loaded, NCCL started once, before any timed case."""
    clip = make_clip(work, 8, "64x36", args.device)
    for gpus in (None, args.gpus):
        folder = work / f"warmup_{gpus or 1}"
        command = [sys.executable, "-m", "tomgs.cli", "fit", str(clip), "-o", str(folder / "scene.ply"), "-y", "-q",
                   "--iterations", "20", "--device", args.device, "--poses", "identity"]
        folder.mkdir(parents=True, exist_ok=True)
        if gpus:
            command += ["--gpus", str(gpus)]
        began = time.perf_counter()
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        print(f"warm-up ({gpus or 1} GPU): {time.perf_counter() - began:.0f} s", flush=True)


def main(argv=None) -> dict | None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=None,
                    help="shards.json, shards.md and the CSV logs go here (default bench_out/shards)")
    ap.add_argument("--work", type=Path, default=None,
                    help="clip, scenes, per-case results (default bench_out/shards_work, bench_out/shards_tiny with "
                         "--tiny, <out>/work with --smoke)")
    ap.add_argument("--clip", default=None, help="a video or frame folder (default: the demo clip, made in --work)")
    ap.add_argument("--synthetic", default="600,854x480", help="frames,size of the demo clip")
    ap.add_argument("--frames", default=None, help="--frames of the clip (a source range)")
    ap.add_argument("--max-side", type=int, default=None)
    ap.add_argument("--gpus", type=int, default=2)
    ap.add_argument("--budget", type=float, default=120.0, help="every fit's --budget (whole command), seconds")
    ap.add_argument("--iterations", type=int, default=None,
                    help="iterations of every fit (default on a GPU 100,000: every fit ends at its budget, not at the "
                         "preset's 12,000, which a 300-frame 854x480 fit reaches in about two minutes)")
    ap.add_argument("--poses", default="auto")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--near", type=int, default=3, help="boundary frames: within this many frames of a boundary")
    ap.add_argument("--refine", type=float, action="append", default=[],
                    help="also the sharded fit with this refinement fraction (0: the union without refinement)")
    ap.add_argument("--overlap", type=int, action="append", default=[],
                    help="also the sharded fit with stretches reaching this many frames into their neighbours")
    ap.add_argument("--fresh-adam", action="store_true",
                    help="also the sharded fit with its refinement starting from a fresh Adam (full_Ngpu_fresh)")
    ap.add_argument("--log-interval", type=int, default=None,
                    help="steps between CSV rows of every fit (default: the preset's 50); the refinement's start, "
                         "row by row")
    ap.add_argument("--cases", default="halves,full_1gpu,full_Ngpu,variants",
                    help="which groups to run: halves, full_1gpu, full_Ngpu, variants")
    ap.add_argument("--redo", action="store_true", help="run cases whose result is already in --work")
    ap.add_argument("--no-warmup", dest="warmup", action="store_false")
    ap.add_argument("--tiny", action="store_true", help="on the CPU: 16 frames of 48x36, 2 gloo ranks, --budget 45")
    ap.add_argument("--smoke", action="store_true",
                    help="on the CPU: 8 frames of 32x18, the halves and the 2-rank fit, 8 iterations each")
    ap.add_argument("--run-case", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.run_case is not None:
        run_case(args.run_case)
        return None
    args.out = output_folder(args.out, args.smoke, "shards")
    if args.tiny or args.smoke:
        args.synthetic, args.device, args.budget, args.near = "16,48x36", "cpu", min(args.budget, 45.0), 2
        args.warmup = False
    if args.smoke:
        args.synthetic, args.iterations, args.cases, args.poses = "8,32x18", 8, "halves,full_Ngpu", "identity"
    args.work = args.work or (args.out / "work" if args.smoke else Path("bench_out/shards_tiny" if args.tiny else
                                                                         "bench_out/shards_work"))
    if args.iterations is None and args.device == "cuda":
        args.iterations = 100_000
    args.work.mkdir(parents=True, exist_ok=True)
    args.env = environment(args.device, "shards", argv)
    if args.clip is None:
        frames, size = args.synthetic.split(",")
        args.clip = str(make_clip(args.work, int(frames), size, args.device))
    args.clip_path = args.clip
    from tomgs.io.video import probe_clip

    count = probe_clip(args.clip, args.frames, args.max_side)[0]
    if args.warmup and args.device == "cuda":
        warm_up(args, args.work)
    wanted = set(args.cases.replace("full_Ngpu", f"full_{args.gpus}gpu").split(","))
    groups: dict[str, list[dict]] = {}
    for spec in cases(args, count):
        group = spec["group"]
        key = "variants" if "_r" in group or "_o" in group or group.endswith("_fresh") else group
        if key not in wanted:
            continue
        if not args.redo and (args.work / spec["name"] / "result.json").is_file():
            print(f"{spec['name']}: kept from {args.work}", flush=True)
            continue
        groups.setdefault(group, []).append(spec)
    for group, specs in groups.items():
        run_group(specs, args, Path(args.clip), args.work)
        report = summarize(args.work, args.out, args, count)  # after every group: a cut-off run keeps what it did
    report = summarize(args.work, args.out, args, count)
    if report["goal"]:
        print(json.dumps(report["goal"]))
    return report


if __name__ == "__main__":
    main()
