"""The gate of a change meant to change no behaviour: a seeded CPU fit of set iterations, fingerprinted.

    python -m benchmarks.same_fit --out bench_out/same_fit/after
    PYTHONPATH=/path/to/old/checkout python benchmarks/same_fit.py --out bench_out/same_fit/before
    python -m benchmarks.same_fit --compare bench_out/same_fit/before bench_out/same_fit/after
    python -m benchmarks.same_fit --smoke                         # 30 iterations at 48 px, seconds

A fit of the bundled clip (tomgs.fit, as `tomgs fit` runs it) on the CPU, seeded, for --iterations
(a few densifications and quality rounds included), and its fingerprint: the SHA-256 of every parameter
array of the scene, the scene's header without what the clock or the checkout decides (seconds, the notes' timings, the
clip's path),
and the CSV's iterations, training PSNRs and Gaussians at its log interval, and the final clip PSNR. Two fingerprints are
the same fit when every field is equal; --compare names the fields that differ and exits 1.
The tomgs it measures is whichever Python imports: run with PYTHONPATH at an older checkout for "before".
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import re
import sys
import tempfile
from pathlib import Path

if __package__:
    from .common import environment, markdown_table, output_folder, write_report
else:  # run as a file (with an older checkout's tomgs): Python puts this folder first on sys.path
    from common import environment, markdown_table, output_folder, write_report

UNCOMPARED = ("train_seconds", "pose_seconds", "source")  # the header's fields that the clock or the checkout decides
SECONDS = re.compile(r"~?\d+(\.\d+)? ?(s|min)\b")  # a duration inside a note


def fingerprint(scene_path: Path, csv_path: Path) -> dict:
    """{'params': {name: sha256}, 'header': {...}, 'log': [[iteration, train_psnr, gaussians], ...],
    'clip_psnr': the final row's}."""
    import numpy as np

    from tomgs.io.scene import load_scene

    scene = load_scene(scene_path)
    params = {name: hashlib.sha256(np.ascontiguousarray(value.detach().cpu().numpy()).tobytes()).hexdigest()
              for name, value in scene.model.parameters_by_name().items()}
    header = {k: v for k, v in scene.info.items() if k not in UNCOMPARED}
    header["notes"] = [SECONDS.sub("<t>", str(note)) for note in header.get("notes", [])]
    with open(csv_path, newline="") as f:
        rows = list(csv.DictReader(f))
    every = int(header.get("config", {}).get("log_interval", 1))
    # the rows of the log's cadence and the last; a measurement's own row falls where the clock says
    log = [[row["iteration"], row["train_psnr"], row["gaussians"]] for i, row in enumerate(rows)
           if int(row["iteration"]) % every == 0 or i == len(rows) - 1]
    return dict(params=params, header=json.loads(json.dumps(header, default=str)), log=log,
                clip_psnr=rows[-1]["clip_psnr"] if rows else None)


def run_fit(iterations: int, max_side: int, seed: int, folder: Path) -> dict:
    """The seeded fit of the bundled clip in `folder`, fingerprinted."""
    import tomgs
    from tomgs.data import example_file
    from tomgs.train import preset

    config = preset("quick", iterations=iterations, seed=seed)
    scene = folder / "scene.ply"
    tomgs.fit(str(example_file("ball.mp4")), scene, config, max_side=max_side, device="cpu", auto_budget=False,
              overwrite=True)
    return fingerprint(scene, scene.with_suffix(".csv"))


def differences(before: dict, after: dict) -> list[str]:
    """The fields in which two fingerprints differ, by name."""
    out = [f"params.{k}" for k in sorted(set(before["params"]) | set(after["params"]))
           if before["params"].get(k) != after["params"].get(k)]
    out += [f"header.{k}" for k in sorted(set(before["header"]) | set(after["header"]))
            if k not in UNCOMPARED and before["header"].get(k) != after["header"].get(k)]
    if before["log"] != after["log"]:
        out.append("log")
    if before["clip_psnr"] != after["clip_psnr"]:
        out.append("clip_psnr")
    return out


def load(path: Path) -> dict:
    """The fingerprint in an --out folder (or its same_fit.json)."""
    path = path / "same_fit.json" if path.is_dir() else path
    return json.loads(path.read_text())["results"]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--iterations", type=int, default=240)
    parser.add_argument("--max-side", type=int, default=96)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, help="the folder for same_fit.md and same_fit.json")
    parser.add_argument("--compare", nargs=2, type=Path, metavar=("BEFORE", "AFTER"))
    parser.add_argument("--smoke", action="store_true", help="30 iterations at 48 px")
    args = parser.parse_args(argv)
    if args.compare:
        changed = differences(*(load(p) for p in args.compare))
        print("same fit" if not changed else "differs in: " + ", ".join(changed))
        return 1 if changed else 0
    if args.smoke:
        args.iterations, args.max_side = 30, 48
    with tempfile.TemporaryDirectory() as folder:
        result = run_fit(args.iterations, args.max_side, args.seed, Path(folder))
    rows = [[name, digest[:16]] for name, digest in result["params"].items()]
    body = (f"{len(result['log'])} log rows, final clip PSNR {result['clip_psnr']} dB, "
            f"{result['log'][-1][2] if result['log'] else 0} Gaussians\n\n" + markdown_table(["parameter", "sha256"], rows))
    write_report(output_folder(args.out, args.smoke, "same_fit"), "same_fit", "A seeded CPU fit, fingerprinted",
                 environment("cpu", "same_fit", argv), body, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
