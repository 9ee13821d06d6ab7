"""A fit's log: its rows' memory column, the CSV file (one row of tomgs.train.checkpoint.LOG_FIELDS per
logged step) and the plot of PSNR, Gaussians and scene bytes against run time."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
import torch

from tomgs.outputs import write_text
from tomgs.train.checkpoint import LOG_FIELDS


def log_memory_mb(device: torch.device) -> float:
    """The log's memory column: peak MiB allocated by torch on a GPU, peak resident host memory on a CPU."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux


def write_csv(path: Path, rows: list[dict]) -> None:
    """The log `rows` as CSV at `path`, replaced atomically (never written through a link)."""
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=LOG_FIELDS)
    writer.writeheader()
    writer.writerows(rows)
    write_text(path, out.getvalue())


def write_plot(path: Path, history: list[dict]) -> None:
    """The plot of a fit's log rows (`history`): PSNR against run time (training frames, evenly spaced clip
    frames, the full clip), and below it the Gaussians and the scene file's megabytes."""
    from tomgs.io.plots import line_plots_png

    train = [(r["wall_s"], r["train_psnr"]) for r in history if r["train_psnr"] != ""]
    clip = [r for r in history if r["clip_psnr"] != ""]
    every = max((int(r.get("clip_frames") or 0) for r in clip), default=0)  # the last covers every frame
    full = [(r["wall_s"], r["clip_psnr"]) for r in clip if int(r.get("clip_frames") or every) == every]
    part = [(r["wall_s"], r["clip_psnr"]) for r in clip if int(r.get("clip_frames") or every) < every]
    series = {}
    if train:
        series["training frames (running)"] = tuple(np.array(v, dtype=float) for v in zip(*train))
    if part:
        series["clip, evenly spaced frames"] = tuple(np.array(v, dtype=float) for v in zip(*part))
    if full:
        series["full clip"] = tuple(np.array(v, dtype=float) for v in zip(*full))
    if not series:
        return
    panels = [dict(series=series, xlabel="wall-clock seconds", ylabel="PSNR (dB)", title="PSNR against run time")]
    sized = [r for r in history if r.get("scene_bytes", "") != ""]
    if sized:
        seconds = np.array([float(r["wall_s"]) for r in sized])
        size = {"Gaussians (millions)": (seconds, np.array([int(r["gaussians"]) / 1e6 for r in sized])),
                "scene file (100 MB)": (seconds, np.array([int(r["scene_bytes"]) / 1e8 for r in sized]))}
        last = sized[-1]
        panels.append(dict(series=size, xlabel="wall-clock seconds", ylabel="size",
                           title=f"Size against run time: {int(last['gaussians']):,} Gaussians, "
                                 f"{int(last['scene_bytes']) / 1e6:.1f} MB at the end"))
    line_plots_png(path, panels)
