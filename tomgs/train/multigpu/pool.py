"""A sharded fit's rank processes, started before the parent's own imports.

A spawned rank begins with Python's and torch's imports (~3 s on the GPU hosts), and so does the
parent before it can check the inputs and plan the run: spawned only then (tomgs.train.multigpu.launch), every
rank's start-up came after the parent's, ~3 s of the budget that no rank trained in. A command that
knows it fits in shards (the CLI's `fit --gpus N`) calls `start(N)` first thing: its ranks import
tomgs.train.multigpu.group while the parent imports and plans, then wait for their Job. The parent's
`take(N)` (tomgs.train.multigpu.launch, when it would spawn) hands them over; a pool nobody takes (the parent
refused its inputs, or failed) is sent away when the parent exits, and a rank whose parent dies
gets SIGTERM (Linux). It also says where a process stands (torchrun's environment, whether a fit runs
in shards, whether this process speaks for the run). This module imports nothing heavy: it runs before
torch is imported; so `check_world` refuses a count of ranks the host cannot run (more than its GPUs,
counted without torch by `visible_gpus`, or than its cores for CPU ranks) before `start` spawns any.
"""

from __future__ import annotations

import atexit
import os
import signal
import sys
import time
from dataclasses import dataclass

from tomgs.errors import InputError


@dataclass
class Pool:
    """N waiting ranks: `procs` (multiprocessing Processes), `jobs` (the parent's ends of the pipes each
    waits on: send it (rank, job), or None to send it away) and `reports` (the parent's ends of the pipes
    it reports on once it runs, as a rank spawned by tomgs.train.multigpu.launch does)."""

    procs: list
    jobs: list
    reports: list


_pool: Pool | None = None


def under_torchrun() -> bool:
    """torchrun started this process as one rank: there is no parent to start ranks."""
    return "RANK" in os.environ and "WORLD_SIZE" in os.environ


def visible_gpus() -> int | None:
    """NVIDIA GPUs this process may use, counted without importing torch (Linux: the driver's
    /proc/driver/nvidia/gpus, or /dev/nvidiaN, narrowed by CUDA_VISIBLE_DEVICES up to its first
    entry that is not a device, as CUDA reads it); 0 where no NVIDIA driver is loaded; None where
    that cannot be told (other systems)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        count = len(os.listdir("/proc/driver/nvidia/gpus"))
    except OSError:
        try:
            count = sum(1 for name in os.listdir("/dev") if name.startswith("nvidia") and name[6:].isdigit())
        except OSError:
            return None
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is None:
        return count
    listed = 0
    for entry in visible.split(","):
        entry = entry.strip()
        if not (entry.isdigit() and int(entry) < count) and not entry.startswith(("GPU-", "MIG-")):
            break
        listed += 1
    return min(listed, count)


def check_world(world: int, device, gpus: int | None, local: int | None = None, cores: int | None = None) -> str:
    """The device type, "cuda" or "cpu", of a fit in `world` ranks asked for `device` (None or "auto",
    "cpu", "cuda") on a host with `gpus` GPUs (None: not known, not checked) that runs `local` of the
    ranks (default all), each CPU rank on one of `cores` cores (None: not checked); else InputError
    saying what to give."""
    text = "auto" if device is None else str(device)
    local = world if local is None else local
    if text == "auto":
        if gpus == 0:  # N CPU processes are asked for by name, not fallen into
            raise InputError(f"--gpus {world}: torch sees no GPU here; give --device cpu to fit with {world} CPU "
                             f"processes")
        text = "cuda"
    if text.startswith("cuda:"):
        raise InputError(f"--device {text} with --gpus {world}: each rank takes its own GPU (cuda:0 .. cuda:"
                         f"{world - 1} on each host); give --device cuda")
    if text not in ("cuda", "cpu"):
        raise InputError(f"--device {text}: give cpu or cuda (a sharded fit puts one rank on each GPU)")
    if text == "cpu":
        if cores is not None and local > cores:
            raise InputError(f"--gpus {world} --device cpu: this machine has {cores} CPU "
                             f"core{'s' if cores != 1 else ''}; give --gpus {cores} or fewer")
        return text
    if gpus == 0:
        raise InputError(f"--device cuda: torch sees no GPU here; use --device cpu for {world} CPU processes")
    if gpus is not None and local > gpus:
        raise InputError(f"--gpus {world}: this host has {gpus} GPU{'s' if gpus != 1 else ''} "
                         f"(CUDA_VISIBLE_DEVICES={os.environ.get('CUDA_VISIBLE_DEVICES', 'unset')}); give --gpus "
                         f"{gpus} or fewer, or spread the ranks over hosts with torchrun")
    return text


def torchrun_env() -> tuple[int, int, int, int] | None:
    """(rank, world size, local rank, local world size) when torchrun (or any launcher that sets
    RANK, WORLD_SIZE and LOCAL_RANK) started this process with WORLD_SIZE > 1, else None."""
    try:
        rank, world, local = (int(os.environ[k]) for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK"))
    except (KeyError, ValueError):
        return None
    if world <= 1:
        return None
    return rank, world, local, int(os.environ.get("LOCAL_WORLD_SIZE", world))


def wants_shards(gpus: int | None) -> bool:
    """Whether a fit runs in temporal shards: --gpus above 1, or started by torchrun."""
    return (gpus is not None and gpus != 1) or torchrun_env() is not None


def is_leader() -> bool:
    """False in a torchrun rank other than 0 (that rank prints nothing: rank 0 speaks for the run)."""
    env = torchrun_env()
    return env is None or env[0] == 0


def start(world: int) -> None:
    """Start `world` waiting ranks (once per process; nothing for fewer than 2 or under torchrun)."""
    global _pool
    if _pool is not None or world < 2 or under_torchrun():
        return
    import multiprocessing as mp

    ctx = mp.get_context("spawn")  # not fork: CUDA and Warp start clean in each rank
    procs, jobs, reports = [], [], []
    for rank in range(world):
        job_reader, job_writer = ctx.Pipe(duplex=False)
        report_reader, report_writer = ctx.Pipe(duplex=False)
        proc = ctx.Process(target=_waiting, args=(job_reader, report_writer), name=f"tomgs-rank{rank}", daemon=False)
        proc.start()
        job_reader.close()  # the parent's copies of the rank's ends: its end of file is its own pipe closing
        report_writer.close()
        procs.append(proc)
        jobs.append(job_writer)
        reports.append(report_reader)
    _pool = Pool(procs, jobs, reports)
    atexit.register(dismiss)


def take(world: int) -> Pool | None:
    """The waiting ranks, for a run of `world` ranks, or None (none started, another count, or one of
    them already gone: sent away, and the caller spawns its own)."""
    global _pool
    pool, _pool = _pool, None
    if pool is None:
        return None
    if len(pool.procs) != world or not all(p.is_alive() for p in pool.procs):
        _send_away(pool)
        return None
    return pool


def dismiss() -> None:
    """Send away the waiting ranks nobody took (at exit)."""
    global _pool
    pool, _pool = _pool, None
    if pool is not None:
        _send_away(pool)


def _send_away(pool: Pool) -> None:
    for conn in pool.jobs:
        try:
            conn.send(None)
            conn.close()
        except OSError:  # already gone
            pass
    for proc in pool.procs:
        proc.join(5.0)
        if proc.is_alive():
            proc.terminate()
            proc.join(1.0)
    for conn in pool.reports:
        conn.close()


def leave_terminal() -> None:
    """A rank of a spawned run: out of the terminal's process group (the parent passes Ctrl-C on, once),
    and SIGTERM when the parent dies (Linux), so that no rank outlives its run."""
    try:
        os.setpgrp()
    except OSError:
        pass
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG
            if os.getppid() == 1:  # the parent died before prctl
                os.kill(os.getpid(), signal.SIGTERM)
        except OSError:
            pass


def run_spawned(rank: int, job, reports) -> None:
    """A rank spawned with its job (no pool): its imports, then out of the terminal's process group, then
    its run (tomgs.train.multigpu.group.spawned), reported on `reports`."""
    from tomgs.train.multigpu import group as ranks

    leave_terminal()
    ranks.spawned(rank, job, reports)


def _waiting(jobs, reports) -> None:
    """A waiting rank: import what a rank runs, then run the (rank, job) the parent sends (None, or the
    parent gone: leave without a word)."""
    leave_terminal()  # before the parent's Ctrl-C can reach an import half done
    from tomgs.train.multigpu import group as ranks

    imported = time.time()
    try:
        message = jobs.recv()
    except (EOFError, OSError):
        message = None
    jobs.close()
    if message is None:
        reports.close()
        os._exit(0)  # skip finalising torch, Warp: nothing was run
    rank, job = message
    ranks.spawned(rank, job, reports, imported=imported)


__all__ = ["Pool", "check_world", "dismiss", "is_leader", "leave_terminal", "run_spawned", "start", "take",
           "torchrun_env", "under_torchrun", "visible_gpus", "wants_shards"]
