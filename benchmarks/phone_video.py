"""Phone-sized videos end to end: `tomgs fit` with the built-in poses under a budget, its time, memory and
quality.

    python -m benchmarks.phone_video --clip ../shared/data/videos/bigbuckbunny.mp4 --budget 300 \
        --device cuda --out <out>
    python -m benchmarks.phone_video --smoke            # one 6-frame synthetic clip on the CPU, 10 iterations

Cases: every --clip as it is, and synthetic clips of the demo scene at --size with --synthetic frames
each (1920x1080 with 300, 900 and 1800 by default; rendered on --device once into --work and kept).
Each case runs `tomgs fit CLIP -o scene.ply --budget B --json ...` in its own process (peak
resident memory is per process) and records: the ETA its plan printed and the wall time the
command took, seconds per phase (read, poses, init, train, save), peak host (resident) and GPU
(torch allocated) memory, the uint8 size of the selected frames (the host budget is that plus
2 GB), the clip PSNR at 1, 2 and 5 minutes of the command's wall time (and the frames it covers:
evenly spaced ones before the fit's last measurement, "(N fr.)" in the table) and at the end,
Gaussians and iterations. Writes phone_video.md / .json.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from tomgs.io.video import probe_clip

if __package__:
    from .common import demo_video, environment, log_rows, output_folder, parse_size, psnr_at, write_report
else:  # run as a file: Python puts this folder first on sys.path
    from common import demo_video, environment, log_rows, output_folder, parse_size, psnr_at, write_report

MARKS = (60, 120, 300)  # seconds of the command's wall time at which the PSNR is reported


def tomgs(*args) -> list[str]:
    return [sys.executable, "-m", "tomgs.cli", *map(str, args)]


def make_synthetic(work: Path, frames: int, size: str, device: str) -> Path:
    """The demo scene's clip of `frames` frames at `size` (WxH), made once in `work`."""
    path = work / f"demo_{frames}_{size}.mp4"
    if not path.exists():
        began = time.perf_counter()
        demo_video(path, frames, *parse_size(size), device=device)
        print(f"made {path} in {time.perf_counter() - began:.0f} s", flush=True)
    return path


def run_sampled(command: list[str]) -> tuple[subprocess.CompletedProcess, dict]:
    """Run `command`, sampling its /proc status every 0.1 s: (the finished process, peak GiB of its
    anonymous memory (RssAnon: what it allocated) and of its file-backed pages (RssFile: mapped library
    code, e.g. the CUDA libraries, shared and reclaimable), and "series": [seconds, RssAnon GiB] every
    second, to place the peak in the fit's phases); empty where /proc is not there."""
    import tempfile
    import threading

    peaks, series = {}, []
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen(command, stdout=out, stderr=err, text=True)

        def sample():
            status = Path(f"/proc/{proc.pid}/status")
            began = time.perf_counter()
            while proc.poll() is None:
                try:
                    fields = dict(line.split(":", 1) for line in status.read_text().splitlines() if ":" in line)
                except OSError:
                    break
                for key in ("RssAnon", "RssFile"):
                    if key in fields:
                        gib = int(fields[key].split()[0]) / 2**20
                        peaks[key] = max(peaks.get(key, 0.0), gib)
                elapsed = time.perf_counter() - began
                if "RssAnon" in fields and (not series or elapsed >= series[-1][0] + 1.0):
                    series.append([round(elapsed, 1), round(int(fields["RssAnon"].split()[0]) / 2**20, 2)])
                time.sleep(0.1)

        watcher = threading.Thread(target=sample, daemon=True)
        watcher.start()
        proc.wait()
        watcher.join()
        out.seek(0)
        err.seek(0)
        done = subprocess.CompletedProcess(command, proc.returncode, out.read(), err.read())
    return done, dict({k: round(v, 2) for k, v in peaks.items()}, series=series)


def run_case(name: str, clip: Path, args, work: Path) -> dict:
    frames, height, width, _ = probe_clip(clip, args.frames, args.max_side)
    out = work / name
    out.mkdir(parents=True, exist_ok=True)
    scene, report = out / "scene.ply", out / "fit.json"
    command = tomgs("fit", clip, "-o", scene, "--budget", args.budget, "--device", args.device, "--json", report, "-y")
    if args.frames:
        command += ["--frames", args.frames]
    if args.max_side:
        command += ["--max-side", str(args.max_side)]
    if args.iterations:
        command += ["--iterations", str(args.iterations)]
    print(f"{name}: {frames} frames of {width}x{height}: {' '.join(command[3:])}", flush=True)
    began = time.perf_counter()
    done, peaks = run_sampled(command)
    wall = time.perf_counter() - began
    plan = next((line for line in done.stderr.splitlines() if line.startswith("plan:")), "")
    if done.returncode != 0:
        print(done.stderr[-2000:], file=sys.stderr)
        return dict(case=name, clip=str(clip), error=done.stderr.strip().splitlines()[-1:], wall_s=wall)
    fit = json.loads(report.read_text())
    rows = log_rows(fit["csv"])
    phases = fit["phase_seconds"]
    before = sum(phases.get(k, 0.0) for k in ("read", "poses", "init")) + (fit["wall_seconds"] - sum(phases.values()))
    marks = {m: psnr_at(rows, m, before) if m <= fit["wall_seconds"] + 5 else (None, None) for m in MARKS}
    return dict(case=name, clip=str(clip), frames=frames, width=width, height=height, budget_s=args.budget,
                plan=plan, eta_s=round(fit["eta_seconds"], 1), wall_s=round(wall, 1),
                fit_wall_s=round(fit["wall_seconds"], 1), phases_s={k: round(v, 1) for k, v in phases.items()},
                peak_host_gib=round(fit["peak_host_mb"] / 1024, 2),
                peak_host_gib_by_phase={k: round(v / 1024, 2) for k, v in fit.get("peak_host_mb_by_phase", {}).items()},
                peak_anon_gib=peaks.get("RssAnon"), peak_file_gib=peaks.get("RssFile"), anon_gib_series=peaks.get("series"),
                peak_gpu_gib=None if fit["peak_gpu_mb"] is None else round(fit["peak_gpu_mb"] / 1024, 2),
                frames_gib=round(frames * height * width * 3 / 2**30, 2),
                psnr_at={f"{m // 60}min": marks[m][0] for m in MARKS},  # None: none measured, or ended before
                psnr_frames_at={f"{m // 60}min": marks[m][1] for m in MARKS},  # frames each covers
                psnr_end=round(fit["clip_psnr"], 2),
                gaussians=fit["gaussians"], iterations=fit["iterations"])


def table(results: list[dict]) -> str:
    head = ("| case | frames | size | ETA s | wall s | read | poses | init | train | save | host GiB (frames) "
            "| anon / file GiB | GPU GiB | PSNR 1/2/5 min | end | Gaussians | iterations |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in results:
        if "error" in r:
            lines.append(f"| {r['case']} | error: {' '.join(r['error'])} |")
            continue
        p = r["phases_s"]
        covers = r.get("psnr_frames_at", {})
        at = "/".join("-" if v is None else f"{v:.2f}" + (f" ({covers[m]} fr.)" if covers.get(m) not in (None, r["frames"])
                                                         else "") for m, v in r["psnr_at"].items())
        gpu = "-" if r["peak_gpu_gib"] is None else f"{r['peak_gpu_gib']:.2f}"
        lines.append(f"| {r['case']} | {r['frames']} | {r['width']}x{r['height']} | {r['eta_s']:.0f} | {r['wall_s']:.0f} "
                     f"| {p.get('read', 0):.1f} | {p.get('poses', 0):.1f} | {p.get('init', 0):.1f} "
                     f"| {p.get('train', 0):.1f} | {p.get('save', 0):.1f} | {r['peak_host_gib']:.2f} "
                     f"({r['frames_gib']:.2f}) | {r.get('peak_anon_gib') or '-'} / {r.get('peak_file_gib') or '-'} | {gpu} | {at} | {r['psnr_end']:.2f} | {r['gaussians']:,} "
                     f"| {r['iterations']:,} |")
    return "\n".join(lines)


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clip", action="append", default=[], help="a video to fit as it is (repeatable)")
    ap.add_argument("--synthetic", default="300,900,1800", help="frame counts of the synthetic clips ('' for none)")
    ap.add_argument("--size", default="1920x1080", help="size of the synthetic clips")
    ap.add_argument("--budget", type=float, default=300.0, help="each fit's --budget (the whole command), seconds")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--frames", default=None, help="--frames for every fit")
    ap.add_argument("--max-side", type=int, default=None, help="--max-side for every fit")
    ap.add_argument("--iterations", type=int, default=None, help="--iterations for every fit (default: the preset's)")
    ap.add_argument("--work", type=Path, default=None, help="clips and scenes go here (default: <out>/work)")
    ap.add_argument("--out", type=Path, default=None, help="default bench_out/phone_video")
    ap.add_argument("--smoke", action="store_true",
                    help="one synthetic clip of 6 frames at 48x28 on the CPU, 10 iterations")
    args = ap.parse_args(argv)
    out = output_folder(args.out, args.smoke, "phone_video")
    if args.smoke:
        args.synthetic, args.size, args.device, args.iterations = "6", "48x28", "cpu", 10
    args.work = args.work or out / "work"
    args.work.mkdir(parents=True, exist_ok=True)
    cases = [(Path(c).stem, Path(c)) for c in args.clip]
    for n in filter(None, args.synthetic.split(",")):
        cases.append((f"synthetic_{n}_{args.size}", make_synthetic(args.work, int(n), args.size, args.device)))
    results = []
    for name, clip in cases:
        results.append(run_case(name, clip, args, args.work))
        (out / "phone_video.partial.json").write_text(json.dumps(results, indent=1))  # a cut-off run keeps what it did
    write_report(out, "phone_video", "phone_video: phone-sized videos end to end",
                 environment(args.device, "phone_video", argv), table(results), results)
    (out / "phone_video.partial.json").unlink()
    return results


if __name__ == "__main__":
    main()
