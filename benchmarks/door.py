"""How soon does `tomgs` answer a mistake? Ten common ones, each run as a user runs it (`python -m tomgs.cli
...` in a fresh process, no GPU visible), timed from the process's start to its exit: the wall seconds, the
lines it printed, its exit code, and the heavy modules (numpy, torch, warp, av, cv2) it imported before it
answered (`-X importtime`, a separate run). The goal: each under 1 s, one line, exit 2, nothing heavy.
`python -c pass` is timed beside them: the interpreter's own start, for scale.

    python -m benchmarks.door [--repeats 5]
    python -m benchmarks.door --smoke          # one run of each
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

if __package__:
    from .common import ROOT, environment, markdown_table, output_folder, smoke_scene, write_report
else:  # run as a file
    from common import ROOT, environment, markdown_table, output_folder, smoke_scene, write_report

HEAVY = ("numpy", "torch", "warp", "av", "cv2")

# name -> the command's arguments; {clip} is the bundled ball.mp4 (40 frames of 160x96), scene.ply a scene of
# another clip (8 frames of 48x27), taken.ply a file the user has
MISTAKES = {
    "path typo": ["fit", "bal.mp4", "-o", "s.ply"],
    "wrong type": ["render", "{clip}", "-o", "out.mp4"],
    "missing -o": ["fit", "{clip}"],
    "existing output": ["fit", "{clip}", "-o", "taken.ply"],
    "bad range": ["fit", "{clip}", "-o", "s.ply", "--frames", "0:x"],
    "0-frame range": ["fit", "{clip}", "-o", "s.ply", "--frames", "40:50"],
    "wrong video for eval": ["eval", "scene.ply", "{clip}"],
    "cuda without a GPU": ["fit", "{clip}", "-o", "s.ply", "--device", "cuda"],
    "bad select": ["edit", "scene.ply", "-o", "e.ply", "--select", "box:1,2", "--remove"],
    "unknown extension": ["render", "scene.ply", "-o", "out.xyz"],
}


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (str(ROOT), os.environ.get("PYTHONPATH")))),
            "CUDA_VISIBLE_DEVICES": ""}  # no GPU visible, whatever the machine has


def timed(argv: list[str], cwd: Path) -> tuple[float, subprocess.CompletedProcess]:
    """(wall seconds from start to exit, the finished process) of `python argv`."""
    start = time.perf_counter()
    done = subprocess.run([sys.executable, *argv], cwd=cwd, env=_env(), capture_output=True, text=True, timeout=120)
    return time.perf_counter() - start, done


def heavy_imports(argv: list[str], cwd: Path) -> list[str]:
    """The heavy packages (HEAVY) that `python -X importtime argv` imported."""
    done = subprocess.run([sys.executable, "-X", "importtime", *argv], cwd=cwd, env=_env(), capture_output=True,
                          text=True, timeout=120)
    found = set()
    for line in done.stderr.splitlines():
        if line.startswith("import time:") and line.count("|") == 2:
            top = line.rsplit("|", 1)[1].strip().split(".")[0]
            if top in HEAVY:
                found.add(top)
    return sorted(found)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5, help="runs of each mistake (the median and the slowest)")
    parser.add_argument("--out", default=None)
    parser.add_argument("--smoke", action="store_true", help="one run of each")
    args = parser.parse_args(argv)
    repeats = 1 if args.smoke else args.repeats
    folder = output_folder(args.out, args.smoke, "door")
    env = environment("cpu", "door", argv)
    clip = str(ROOT / "tomgs" / "data" / "ball.mp4")
    with tempfile.TemporaryDirectory(prefix="tomgs-door-") as tmp:
        cwd = Path(tmp)
        smoke_scene(cwd / "scene.ply")
        (cwd / "taken.ply").write_bytes(b"the user's")
        python = [timed(["-c", "pass"], cwd)[0] for _ in range(repeats)]
        rows = []
        for name, args_ in MISTAKES.items():
            command = ["-m", "tomgs.cli", *(a.replace("{clip}", clip) for a in args_)]
            runs = [timed(command, cwd) for _ in range(repeats)]
            done = runs[-1][1]
            lines = [line for line in (done.stdout + done.stderr).splitlines() if line.strip()]
            seconds = [s for s, _ in runs]
            rows.append(dict(mistake=name, command="tomgs " + " ".join(args_), median_s=statistics.median(seconds),
                             max_s=max(seconds), lines=len(lines), exit=done.returncode,
                             said=lines[-1] if lines else "", heavy=heavy_imports(command, cwd)))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    body = (f"`python -c pass`: {statistics.median(python):.2f} s (median of {repeats}); load average "
            f"{load:.1f} at the end\n\n" if load is not None else "")
    body += markdown_table(["mistake", f"wall s (median of {repeats})", "slowest s", "lines", "exit",
                            "heavy imports", "what it said"],
                           [[r["mistake"], r["median_s"], r["max_s"], r["lines"], r["exit"],
                             ", ".join(r["heavy"]) or "none", r["said"][:90]] for r in rows])
    write_report(folder, "door", "Time to the first error: ten common mistakes", env, body,
                 dict(python_start_s=statistics.median(python), load=load, rows=rows))


if __name__ == "__main__":
    main()
