"""torch's CPU threads while tomgs works on the CPU.

    one_cpu_thread(device)   a context: torch's CPU ops in one thread while it runs on a CPU device

The work tomgs hands to torch on a CPU is many small ops (the tracker's bundle adjustment: a few
hundred unknowns; a training step's loss and bookkeeping around the Warp kernels, which run serially
anyway). Handing each op to a second thread costs more than it saves, and on a 2-core machine that
other work keeps busy the thread that waits for the other at every op is what the time goes to: at
load ~8, the bundled clip's poses took 45 s of wall time in two threads and 5.7 s in one, and 80
training steps 326 s against 158 s, with the same cameras and the same scene.
"""

from __future__ import annotations

import contextlib

import torch


@contextlib.contextmanager
def one_cpu_thread(device):
    """torch's CPU ops in one thread while the block runs, where `device` is a CPU (a GPU's work is
    left as it is); the thread count before it is restored after."""
    if torch.device(device).type != "cpu":
        yield
        return
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
