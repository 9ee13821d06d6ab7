"""A fit's one-off start-up costs, paid in a thread beside the camera estimate.

The first training steps of a process pay once for what has nothing to do with the clip: Warp's
start, its kernels loaded onto the device (compiled, on the first run of a machine), cuBLAS and
cuDNN handles, the caching allocator's first blocks. On a GPU that is seconds (the H100: a DAVIS
fit's first 50 steps took 8.6 s against 0.35 s for the next 50). `WarmUp` runs a throwaway Trainer
on a tiny made-up clip in a thread meanwhile; the fit joins it before its own Trainer. Used by
`tomgs.train.pipeline` (one GPU) and by every rank of `tomgs.train.multigpu.rank`.

It was made for poses on the CPU, when the GPU idled through them; the tracker now runs on the GPU
too, beside it. What made the two contend was torch.optim.Optimizer's first add_param_group, which
imports torch._dynamo (1.5-5 s of Python holding the interpreter lock against the tracker's):
SeenAdam no longer goes through it (tomgs/train/optim.py). With that, kite-surf's poses took 2.8-3.3
s beside the thread (6.5-7.0 s before) and a 1-minute fit started training 3.5-4.0 s in (7.2-8.2 s
before; H100, docs/notes/training.md). Without the thread a Trainer's construction and first steps
took 5.2-6.4 s (then with the import).
"""

from __future__ import annotations

import sys
import threading
import time

import numpy as np
import torch

FRAMES, SIZE, STEPS = 4, (32, 24), 3  # the made-up clip: frames, (width, height), training steps


def pays_on(device: torch.device) -> bool:
    """Whether a warm-up beside the poses saves time on `device`: on a GPU (which idles through the
    poses). Not on a CPU, where its kernels would take cores from the poses themselves."""
    return device.type == "cuda"


def warm_up(config, device: torch.device) -> None:
    """A throwaway Trainer on a tiny made-up clip on `device`: a few steps, a clip measurement and a
    frame_psnr. Changes no result: it draws only from its own generators under a forked torch RNG,
    and a fit seeds torch again before its own Trainer. A failure is reported and left to the real
    steps to show."""
    from tomgs.cameras import Cameras
    from tomgs.metrics import frame_psnr
    from tomgs.train.trainer import Trainer

    try:
        if device.type == "cuda" and device.index is not None:
            torch.cuda.set_device(device)  # a thread's own: no context on another GPU
        width, height = SIZE
        c2w = np.tile(np.eye(4), (FRAMES, 1, 1))
        c2w[:, 0, 3] = np.linspace(-0.1, 0.1, FRAMES)
        K = np.array([[40.0, 0, width / 2], [0, 40.0, height / 2], [0, 0, 1]])
        cameras = Cameras(c2w, K, width, height, np.linspace(0, 1, FRAMES), np.arange(FRAMES))
        g = np.random.default_rng(0)
        frames = g.integers(0, 256, (FRAMES, height, width, 3), dtype=np.uint8)
        points = g.normal(0, 0.5, (64, 3)) + np.array([0.0, 0.0, 3.0])
        colors = g.random((64, 3)).astype(np.float32)
        with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
            trainer = Trainer(frames, cameras, points, colors, config.replace(iterations=STEPS, max_seconds=0.0),
                              device)
            for _ in range(STEPS):
                trainer.step()
            trainer.clip_psnr()
            frame_psnr(trainer.model, trainer.frames, cameras, device)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
    except Exception as e:  # noqa: BLE001 - a warm-up, not the fit
        sys.stderr.write(f"warm-up skipped: {type(e).__name__}: {e}\n")


class WarmUp:
    """`warm_up(config, device)` in a daemon thread from construction; `join()` waits for it and
    returns the seconds waited (0.0 once joined, or when it had ended)."""

    def __init__(self, config, device: torch.device):
        self.began = time.time()
        self.ended: float | None = None
        self._thread = threading.Thread(target=self._run, args=(config, device), name="tomgs-warm-up", daemon=True)
        self._thread.start()

    def _run(self, config, device) -> None:
        warm_up(config, device)
        self.ended = time.time()

    def join(self) -> float:
        waiting = time.perf_counter()
        self._thread.join()
        return time.perf_counter() - waiting
