"""Do `fit`, `render`, `demo`, `export` and `edit` keep their promises when the disk fills up or a
SIGTERM arrives at a random moment? Nothing of the user's lost, no temporary left, one line said.

Each command writes into a folder that already holds the user's things: an unrelated file and the
output of an earlier run of the same command (replaced with -y only by a complete new one). Two
kinds of trial, `--trials` of each per command:

    disk full   the folder is a fresh tmpfs holding those things plus a random room of 0..1.2x what
                the command writes (so some trials fit, most fail at a random point of the write);
                needs root (mount -t tmpfs); skipped otherwise
    SIGTERM     the command runs in an ordinary folder and gets SIGTERM after a random share of the
                time an undisturbed run takes

After each: the user's file is byte for byte as it was, the earlier output too or replaced by a
complete new one (it loads: a fit can finish its scene and be stopped while it reports), no hidden
entry ('.NAME.*.tmp', a lock) is left, and a command that did not finish said why in one line on
stderr (-q: nothing else is printed), naming the file when the disk was full. The report lists the
distinct lines said (the trial's folder as DIR); its JSON keeps the whole stderr of every trial that
broke a promise.
A SIGTERM that lands outside the command's handlers ends the process silently: while Python is still
starting (nothing written yet), or after the command ended, while Python exits (seconds on a loaded
machine: its output is complete, its exit status 143). Counted apart, as "killed outside the command".

    python -m benchmarks.safety_trials [--trials 20] [--commands fit,render,demo,export,edit]
    python -m benchmarks.safety_trials --smoke        # render: one trial of each kind
"""

from __future__ import annotations

import argparse
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

if __package__:
    from .common import ROOT, demo_video, environment, markdown_table, output_folder, smoke_scene, write_report
else:  # run as a file
    from common import ROOT, demo_video, environment, markdown_table, output_folder, smoke_scene, write_report

COMMANDS = ("render", "demo", "export", "edit", "fit")
PAGE = 4096


def command_line(name: str, inputs: dict, out: Path) -> tuple[list[str], list[str]]:
    """(the tomgs arguments of a small run of `name` writing into `out`, the outputs it replaces)."""
    scene, clip = str(inputs["scene"]), str(inputs["clip"])
    return {
        "fit": (["fit", clip, "-o", f"{out}/s.ply", "--iterations", "20", "--poses", "identity", "--device", "cpu"],
                ["s.ply"]),
        "render": (["render", scene, "-o", f"{out}/r.mp4", "--device", "cpu"], ["r.mp4"]),
        "demo": (["demo", "-o", f"{out}/d.mp4", "--frames", "24", "--size", "128x72", "--device", "cpu"], ["d.mp4"]),
        "export": (["export", scene, "-o", f"{out}/x.ply", "--frame", "0"], ["x.ply"]),
        "edit": (["edit", scene, "-o", f"{out}/e.ply", "--translate", "0,0,0.1"], ["e.ply"]),
    }[name]


def run(args: list[str], cwd: Path, term_after: float | None = None) -> tuple[int, str, float]:
    """Run `tomgs <args> -q -y` (SIGTERM after `term_after` s): (exit status, stderr, seconds)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    began = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "tomgs.cli", *args, "-q", "-y"], cwd=cwd, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if term_after is not None:
        try:
            proc.wait(timeout=term_after)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=600)
    return proc.returncode, err, time.perf_counter() - began


def snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}


def complete(path: Path) -> bool:
    """Whether the output at `path` is whole: a scene loads, a video decodes to frames."""
    import tomgs

    try:
        if path.suffix == ".mp4":
            import av

            with av.open(str(path)) as container:
                return sum(1 for _ in container.decode(video=0)) > 0
        return len(tomgs.load_scene(path).model) > 0
    except Exception:  # noqa: BLE001 - anything that does not read is not whole
        return False


def verdict(before: dict, after_folder: Path, replaced: list[str], code: int, err: str) -> tuple[str, list[str]]:
    """(outcome, what broke a promise) of a trial: finished, stopped (one line), or killed outside the
    command (Python starting or exiting)."""
    broken = []
    after = snapshot(after_folder)
    hidden = [p.name for p in after_folder.iterdir() if p.name.startswith(".") and p.name != "lost+found"]
    if hidden:
        broken.append(f"left {hidden}")
    for name, data in before.items():
        if after.get(name) != data and not (name in replaced and name in after and complete(after_folder / name)):
            broken.append(f"{name} {'changed to something incomplete' if name in after else 'lost'}")
    lines = [line for line in err.splitlines() if line.strip()]
    if code == 0:
        outcome = "finished"
        if lines:
            broken.append(f"printed {lines!r}")
    elif code == -signal.SIGTERM and not lines:
        outcome = "killed outside the command"
    else:
        outcome = "stopped"
        if len(lines) != 1:
            broken.append(f"exit {code} with {len(lines)} lines: {lines[-3:]!r}")
        elif "No space left" in lines[0] and str(after_folder) not in lines[0]:
            broken.append(f"a full disk's line names no file: {lines[0]!r}")
    return outcome, broken


def pages(size: int) -> int:
    """Bytes a file of `size` bytes takes on a tmpfs: whole pages."""
    return -(-size // PAGE) * PAGE


def fill(folder: Path, user: dict[str, bytes]) -> None:
    for name, data in user.items():
        (folder / name).write_bytes(data)


def mount(folder: Path, size: int) -> bool:
    folder.mkdir(parents=True, exist_ok=True)
    return subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)],
                          capture_output=True).returncode == 0


def unmount(folder: Path) -> None:
    subprocess.run(["umount", str(folder)], capture_output=True)


def trials(name: str, inputs: dict, root: Path, count: int, rng: random.Random, disk: bool) -> dict:
    """`count` disk-full and `count` SIGTERM trials of command `name`."""
    reference = root / f"{name}-reference"
    reference.mkdir()
    args, replaced = command_line(name, inputs, reference)
    code, err, seconds = run(args, reference)
    assert code == 0, err
    written = sum(pages(p.stat().st_size) for p in reference.iterdir() if p.is_file())  # all it leaves
    user = {"notes.txt": rng.randbytes(2000), **{n: (reference / n).read_bytes() for n in replaced}}
    rows = dict(command=name, reference_s=round(seconds, 2), written_bytes=written, disk={}, sigterm={}, broken=[],
                lines=set(), stderr_of_broken=[])

    def record(kind, outcome, broken, err, folder):
        err = err.replace(str(folder), "DIR")  # the trial's folder: one line for every trial that said the same
        rows[kind][outcome] = rows[kind].get(outcome, 0) + 1
        rows["broken"] += [f"{kind}: {b}" for b in broken]
        if broken:
            rows["stderr_of_broken"].append(err)
        if outcome == "stopped":
            rows["lines"].add(err.strip().splitlines()[-1][:300])

    for k in range(count if disk else 0):
        folder = root / f"{name}-full-{k}"
        room = int(rng.uniform(0, 1.2) * written) // PAGE * PAGE  # whole pages, none at all included
        size = sum(pages(len(d)) for d in user.values()) + room
        if not mount(folder, size):
            rows["disk"] = "needs root"
            break
        try:
            fill(folder, user)
            before = snapshot(folder)
            args, _ = command_line(name, inputs, folder)
            code, err, _ = run(args, folder)
            outcome, broken = verdict(before, folder, replaced, code, err)
            record("disk", outcome, broken, err, folder)
        finally:
            unmount(folder)
    for k in range(count):
        folder = root / f"{name}-term-{k}"
        folder.mkdir()
        fill(folder, user)
        before = snapshot(folder)
        args, _ = command_line(name, inputs, folder)
        code, err, _ = run(args, folder, term_after=rng.uniform(0.0, 1.1) * seconds)
        outcome, broken = verdict(before, folder, replaced, code, err)
        for leftover in ("s.ckpt", "s.csv"):  # an interrupted fit's resume state and log: its own, expected
            (folder / leftover).unlink(missing_ok=True)
        record("sigterm", outcome, broken, err, folder)
        shutil.rmtree(folder)
    rows["lines"] = sorted(rows["lines"])
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=20)
    parser.add_argument("--commands", default=",".join(COMMANDS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None)
    parser.add_argument("--smoke", action="store_true", help="render only, one trial of each kind")
    args = parser.parse_args(argv)
    names = ["render"] if args.smoke else [c for c in args.commands.split(",") if c]
    count = 1 if args.smoke else args.trials
    folder = output_folder(args.out, args.smoke, "safety_trials")
    env = environment("cpu", "safety_trials", argv)
    disk = hasattr(os, "geteuid") and os.geteuid() == 0 and shutil.which("mount") is not None
    rng = random.Random(args.seed)
    with tempfile.TemporaryDirectory(prefix="tomgs-trials-") as tmp:
        root = Path(tmp)
        inputs = dict(scene=smoke_scene(root / "scene.ply", frames=24, width=128, height=72),
                      clip=demo_video(root / "clip.mp4", frames=6, width=48, height=28))
        results = [trials(name, inputs, root, count, rng, disk) for name in names]

    def cell(counts):
        return counts if isinstance(counts, str) else ", ".join(f"{v} {k}" for k, v in sorted(counts.items())) or "-"

    table = markdown_table(["command", "undisturbed run", "disk full (tmpfs)", "SIGTERM at a random moment",
                            "promises broken"],
                           [[r["command"], f"{r['reference_s']:.1f} s", cell(r["disk"]), cell(r["sigterm"]),
                             len(r["broken"])] for r in results])
    lines = "\n".join(f"- {r['command']}: `{line}`" for r in results for line in r["lines"])
    broken = "\n".join(f"- {r['command']} {b}" for r in results for b in r["broken"]) or "none"
    body = (f"{count} trials of each kind per command{'' if disk else '; disk-full trials skipped (not root)'}.\n\n"
            f"{table}\n\nWhat the stopped commands said (distinct lines):\n\n{lines or '-'}\n\n"
            f"Promises broken: {broken}\n")
    write_report(folder, "safety_trials", "Disk full and SIGTERM at random moments", env, body, results)


if __name__ == "__main__":
    main()
