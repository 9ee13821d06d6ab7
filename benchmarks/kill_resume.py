"""What a `kill -9` at a random moment costs a fit, and whether the resumed fit ends as well.

A fit of the bundled clip (or VIDEO) runs in a child process; at a seeded random moment (a uniform
fraction of the run's iterations, then a uniform fraction of the step after it: the machine's load
cannot move a kill past the end) it is killed with SIGKILL (nothing runs in it: no handler, no
save), then the fit is run again with resume=True and left to finish (from scratch when no
checkpoint exists yet). For each kill:

    kill_s       wall seconds after the launch of the killed process
    train_s_at_kill  training seconds of the killed run when it was killed
    reached      the iteration the killed run had completed (its log holds one row per iteration)
    saved        the iteration of the checkpoint the resume started from (0: none, started over)
    lost_it      reached - saved
    lost_s       training seconds between the two (the killed run's own clock)
    restart_s    seconds from the resume's launch to its first step (imports, decoding, set-up)
    psnr         the resumed fit's final full-clip PSNR, against an uninterrupted fit's

    python -m benchmarks.kill_resume [--video tomgs/data/ball.mp4] [--preset quick] [--kills 4] [--seed 0]
    python -m benchmarks.kill_resume --smoke     # a 6-frame synthetic clip, 12 iterations, one kill

Every fit (the uninterrupted reference, each killed fit and its resume) runs in a child process that
logs every iteration (log_interval=1) so the moment of the kill is known to the step, and measures the
full-clip PSNR at the end only; everything else is the preset's, checkpoint schedule included.
`--pythonpath DIR` runs the children on another copy of tomgs (e.g. an older commit, to compare
schedules). Writes kill_resume.md / .json.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

if __package__:
    from .common import ROOT, environment, markdown_table, output_folder, demo_video, write_report
else:  # run as a file (the children are): Python puts this folder first on sys.path
    from common import ROOT, environment, markdown_table, output_folder, demo_video, write_report

CLIP = ROOT / "tomgs" / "data" / "ball.mp4"  # the bundled clip


def child(args, launched: float) -> None:
    """One fit (or its resume) of args.video to args.output on the CPU, in this process: JSON lines on
    stdout, its first log row ({"event": "first_row", ...}) and its end ({"event": "done", ...});
    `launched`: perf_counter at the process's start."""
    from tomgs.train import fit, preset

    def say(event):
        print(json.dumps(event), flush=True)

    # a log row every step, and the full-clip PSNR only at the end (with a row per step, the preset's
    # evaluation every few seconds would take a share of the run that depends on the machine's load)
    config = preset(args.preset, log_interval=1, eval_interval_s=1e9,
                    **({"iterations": args.iterations} if args.iterations else {}))
    first = []

    def progress(row):
        if not first:
            first.append(row)
            say(dict(event="first_row", iteration=row["iteration"], wall_s=row["wall_s"],
                     since_launch=time.perf_counter() - launched))

    result = fit(args.video, args.output, config, resume=args.resume, poses=args.poses, device="cpu",
                 progress=progress, overwrite=not args.resume)
    say(dict(event="done", iterations=result.iterations, seconds=result.seconds, clip_psnr=result.clip_psnr,
             since_launch=time.perf_counter() - launched))


def launch(args, output: Path, resume: bool) -> subprocess.Popen:
    env = dict(os.environ)
    if args.pythonpath:
        env["PYTHONPATH"] = os.pathsep.join([args.pythonpath, env.get("PYTHONPATH", "")])
    cmd = [sys.executable, __file__, "--child", "--video", str(args.video), "--output", str(output), "--preset",
           args.preset, "--poses", args.poses]
    if args.iterations:
        cmd += ["--iterations", str(args.iterations)]
    if resume:
        cmd.append("--resume")
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def events(out: str) -> dict:
    found = {}
    for line in out.splitlines():
        if line.startswith("{"):
            event = json.loads(line)
            found[event["event"]] = event
    return found


def log_rows(path: Path) -> dict[int, float]:
    """iteration -> training seconds of a fit's CSV (a torn last line is skipped)."""
    rows = {}
    if path.exists():
        for row in csv.DictReader(path.read_text().splitlines()):
            try:
                rows[int(row["iteration"])] = float(row["wall_s"])
            except (TypeError, ValueError):
                pass
    return rows


def finish(args, output: Path, resume: bool) -> tuple[dict, float]:
    started = time.perf_counter()
    proc = launch(args, output, resume)
    out, err = proc.communicate()
    if proc.returncode != 0:
        raise SystemExit(f"fit failed ({proc.returncode}):\n{err[-3000:]}")
    return events(out), time.perf_counter() - started


def kill_at(args, output: Path, target: int, extra: float) -> dict:
    """Launch a fresh fit and SIGKILL it `extra` of a step after its log reaches iteration `target`."""
    log = output.with_suffix(".csv")
    launched = time.perf_counter()
    proc = launch(args, output, resume=False)
    while True:
        rows = log_rows(log)
        if rows and max(rows) >= target:
            break
        if proc.poll() is not None:
            raise SystemExit(f"the fit ended before iteration {target}:\n{proc.stderr.read()[-3000:]}")
        time.sleep(0.02)
    seen = time.perf_counter()  # the row was written at most one poll (20 ms) before
    at_seen = rows[max(rows)]
    step = at_seen - rows.get(max(rows) - 1, 0.0)
    time.sleep(extra * step)
    os.kill(proc.pid, signal.SIGKILL)
    killed = time.perf_counter()
    proc.communicate()
    rows = log_rows(log)  # a step may have finished in between
    return dict(kill_s=round(killed - launched, 1), reached=max(rows), rows=rows,
                train_s_at_kill=at_seen + (killed - seen))


def main(argv=None) -> list[dict]:
    launched = time.perf_counter()
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--video", type=Path, default=CLIP)
    ap.add_argument("--preset", default="quick")
    ap.add_argument("--iterations", type=int, default=None)
    ap.add_argument("--poses", default="auto")
    ap.add_argument("--kills", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--pythonpath", default=None, help="run the children on this copy of tomgs")
    ap.add_argument("--out", default=None, help="default bench_out/kill_resume")
    ap.add_argument("--smoke", action="store_true", help="a 6-frame synthetic clip at 48x28, 12 iterations, one kill")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--output", type=Path, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--resume", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return child(args, launched)
    out = output_folder(args.out, args.smoke, "kill_resume")
    if args.smoke:
        args.video = demo_video(out / "smoke.mp4")
        args.iterations, args.kills, args.poses = 12, 1, "identity"

    rng = random.Random(args.seed)
    work = Path(tempfile.mkdtemp(prefix="kill_resume.", dir=out))
    reference, reference_wall = finish(args, work / "reference.ply", resume=False)
    done = reference["done"]
    total = done["iterations"]
    print(f"reference: {total} iterations, {done['seconds']:.1f} s training, {reference_wall:.1f} s wall, "
          f"PSNR {done['clip_psnr']:.2f} dB", flush=True)
    # moments: a uniform fraction of the run (by iterations, so the machine's load cannot move a kill
    # past the end), then a uniform fraction of the step that follows
    moments = sorted((max(1, round(rng.uniform(0.05, 0.95) * total)), rng.random()) for _ in range(args.kills))

    results = []
    for k, (target, extra) in enumerate(moments):
        folder = work / f"kill{k}"
        folder.mkdir()
        output = folder / "scene.ply"
        killed = kill_at(args, output, target, extra)
        rows, reached = killed.pop("rows"), killed["reached"]
        has_checkpoint = output.with_suffix(".ckpt").exists()
        resumed, _ = finish(args, output, resume=has_checkpoint)
        first, end = resumed["first_row"], resumed["done"]
        saved = first["iteration"] - 1 if has_checkpoint else 0
        saved_s = rows.get(saved, 0.0) if saved else 0.0
        row = dict(kill_s=killed["kill_s"], train_s_at_kill=round(killed["train_s_at_kill"], 1), reached=reached,
                   saved=saved, lost_it=reached - saved, lost_s=round(killed["train_s_at_kill"] - saved_s, 1),
                   restart_s=round(first["since_launch"] - (first["wall_s"] - saved_s), 1),
                   psnr=round(end["clip_psnr"], 2), reference_psnr=round(done["clip_psnr"], 2),
                   stale_temporaries=sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp")))
        results.append(row)
        print(json.dumps(row), flush=True)

    lost = [r["lost_s"] for r in results]
    head = ["kill_s", "train_s_at_kill", "reached", "saved", "lost_it", "lost_s", "restart_s", "psnr",
            "reference_psnr"]
    body = (f"{args.video}, --preset {args.preset}, {total} iterations ({done['seconds']:.1f} s of training), seed "
            f"{args.seed}: {len(results)} kills, training seconds lost mean {sum(lost) / len(lost):.1f}, max "
            f"{max(lost):.1f}\n\n" + markdown_table(head, [[r[h] for h in head] for r in results]))
    write_report(out, "kill_resume", "kill_resume: what a kill -9 costs a fit", environment("cpu", "kill_resume", argv),
                 body, dict(reference=done, kills=results))
    return results


if __name__ == "__main__":
    main()
