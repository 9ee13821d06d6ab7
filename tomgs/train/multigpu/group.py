"""A rank's process: how it joins the run's process group, runs its ShardedPipeline
(tomgs.train.multigpu.rank) under the stop signals, leaves the group and reports to the parent
(tomgs.train.multigpu.launch), which spawned it or whose pool (tomgs.train.multigpu.pool) started it; or
one started by torchrun."""

from __future__ import annotations

import os
import sys
import time
import traceback
from datetime import timedelta

import torch

from tomgs.errors import InputError
from tomgs.train.checkpoint import FitInterrupted, StopSignals
from tomgs.train.multigpu.job import Job, Timeline, tomgs_start_epoch
from tomgs.train.multigpu.rank import ShardedPipeline
from tomgs.train.multigpu.shards import rank_paths

GROUP_TIMEOUT = timedelta(hours=1)  # a collective waits this long (rank 0's poses on a long clip come first)
PHASE_MESSAGES_PER_S = 5.0  # progress relayed from rank 0 to the parent at most this often


def spawned(rank: int, job: Job, conn, imported: float | None = None) -> None:
    """A spawned rank: run it, and report how it ended to the parent (`conn`). A rank of a
    tomgs.train.multigpu.pool passes `imported`: time.time() when its imports were done and it began waiting
    for the job."""
    received = time.time()
    if imported is None:  # spawned with its job (tomgs.train.multigpu.pool.run_spawned): its imports are done
        imported = received
    last = {"phase": 0.0}

    def report(kind, payload):
        if kind == "phase":  # throttled: a heartbeat, not a log
            now = time.monotonic()
            done, total = payload[1], payload[2]
            if done < total and now - last["phase"] < 1.0 / PHASE_MESSAGES_PER_S:
                return
            last["phase"] = now
        conn.send((kind, payload))

    try:
        summary = run_rank(job, rank, rank, report, entered=imported,
                           waited=(imported, received) if received > imported else None)
        conn.send(("done", summary))
        conn.close()
        # the run's outputs are written and closed, the group left: skip Python's finalisation, which
        # with torch, Warp and a GPU context loaded took 1-3 s of the budget (CPU, gloo) for nothing
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
    except FitInterrupted as e:
        conn.send(("interrupted", dict(checkpoint=None if e.checkpoint is None else str(e.checkpoint),
                                       signum=e.signum, iteration=e.iteration)))
    except InputError as e:
        conn.send(("failed", dict(kind="input", message=str(e))))
    except BaseException as e:  # noqa: BLE001 - every failure goes to the parent, which names it
        conn.send(("failed", dict(kind=type(e).__name__, message=str(e) or repr(e), traceback=traceback.format_exc())))
    finally:
        conn.close()


def init_group(job: Job, rank: int, device: torch.device):
    """Join the run's process group (NCCL on GPUs, gloo on CPUs); a gloo group for objects beside
    NCCL. Returns the group for objects."""
    import torch.distributed as dist

    backend = "nccl" if device.type == "cuda" else "gloo"
    kwargs = dict(backend=backend, init_method=job.store or "env://", rank=rank, world_size=job.world,
                  timeout=GROUP_TIMEOUT)
    if device.type == "cuda":
        torch.cuda.set_device(device)
        kwargs["device_id"] = device
    dist.init_process_group(**kwargs)
    return dist.new_group(backend="gloo", timeout=GROUP_TIMEOUT) if backend != "gloo" else None


def run_rank(job: Job, rank: int, local_rank: int, report, entered: float | None = None,
             waited: tuple[float, float] | None = None, local_world: int | None = None) -> dict:
    """What rank `rank` of `job` does (this module's docstring). `report(kind, payload)` hears
    ('started', {...}), ('phase', (name, done, total, text)), ('poses', (done, total)) and ('row', row)
    as they happen. `entered`: time.time() when the process's imports were done (its start-up ends
    there); `waited`: (from, to), a rank of a tomgs.train.multigpu.pool's wait for its job; `local_world`:
    the ranks on this host (None: all of them, as spawned). Returns its summary (rank 0's describes the
    run); "own_timeline" is its phases (Timeline)."""
    import torch.distributed as dist

    timeline = Timeline(job.start_time)
    entered = time.time() if entered is None else entered
    # /proc's process start has a clock tick's resolution (10 ms): a rank spawned just after the command
    # started can read as started before it, which no phase of the command can
    # a pool's rank (tomgs.train.multigpu.pool) may have started before a fit() call's clock: its phases begin at it
    entered = max(entered, job.start_time)
    timeline.add("start-up", max(job.start_time, min(tomgs_start_epoch(), entered)), entered)
    if waited is not None:
        timeline.add("wait for the job", max(waited[0], job.start_time), waited[1])
    device = torch.device(f"cuda:{local_rank}") if job.device_type == "cuda" else torch.device("cpu")
    if device.type == "cpu":
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // (local_world or job.world)))  # the ranks share the cores
    with timeline.span("join group"):  # from the first line: importing tomgs' modules, NCCL's start
        control = init_group(job, rank, device)
    checkpoint = rank_paths(job.output, job.world)[rank]["checkpoint"]
    # on an error the process group is left as it is: a collective with a dead peer may never return
    with StopSignals(immediate=True, checkpoint=lambda: checkpoint if checkpoint.is_file() else None):
        summary = ShardedPipeline(job, rank, device, control, report, timeline).run()
    with timeline.span("leave group"):
        dist.destroy_process_group()
    summary["own_timeline"] = timeline.events
    if "timelines" in summary:
        summary["timelines"][f"rank{rank}"] = timeline.events
    return summary


__all__ = ["init_group", "run_rank", "spawned"]
