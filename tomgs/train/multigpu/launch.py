"""How a sharded fit's processes start, are watched and stop: supervision (what each rank does:
tomgs.train.multigpu.rank; its plan: job.sharded_plan; its outputs: shards.check_shard_outputs).

Start: `fit(..., gpus=N)` (the CLI's --gpus N) checks the inputs and every output, hands the plan to
`on_plan`, and spawns N processes on this host (spawn, not fork: CUDA and Warp start clean in each),
one per GPU (cuda:0 .. cuda:N-1; NCCL between them) or, with device cpu, N CPU processes (gloo). The
CLI starts them before its own imports (tomgs.train.multigpu.pool) and the fit hands them their job
instead. Under torchrun (RANK, WORLD_SIZE and LOCAL_RANK in the environment, WORLD_SIZE > 1) every
process torchrun started is one rank and `fit` runs that rank: `torchrun --nnodes 2 --nproc_per_node 8
... -m tomgs.cli fit ...` fits on two hosts (each host's ranks write their checkpoints and CSVs on
that host, rank 0 the scene).

Faults: a rank that raises or dies stops the run. A spawned run's parent then sends SIGTERM to the
other ranks, which save a checkpoint at their next step boundary as an interrupted fit does
(tomgs.train.checkpoint.StopSignals), waits for them (SIGKILL after STOP_GRACE_S: a rank blocked in
a collective with a dead peer never reaches one), and raises ShardFailed naming the rank, its error
and every checkpoint kept; an InputError when the rank's error was one (a bad input that a rank
found: a corrupt frame in its stretch, a checkpoint of other options). torchrun's agent stops the
other ranks the same way (SIGTERM). SIGINT and SIGTERM to the parent go on to every rank (the ranks
leave the terminal's process group, so that one Ctrl-C is one signal to each), which save and stop;
the parent raises ShardsInterrupted (a FitInterrupted) naming the checkpoints. Every rank's last
checkpoint is kept; `resume=True` continues all of them (a rank killed before its first checkpoint
starts its stretch again).

Python callers: the spawned processes import the caller's main module again, so a script that calls
fit(..., gpus=N) keeps that call under `if __name__ == "__main__":`.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import torch

from tomgs.errors import InputError
from tomgs.train.checkpoint import FitInterrupted
from tomgs.train.clip import fit_options
from tomgs.train.config import TrainConfig
from tomgs.train.multigpu import pool as rank_pool
from tomgs.train.multigpu.group import run_rank
from tomgs.train.multigpu.job import Job, Timeline, sharded_plan
from tomgs.train.multigpu.shards import REFINE_FRACTION, check_shard_outputs
from tomgs.train.trainer import FitResult

STOP_GRACE_S = 120.0  # after SIGTERM, a rank's time to save before SIGKILL


class ShardFailed(RuntimeError):
    """A rank of a sharded fit failed: `rank`, its error (`error`), and the checkpoints kept
    (`checkpoints`: rank -> path of the ones on disk)."""

    def __init__(self, message: str, rank: int, error: str, checkpoints: dict[int, Path]):
        super().__init__(message)
        self.rank, self.error, self.checkpoints = rank, error, checkpoints


class ShardsInterrupted(FitInterrupted):
    """A sharded fit stopped by SIGINT or SIGTERM; `checkpoints`: rank -> checkpoint kept."""

    def __init__(self, checkpoints: dict[int, Path], signum: int, iterations: dict[int, int] | None = None):
        self.checkpoints = dict(checkpoints)
        self.iterations = dict(iterations or {})
        super().__init__(next(iter(self.checkpoints.values()), None), signum)

    def message(self) -> str:
        try:
            name = signal.Signals(self.signum).name
        except ValueError:
            name = f"signal {self.signum}"
        if not self.checkpoints:
            return f"interrupted ({name}) before the first checkpoint: nothing to resume; run the fit again"
        kept = ", ".join(f"{path}" + (f" (iteration {self.iterations[r]})" if r in self.iterations else "")
                         for r, path in sorted(self.checkpoints.items()))
        return f"interrupted ({name}): checkpoints {kept}; continue with --resume"


# -- the parent: checks, spawn, watch ----------------------------------------------------------------

def fit_shards(video, output, config, *, gpus=None, masks=None, frames=None, max_side=None, poses="auto",
               focal=None, device=None, resume=False, overwrite=False, progress=None, pose_progress=None,
               layer=None, mask_dilation=2, phases=None, on_plan=None, auto_budget=True, started=None,
               overlap: int | None = None, refine_fraction: float = REFINE_FRACTION, carry_adam: bool = True):
    """`tomgs.train.fit` in temporal shards (this module's docstring): the same arguments, with `gpus`
    ranks (None: torchrun's WORLD_SIZE), `overlap` frames into each neighbour (None: default) and
    `refine_fraction` of the training time for the joint refinement (0: none, the union as merged);
    `carry_adam=False` starts the refinement from a fresh Adam instead of each Gaussian's phase-1
    state (a comparison: docs/multi-gpu.md)."""
    entered = time.time()
    # as a one-GPU fit: the budget counts from the call unless told (the CLI: from the process's start)
    started = time.perf_counter() if started is None else started
    env = rank_pool.torchrun_env()
    if env is not None and gpus not in (None, env[1]):
        raise InputError(f"--gpus {gpus} under torchrun with WORLD_SIZE {env[1]}: leave --gpus out (torchrun's "
                         f"--nnodes x --nproc_per_node picks the ranks)")
    world = env[1] if env is not None else int(gpus)
    if world < 1:
        raise InputError(f"--gpus {gpus}: give 1 or more")
    if layer is not None:
        raise InputError(f"--layer {layer} with --gpus {world}: layers are fitted on one GPU (leave --gpus out)")
    if not 0.0 <= float(refine_fraction) < 1.0:
        raise InputError(f"refine_fraction {refine_fraction}: give a share of the training time in [0, 1)")
    device_type = _device_type(device, world, env)
    config = config or TrainConfig()
    options = fit_options(video, frames=frames, max_side=max_side, masks=masks, poses=poses, focal=focal)
    job = Job(video=video if not isinstance(video, (str, os.PathLike)) else str(video), output=str(output),
              config=config, world=world, device_type=device_type, options=options, masks=masks, frames=frames,
              max_side=max_side, poses=poses, focal=focal, resume=resume, overwrite=overwrite,
              auto_budget=auto_budget, start_time=time.time() - (time.perf_counter() - started), overlap=overlap,
              refine_fraction=float(refine_fraction), carry_adam=bool(carry_adam))
    if env is not None:  # torchrun: this process is one rank
        rank, _, local_rank, local_world = env
        check_shard_outputs(output, world, resume, overwrite, tidy=rank == 0)
        plan = sharded_plan(job)
        if on_plan is not None and rank == 0:
            on_plan(plan)
        phases = phases or (lambda *a: None)
        report = _local_report(rank, progress, phases, pose_progress)
        summary = run_rank(job, rank, local_rank, report, entered=entered, local_world=local_world)
        result = _result(summary, output, started, rank == 0)
        result.plan = plan
        result.timeline = summary.get("timelines")  # every rank's phases, to the scene written
        return result

    timeline = Timeline(job.start_time)  # the parent's phases; the ranks' come with their summaries
    timeline.add("start-up", job.start_time, entered)  # the process, Python, imports, the CLI
    paths = check_shard_outputs(output, world, resume, overwrite, tidy=True)
    plan = sharded_plan(job)
    if on_plan is not None:
        on_plan(plan)
    timeline.add("plan", entered)
    with tempfile.TemporaryDirectory(prefix="tomgs-ranks-") as folder:
        job.store = "file://" + str(Path(folder) / "store")
        summary = _spawn_and_watch(job, paths, progress, phases or (lambda *a: None), pose_progress, timeline)
    with timeline.span("read back"):
        result = _result(summary, output, started, True)
    result.plan = plan
    result.timeline = dict(summary.get("timeline") or {}, parent=timeline.events)
    return result


def _device_type(device, world: int, env) -> str:
    """"cuda" or "cpu" for a run of `world` ranks; InputError for a device it cannot use
    (tomgs.train.multigpu.pool.check_world, with the GPUs torch sees)."""
    gpus = torch.cuda.device_count() if torch.cuda.is_available() else 0
    return rank_pool.check_world(world, device, gpus, local=env[3] if env is not None else None)


def _spawn_and_watch(job: Job, paths: dict, progress, phases, pose_progress, timeline=None) -> dict:
    """Start the ranks, relay their progress, stop them all when one fails or a signal arrives, and
    return rank 0's summary (or raise ShardFailed, InputError, ShardsInterrupted). `timeline` (a
    Timeline) hears the spawn and the wait for the ranks; the summary's "timeline" is then every
    rank's own phases, each with its end seen from here ("exit": its report to its process gone)."""
    pool = rank_pool.take(job.world)  # ranks the caller started before its imports (tomgs.train.multigpu.pool)
    if pool is None:
        procs, report_pipes, writers = _new_ranks(job)
    else:
        procs, report_pipes, writers = pool.procs, pool.reports, []
    watch = _RankWatch(procs, report_pipes, progress, phases, pose_progress)
    with _signals_forwarded(watch.forward):
        try:
            spawning = time.time()
            _start_ranks(job, pool, procs, writers)
            if timeline is not None:
                timeline.add("spawn" if pool is None else "hand the job to the ranks", spawning)
            running = time.time()
            watch.until_all_gone()
            if timeline is not None:
                timeline.add("ranks", running)
        except BaseException:  # the parent's own failure (a callback's error): no rank outlives it
            watch.stop_all()
            raise
    summary = _verdict(job, paths, procs, watch.outcome, watch.died, watch.first_fault, watch.signals)
    if timeline is not None:  # each rank's own phases (its summary's), and its exit as seen from here
        summary = dict(summary, timeline=watch.rank_timelines(timeline.origin))
    return summary


def _new_ranks(job: Job) -> tuple[list, list, list]:
    """job.world rank processes, not started yet (spawn, not fork): (procs, the parent's reading ends of
    their report pipes, the writing ends, which the parent closes once the ranks have started)."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    pipes = [ctx.Pipe(duplex=False) for _ in range(job.world)]
    procs = [ctx.Process(target=rank_pool.run_spawned, args=(rank, job, pipes[rank][1]), name=f"tomgs-rank{rank}",
                         daemon=False)
             for rank in range(job.world)]
    return procs, [reader for reader, _ in pipes], [writer for _, writer in pipes]


def _start_ranks(job: Job, pool, procs: list, writers: list) -> None:
    """Start the new ranks `procs` (without a `pool`), or tell the pool's waiting ranks their rank and
    the job: they started and imported before the caller did."""
    if pool is None:
        for p in procs:
            p.start()
        for writer in writers:
            writer.close()  # the parent's copy: a rank's end of file is its own pipe closing
    else:  # started and imported already: each is told its rank and the job
        for rank, conn in enumerate(pool.jobs):
            conn.send((rank, job))
            conn.close()


@contextlib.contextmanager
def _signals_forwarded(forward):
    """SIGINT and SIGTERM to this process call `forward(signum, frame)` inside the block, and the caller's
    handlers come back after it. Only from the main thread (the only one that may set handlers), and a
    signal the caller ignores stays ignored."""
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            if signal.getsignal(sig) not in (signal.SIG_IGN, None):
                previous[sig] = signal.signal(sig, forward)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


class _RankWatch:
    """The parent's watch over a spawned run's ranks (procs, and the reading ends of their report
    pipes, one a rank): it relays rank 0's phases, pose progress and log rows to the callbacks, keeps
    each rank's outcome, and stops every rank (SIGTERM, then SIGKILL after STOP_GRACE_S) once one
    fails or dies, or a signal to this process asks it to."""

    def __init__(self, procs: list, report_pipes: list, progress, phases, pose_progress):
        self.procs, self.report_pipes = procs, report_pipes
        self.progress, self.phases, self.pose_progress = progress, phases, pose_progress
        self.readers = {conn: rank for rank, conn in enumerate(report_pipes)}  # the pipes not at their end yet
        self.outcome: dict[int, tuple[str, dict]] = {}  # rank -> (done | interrupted | failed, payload)
        self.died: dict[int, int] = {}  # rank -> exit code, for a rank that ended without a report
        self.first_fault: list[int] = []  # ranks in the order their fault was seen
        self.signals: list[int] = []  # the signals this process forwarded, in order
        self.stop_at: float | None = None  # time.monotonic() when the ranks were first asked to stop
        self.faulted = False  # whether they were asked because a rank failed or died
        self.reported: dict[int, float] = {}  # rank -> when its last report arrived (time.time())
        self.ended: dict[int, float] = {}  # rank -> when its process was seen gone

    def send(self, signum) -> None:
        """`signum` to every rank still alive."""
        for p in self.procs:
            if p.is_alive():
                try:
                    os.kill(p.pid, signum)
                except OSError:
                    pass

    def forward(self, signum, frame) -> None:
        """The parent's SIGINT / SIGTERM handler: every rank saves and stops."""
        self.signals.append(signum)
        self.stop_at = self.stop_at or time.monotonic()
        self.send(signum)

    def until_all_gone(self) -> None:
        """Relay reports and note exits until every rank has ended and every report pipe is read, asking
        the ranks to stop once one faults; then join them."""
        from multiprocessing.connection import wait

        while any(p.is_alive() for p in self.procs) or self.readers:
            ready = wait(list(self.readers) + [p.sentinel for p in self.procs if p.is_alive()], timeout=0.5)
            for conn in [c for c in ready if c in self.readers]:
                self._receive(conn)
            self._note_exits()
            if self.first_fault and not self.faulted:
                self.stop_at, self.faulted = self.stop_at or time.monotonic(), True
                self.send(signal.SIGTERM)
            if self.stop_at is not None and time.monotonic() - self.stop_at > STOP_GRACE_S:
                self.send(signal.SIGKILL)  # blocked in a collective with a dead peer: it keeps its last checkpoint
        for rank, p in enumerate(self.procs):
            p.join()
            self.ended.setdefault(rank, time.time())  # gone between the loop's last look and its end

    def _receive(self, conn) -> None:
        """One message from a rank's report pipe: its outcome, or rank 0's progress for the callbacks;
        the pipe's end (the rank gone) drops it from the readers."""
        rank = self.readers[conn]
        try:
            kind, payload = conn.recv()
        except (EOFError, OSError):
            del self.readers[conn]
            return
        if kind in ("done", "interrupted", "failed"):
            self.outcome[rank] = (kind, payload)
            self.reported[rank] = time.time()
            if kind == "failed":
                self.first_fault.append(rank)
        elif kind == "phase" and rank == 0:
            self.phases(*payload)
        elif kind == "poses" and rank == 0 and self.pose_progress is not None:
            self.pose_progress(*payload)
        elif kind == "row" and rank == 0 and self.progress is not None:
            try:
                self.progress(payload)
            except KeyboardInterrupt:  # the caller's Ctrl-C, as in a one-GPU fit
                self.forward(signal.SIGINT, None)

    def _note_exits(self) -> None:
        """When each rank was seen gone; a rank gone with no report and none left unread died (a fault)."""
        for rank, p in enumerate(self.procs):
            if rank not in self.ended and not p.is_alive():
                self.ended[rank] = time.time()
            if not p.is_alive() and p.exitcode is not None and rank not in self.outcome and rank not in self.died \
                    and not _pending(self.report_pipes[rank], self.readers):
                self.died[rank] = p.exitcode
                self.first_fault.append(rank)

    def stop_all(self) -> None:
        """The parent's own failure: SIGTERM to every rank, a wait of up to STOP_GRACE_S for each, then SIGKILL."""
        self.send(signal.SIGTERM)
        for p in self.procs:
            p.join(STOP_GRACE_S)
        self.send(signal.SIGKILL)

    def rank_timelines(self, origin: float) -> dict[str, list[dict]]:
        """{"rank<r>": events} for each rank with an outcome: its own phases (a finished rank's
        summary's), then its "exit" (its report to its process gone), in seconds from `origin`."""
        ranks = {}
        for rank, (kind, payload) in sorted(self.outcome.items()):
            events = list(payload.get("own_timeline") or []) if kind == "done" else []
            if rank in self.reported and rank in self.ended:
                events.append(dict(phase="exit", start=round(self.reported[rank] - origin, 3),
                                   end=round(max(self.ended[rank], self.reported[rank]) - origin, 3)))
            ranks[f"rank{rank}"] = events
        return ranks


def _pending(conn, readers) -> bool:
    """Whether a rank's pipe still holds unread messages (its report arrives after its exit)."""
    return conn in readers and conn.poll()


def _verdict(job: Job, paths: dict, procs, outcome, died, first_fault, signals) -> dict:
    kept = {r: p["checkpoint"] for r, p in enumerate(paths["ranks"]) if p["checkpoint"].is_file()}
    if not first_fault and all(outcome.get(r, ("",))[0] == "done" for r in range(job.world)):
        return outcome[0][1]
    if signals or not first_fault:  # stopped by a signal (a rank in a collective may fail instead of saving)
        iterations = {r: payload["iteration"] for r, (kind, payload) in outcome.items()
                      if kind == "interrupted" and payload.get("iteration") is not None}
        raise ShardsInterrupted(kept, signals[0] if signals else signal.SIGTERM, iterations)
    rank = first_fault[0]
    if rank in died:
        code = died[rank]
        names = {int(s): s.name for s in signal.Signals}
        error = f"was killed by {names[-code]}" if code < 0 and -code in names else f"exited with code {code}"
        error += f" (pid {procs[rank].pid})"
    else:
        payload = outcome[rank][1]
        inputs = [outcome[r][1]["message"] for r in first_fault
                  if r in outcome and outcome[r][0] == "failed" and outcome[r][1]["kind"] == "input"]
        if payload["kind"] == "input":
            message = payload["message"]
            raise InputError(message if all(m == message for m in inputs) else f"rank {rank}: {message}")
        error = f"failed: {payload['kind']}: {payload['message']}"
        if payload.get("traceback"):
            sys.stderr.write(f"rank {rank}'s traceback:\n{payload['traceback']}")
    others = []
    for r in range(job.world):
        if r == rank:
            continue
        kind, payload = outcome.get(r, ("", {}))
        if kind == "interrupted":
            at = f" at iteration {payload['iteration']}" if payload.get("iteration") is not None else ""
            others.append(f"rank {r} stopped{at}")
        elif r in died:
            others.append(f"rank {r} exited ({died[r]})")
        elif kind == "failed":
            others.append(f"rank {r} stopped ({payload['kind']})")
        elif kind == "done":
            others.append(f"rank {r} finished")
    keep = ", ".join(f"{path} (rank {r})" for r, path in sorted(kept.items())) or "none yet"
    message = (f"rank {rank} of {job.world} {error}; the run stopped"
               + (f" ({'; '.join(others)})" if others else "") + f". Checkpoints kept: {keep}"
               + ("; continue with --resume" if kept else "; run the fit again"))
    raise ShardFailed(message, rank, error, kept)


def _local_report(rank: int, progress, phases, pose_progress):
    """torchrun: rank 0 reports to this process's callbacks; the others stay quiet."""
    def report(kind, payload):
        if rank != 0:
            return
        if kind == "phase":
            phases(*payload)
        elif kind == "poses" and pose_progress is not None:
            pose_progress(*payload)
        elif kind == "row" and progress is not None:
            progress(payload)
    return report


def _result(summary: dict, output, started: float, leader: bool):
    """A FitResult from rank 0's summary; its model read back from the scene written."""
    from tomgs.io.scene import load_scene

    scene = load_scene(output) if leader else None
    result = FitResult(model=scene.model if scene else None, cameras=scene.cameras if scene else None,
                       clip_psnr=float(summary.get("clip_psnr", math.nan)),
                       iterations=int(summary.get("iterations", 0)),
                       seconds=float(summary.get("seconds", 0.0)), history=list(summary.get("history", [])),
                       notes=list(summary.get("notes", [])))
    result.phase_seconds = dict(summary.get("phase_seconds", {}))
    result.wall_seconds = time.perf_counter() - started
    result.peak_host_mb = float(summary.get("peak_host_mb", 0.0))
    result.peak_gpu_mb = summary.get("peak_gpu_mb")
    result.peak_host_mb_by_phase = dict(summary.get("peak_host_mb_by_phase", {}))
    result.shards = summary.get("shards")
    return result


__all__ = ["ShardFailed", "ShardsInterrupted", "fit_shards"]
