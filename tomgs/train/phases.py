"""A fit's phases and what they cost: their names, the progress ticks of training, tomgs's start (a
budget counts a command's start-up too) and the peak memory."""

from __future__ import annotations

import torch

PHASES = ("read", "poses", "compile", "init", "train", "save")  # "compile": a first run's kernels, on a CPU


def tomgs_started() -> float:
    """The time.perf_counter() value at which tomgs was first imported in this process (tomgs.STARTED),
    so a command's budget counts its start-up too, and not what ran in the process before tomgs."""
    import tomgs

    return tomgs.STARTED


def phase_text(seconds: dict) -> str:
    """'read 1.2 s, poses 3.4 s, ...' in PHASES order."""
    return ", ".join(f"{name} {seconds[name]:.1f} s" for name in PHASES if name in seconds)


def peak_memory(device) -> tuple[float, float | None]:
    """(peak resident host memory of this process, peak GPU memory allocated by torch or None), MiB."""
    import resource

    host = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
    gpu = torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else None
    return host, gpu


def train_ticks(phases, budget):
    """The trainer's tick as the "train" phase: iterations done, or seconds under the Budget's time limit."""
    limit = budget.training_until

    def tick(iteration, seconds, text):
        text = text or f"iteration {iteration:,}"
        if limit > 0:
            phases("train", min(seconds, limit), limit, text)
        else:
            phases("train", iteration, budget.iterations, text)
    return tick
