"""Run the README's quick start on the bundled clip and keep the frames its renders wrote as the
README's pictures (assets/example/*.png): `python assets/example/make.py` from a checkout, tomgs
installed (or PYTHONPATH=. and TOMGS="python -m tomgs.cli"). tests/test_readme.py runs the same
commands, each fit cut short."""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
README = HERE.parents[1] / "README.md"


def quick_start(text: str, fit_args: list[str] | None = None) -> list[list[str]]:
    """The `tomgs ...` lines of the README's quick start as argument lists (after `tomgs`), each
    `"$(tomgs example NAME)"` replaced by the bundled file's path; with `fit_args`, a fit's
    `--budget S` or `--preset P` by them (a short fit for a test)."""
    from tomgs.data import example_file

    section = text.split("## Quick start", 1)[1].split("\n## ", 1)[0]
    commands = []
    for line in section.splitlines():
        if not line.startswith("    tomgs "):
            continue
        line = re.sub(r'"\$\(tomgs example ([\w.]+)\)"', lambda m: shlex.quote(str(example_file(m.group(1)))), line)
        args = shlex.split(line.split(" #", 1)[0])[1:]
        if fit_args is not None and args[0] == "fit":
            for option in ("--budget", "--preset", "--iterations"):
                if option in args:
                    at = args.index(option)
                    del args[at:at + 2]
            args += fit_args
        commands.append(args)
    return commands


def main() -> None:
    tomgs = shlex.split(os.environ.get("TOMGS", "tomgs"))
    work = Path(tempfile.mkdtemp(prefix="tomgs-example-"))
    for args in quick_start(README.read_text()):
        print("$ tomgs", shlex.join(args), flush=True)
        subprocess.run([*tomgs, *args], cwd=work, check=True)
    for folder in sorted(p for p in work.iterdir() if p.is_dir()):
        for png in sorted(folder.glob("*.png")):
            shutil.copy(png, HERE / f"{folder.name}-{png.stem}.png")
    print(f"pictures in {HERE}; the run's files in {work}")


if __name__ == "__main__":
    sys.exit(main())
