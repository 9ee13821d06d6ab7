"""Run benchmark jobs in parallel, one queue per GPU, each job's output in its own log.

    python benchmarks/parallel.py benchmarks/jobs/davis_caps.txt --out bench_out/caps

A job file has one job per line, `GPU | NAME | COMMAND` (blank lines and # comments skipped);
jobs of one GPU run one after another with CUDA_VISIBLE_DEVICES set, GPUs run side by side.
`{out}` in a command becomes the output folder. Prints each job's exit code and minutes.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import threading
import time
from collections import defaultdict
from pathlib import Path


def parse(path: Path) -> dict[str, list[tuple[str, str]]]:
    queues = defaultdict(list)
    for number, line in enumerate(path.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = [p.strip() for p in line.split("|", 2)]
        if len(parts) != 3 or not all(parts):
            raise SystemExit(f"{path}:{number}: expected 'GPU | NAME | COMMAND', got {line!r}")
        queues[parts[0]].append((parts[1], parts[2]))
    return queues


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("jobs", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    results = []

    def worker(gpu: str, jobs: list[tuple[str, str]]) -> None:
        env = {**os.environ, "CUDA_VISIBLE_DEVICES": gpu, "PYTHONUNBUFFERED": "1"}
        for name, command in jobs:
            start = time.perf_counter()
            with open(args.out / f"{name}.log", "w") as log:
                code = subprocess.call(command.replace("{out}", str(args.out)), shell=True, env=env,
                                       stdout=log, stderr=subprocess.STDOUT)
            results.append((gpu, name, code, (time.perf_counter() - start) / 60))
            print(f"gpu {gpu} {name}: exit {code} after {results[-1][3]:.1f} min", flush=True)

    threads = [threading.Thread(target=worker, args=item) for item in parse(args.jobs).items()]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    failed = [r for r in results if r[2] != 0]
    raise SystemExit(1 if failed else 0)


if __name__ == "__main__":
    main()
