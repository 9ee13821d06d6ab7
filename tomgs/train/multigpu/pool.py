"""A sharded fit's rank processes, started before the parent's own imports.

A spawned rank begins with Python's and torch's imports (~3 s on the GPU hosts), and so does the
parent before it can check the inputs and plan the run: spawned only then (tomgs.train.multigpu.rank), every
rank's start-up came after the parent's, ~3 s of the budget that no rank trained in. A command that
knows it fits in shards (the CLI's `fit --gpus N`) calls `start(N)` first thing: its ranks import
tomgs.train.multigpu.rank while the parent imports and plans, then wait for their Job. The parent's
`take(N)` (tomgs.train.multigpu.rank, when it would spawn) hands them over; a pool nobody takes (the parent
refused its inputs, or failed) is sent away when the parent exits, and a rank whose parent dies
gets SIGTERM (Linux). This module imports nothing heavy: it runs before torch is imported.
"""

from __future__ import annotations

import atexit
import os
import signal
import sys
import time
from dataclasses import dataclass


@dataclass
class Pool:
    """N waiting ranks: `procs` (multiprocessing Processes), `jobs` (the parent's ends of the pipes each
    waits on: send it (rank, job), or None to send it away) and `reports` (the parent's ends of the pipes
    it reports on once it runs, as a rank spawned by tomgs.train.multigpu.rank does)."""

    procs: list
    jobs: list
    reports: list


_pool: Pool | None = None


def under_torchrun() -> bool:
    """torchrun started this process as one rank: there is no parent to start ranks."""
    return "RANK" in os.environ and "WORLD_SIZE" in os.environ


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


def _waiting(jobs, reports) -> None:
    """A waiting rank: import what a rank runs, then run the (rank, job) the parent sends (None, or the
    parent gone: leave without a word)."""
    leave_terminal()  # before the parent's Ctrl-C can reach an import half done
    from tomgs.train.multigpu import rank as ranks

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


__all__ = ["Pool", "dismiss", "leave_terminal", "start", "take", "under_torchrun"]
