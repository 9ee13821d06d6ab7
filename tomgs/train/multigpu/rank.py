"""What one rank of a sharded fit does (tomgs.train.multigpu.shards; how the ranks start and stop:
tomgs.train.multigpu.launch).

Each rank, in order: joins the process group; rank 0 reads the clip and estimates the cameras (or
takes them from a checkpoint) and broadcasts them, the others meanwhile read their stretch and warm
up (tomgs.train.warm, in a thread); every rank checks its checkpoint on resume, and all refuse
together when one refuses (before anything is written); phase 1 (its Trainer); the merge, the joint
refinement and the measurement of its frames (tomgs.train.multigpu.shards), the refinement ending by
what follows it as measured (Rank.merge); rank 0 writes the scene, the merged CSV and plot; every
rank removes its checkpoint and, spawned, leaves by os._exit. Each process records its phases
(Timeline; FitResult.timeline).

A rank reuses the one-process fit's pieces: the options and the clip's identity a checkpoint records
and the checks a resume makes (tomgs.train.clip), the outputs' paths (tomgs.outputs), the phases' ticks
and memory (tomgs.train.phases), the plan (tomgs.train.plan) and the Trainer with its log and plot.
"""

from __future__ import annotations

import os
import sys
import time
import traceback
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

from tomgs.cameras import Cameras
from tomgs.errors import InputError
from tomgs.io import Video, read_video
from tomgs.io.video import parse_frames, probe_clip, read_video_for
from tomgs.train.checkpoint import START_OVER, FitInterrupted, StopSignals, read_checkpoint
from tomgs.train.clip import check_clip, check_options, clip_fps, clip_identity
from tomgs.metrics import frame_psnr
from tomgs.train.multigpu.shards import (REFINE_FRACTION, assemble, boundary_psnr, default_overlap, gather_union,
                                         halo, local_cameras, log_row, merged_history, model_of, plan_stretches,
                                         rank_paths, refine, stretch_points)
from tomgs.outputs import fit_output_paths
from tomgs.train.phases import peak_memory, tomgs_started, train_ticks
from tomgs.train.plan import SAVE_COST, make_plan, render_seconds
from tomgs.train.log import write_csv, write_plot
from tomgs.train.clip import frame_store
from tomgs.train.trainer import Trainer
from tomgs.train.warm import WarmUp

GROUP_TIMEOUT = timedelta(hours=1)  # a collective waits this long (rank 0's poses on a long clip come first)
PHASE_MESSAGES_PER_S = 5.0  # progress relayed from rank 0 to the parent at most this often
# after the refinement's last step, beside what the ranks measure (the final measurement, the gather,
# the scene's write and read back): the ranks leaving the group and exiting (os._exit: ~0.02 s), the
# parent joining them, the logs gathered (CPU, gloo, 2 ranks: 0.05-0.1 s in all)
EXIT_S = 0.5
SAMPLE_IO_SHARE = 1 / 16  # rank 0 times the scene's write and read back on this share of the union
MIN_SAMPLE_IO = 20_000  # ... and on at least this many Gaussians


# -- when each phase ran -----------------------------------------------------------------------------

class Timeline:
    """A process's phases as {phase, start, end}: seconds since the command started (`origin`, a
    time.time() value: Job.start_time), so that every rank's and the parent's line up."""

    def __init__(self, origin: float):
        self.origin, self.events = float(origin), []

    def add(self, phase: str, start: float, end: float | None = None) -> None:
        """A phase from `start` to `end` (time.time() values; end: now)."""
        end = time.time() if end is None else end
        self.events.append(dict(phase=phase, start=round(start - self.origin, 3), end=round(end - self.origin, 3)))

    def span(self, phase: str):
        """Context: the phase from entering to leaving."""
        import contextlib

        @contextlib.contextmanager
        def timed():
            began = time.time()
            try:
                yield
            finally:
                self.add(phase, began)
        return timed()


def tomgs_start_epoch() -> float:
    """time.time() at which tomgs started in this process (tomgs.train.phases.tomgs_started)."""
    return time.time() - (time.perf_counter() - tomgs_started())


@dataclass
class Job:
    """Everything a rank needs (pickled to spawned ranks)."""

    video: object  # a path (str) or a tomgs.io.Video
    output: str
    config: object  # TrainConfig
    world: int
    device_type: str  # "cuda" or "cpu"
    options: dict  # what a checkpoint records of the options (tomgs.train.clip.fit_options)
    masks: object = None
    frames: object = None
    max_side: int | None = None
    poses: object = "auto"
    focal: float | None = None
    resume: bool = False
    overwrite: bool = False
    auto_budget: bool = True
    start_time: float = 0.0  # time.time() when the command started: the budget counts from it
    overlap: int | None = None  # None: default_overlap
    refine_fraction: float = REFINE_FRACTION
    carry_adam: bool = True  # the refinement goes on from each row's phase-1 Adam state (False: a fresh Adam)
    store: str | None = None  # init_method of a spawned run (a file:// store); None: env:// (torchrun)


def rank_plan(config, frames: int, height: int, width: int, source: int, device_type: str, auto_budget: bool,
              free=None):
    """(FitPlan, config) of one rank's stretch of `frames` frames (tomgs.train.plan.make_plan; its cameras
    come from rank 0, so none are estimated in its time)."""
    return make_plan(config, frames, height, width, source, device_type, poses_estimated=False,
                     auto_budget=auto_budget, free_bytes=free)


# -- one rank ---------------------------------------------------------------------------------------

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


def _init_group(job: Job, rank: int, device: torch.device):
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
        control = _init_group(job, rank, device)
    checkpoint = rank_paths(job.output, job.world)[rank]["checkpoint"]
    # on an error the process group is left as it is: a collective with a dead peer may never return
    with StopSignals(immediate=True, checkpoint=lambda: checkpoint if checkpoint.is_file() else None):
        summary = Rank(job, rank, device, control, report, timeline).run()
    with timeline.span("leave group"):
        dist.destroy_process_group()
    summary["own_timeline"] = timeline.events
    if "timelines" in summary:
        summary["timelines"][f"rank{rank}"] = timeline.events
    return summary


class Rank:
    """One rank's run, step by step (this module's docstring): `start` (cameras, frames, checks),
    `phase1` (its Trainer), `merge` (the union and its joint refinement), `finish` (the outputs)."""

    def __init__(self, job: Job, rank: int, device: torch.device, control, report, timeline: Timeline | None = None):
        self.job, self.rank, self.device, self.control, self.report = job, rank, device, control, report
        self.timeline = timeline or Timeline(job.start_time)
        self.world = job.world
        self.paths = rank_paths(job.output, job.world)[rank]
        self.outputs = fit_output_paths(job.output)
        self.seconds: dict[str, float] = {}
        self.peaks: dict[str, float] = {}
        self._mark = time.perf_counter()

    def run(self) -> dict:
        self.start()
        self.phase1()
        self.merge()
        return self.finish()

    # -- bookkeeping ---------------------------------------------------------------------------

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.seconds[name] = self.seconds.get(name, 0.0) + now - self._mark
        self.peaks[name] = peak_memory(self.device)[0]
        self._mark = now

    def phase(self, name, done, total, text=None) -> None:
        self.report("phase", (name, done, total, text))

    def gather(self, value) -> list:
        """`value` of every rank, in rank order (the gloo group: plain Python objects)."""
        import torch.distributed as dist

        out = [None] * self.world
        dist.all_gather_object(out, value, group=self.control)
        return out

    # -- the steps -----------------------------------------------------------------------------

    def start(self) -> None:
        """The cameras (rank 0, broadcast), this rank's frames, its checkpoint checked; every rank
        refuses together, before anything is written, when one refuses."""
        import torch.distributed as dist


        job, rank = self.job, self.rank
        self.report("started", dict(rank=rank, pid=os.getpid(), device=str(self.device)))
        errors, saved = [], None
        if job.resume and self.paths["checkpoint"].is_file():
            try:
                saved = read_checkpoint(self.paths["checkpoint"])
                check_options(saved, job.options, job.config, self.paths["checkpoint"])
            except InputError as e:
                errors.append(str(e))
        # while rank 0 estimates the cameras, the others read their frames and pay their first steps'
        # one-off costs (tomgs.train.warm); nothing of it changes a result
        early = None
        payload, clip, failure = None, None, None
        if rank == 0:
            try:
                payload, clip = _shared_setup(job, self.device, saved, self.phase, self.report, self.timeline)
            except InputError as e:
                payload = dict(error=str(e), input=True)
            except Exception as e:  # noqa: BLE001 - the others must not wait for a broadcast that never comes
                payload, failure = dict(error=f"{type(e).__name__}: {e}", input=False), e
        else:
            try:
                with self.timeline.span("read early"):
                    early = _read_early(job, rank)
            except InputError as e:
                errors.append(str(e))
            if early is not None:
                with self.timeline.span("thumbnails"):  # what a checkpoint identifies them by
                    self.early_identity = _identity_of(early)
            # beside the wait, joined before phase 1's Trainer: no other rank waits for it
            self.warming = WarmUp(self.job.config, self.device)
        waiting = time.time()
        box = [payload]
        dist.broadcast_object_list(box, src=0, group=self.control)
        payload = box[0]
        self.timeline.add("wait for cameras" if rank else "send cameras", waiting)
        began = time.time()
        if "error" in payload:
            if failure is not None:
                raise failure
            if payload["input"]:
                raise InputError(payload["error"])
            raise RuntimeError(f"rank 0 failed while reading the clip or estimating its cameras: {payload['error']}")
        self.payload = payload
        self.cameras = cameras = Cameras.from_dict(payload["cameras"], source="rank 0's cameras")
        overlap = default_overlap(len(cameras), self.world) if job.overlap is None else job.overlap
        self.stretches = plan_stretches(len(cameras), self.world, overlap)
        self.stretch = stretch = self.stretches[rank]
        sys.stderr.write(f"rank {rank}/{self.world} (pid {os.getpid()}, {self.device}): "
                         f"{stretch.describe(cameras.frame_indices)}\n")
        sys.stderr.flush()
        try:
            if saved is not None and not errors:
                _check_shard(saved["clip"].get("shard"), stretch, self.world, self.paths["checkpoint"])
            self.frames, self.identity = self._own_frames(clip, early)
            clip = None  # rank 0: the rest of the clip goes now
            if saved is not None and not errors:
                check_clip(saved["clip"], self.identity, job.options, self.paths["checkpoint"])
        except InputError as e:
            errors.append(str(e))
        refused = [e for e in self.gather(errors[0] if errors else None) if e is not None]
        if refused:
            raise InputError(refused[0])
        self.timeline.add("frames", began)  # its stretch read (or the early read's taken), checked, agreed
        self.saved = saved
        self.lap("read")
        if rank == 0:  # rank 0 estimated the cameras inside its reading time; the others waited for them
            self.seconds["poses"] = float(payload["pose_seconds_run"])
            self.seconds["read"] -= self.seconds["poses"]

    def _own_frames(self, clip, early):
        """(uint8 [F,H,W,3] of the stretch, what identifies them for a checkpoint)."""
        s, numbers = self.stretch, self.cameras.frame_indices[self.stretch.lo:self.stretch.hi]
        if clip is not None:
            frames = np.ascontiguousarray(clip.frames[s.lo:s.hi]).copy()
        elif early is not None and np.array_equal(early.indices, numbers) \
                and early.frames.shape[1:3] == (self.cameras.height, self.cameras.width):
            frames = early.frames
            if getattr(self, "early_identity", None) is not None:  # worked out while rank 0 estimated the cameras
                return frames, self.early_identity
        else:
            frames = _read_stretch(self.job, self.cameras, s)
        identity = clip_identity(SimpleNamespace(indices=numbers, frames=frames, masks=None))
        return frames, identity

    def phase1(self) -> None:
        """An ordinary Trainer on the stretch, in the stretch's own time, to the end of phase 1 (or
        its iterations), with its checkpoints and log beside the output."""
        job, stretch, payload, frames = self.job, self.stretch, self.payload, self.frames
        if getattr(self, "warming", None) is not None:
            waiting = time.time()
            if self.warming.join() > 0.005:
                self.timeline.add("wait for the warm-up", waiting)
            self.timeline.add("warm up", self.warming.began, self.warming.ended)
            self.warming = None
        self.phase("init", 0, 1)
        initialising = time.time()
        height, width = frames.shape[1:3]
        free = None
        if self.device.type == "cuda":
            free = torch.cuda.mem_get_info(self.device)[0] - frames.nbytes
        _, config = rank_plan(job.config, stretch.frames, height, width, height * width, self.device.type,
                               job.auto_budget, free)
        self.config = config = config.replace(seed=config.seed + self.rank)  # the ranks draw differently
        points, colors, point_frames = stretch_points(payload["points"], payload["colors"], payload["point_frames"],
                                                      stretch)
        torch.manual_seed(config.seed)
        trainer = Trainer(frames, local_cameras(self.cameras, stretch), points, colors, config, self.device,
                          point_frames=point_frames, init_progress=lambda done, total: self.phase("init", done, total))
        trainer.notes[:0] = list(payload["notes"])
        if self.saved is not None:
            trainer.load_checkpoint(self.saved)
            write_csv(self.paths["csv"], trainer.history)  # the log as of the checkpoint
        else:
            self.paths["checkpoint"].unlink(missing_ok=True)  # overwrite, or a rank that never saved: start over
        trainer.clip = dict(self.identity, options=job.options, pose_seconds=payload["pose_seconds"],
                            cameras=payload["cameras"], source=payload["source"],
                            shard=dict(world=self.world, rank=self.rank, lo=stretch.lo, hi=stretch.hi,
                                       own_lo=stretch.own_lo, own_hi=stretch.own_hi))
        self.saved = None
        self.phase("init", 1, 1)
        self.lap("init")
        self.timeline.add("init", initialising)
        training = time.time()
        # a resume trains on as a one-GPU resume does: to its iterations, or for this command's budget
        end = payload["times"]["phase1_end"]
        limit = 0.0 if end is None else trainer.elapsed + max(end - time.time(), 1.0)
        trainer.run(checkpoint=self.paths["checkpoint"], log_csv=self.paths["csv"],
                    progress=lambda row: self.report("row", row), time_limit=limit,
                    tick=train_ticks(self.phase, config.iterations, limit))
        self.lap("train")
        self.timeline.add("phase 1", training)
        measured = [row["clip_psnr"] for row in trainer.history if row["clip_psnr"] != ""]
        self.alone = dict(iterations=trainer.iteration, seconds=trainer.elapsed, extent=float(trainer.extent),
                          psnr=round(float(measured[-1]), 3) if measured else None,
                          sh=(trainer.model.max_sh_degree, trainer.model.sh_degree))
        self.history = list(trainer.history)
        self.trainer = trainer

    def merge(self) -> None:
        """The union of every rank's owned Gaussians, gathered on every rank; this rank's part of it
        (its Halo: those that may be alive in its stretch) refined jointly with the other ranks'; the
        scene assembled from every part; this rank's own frames measured before and after.

        Under a budget the refinement ends when what comes after it would reach the deadline, as
        measured here (`_after_refinement`): the measurement of the rank's frames (timed before the
        refinement), the gather (timed on the union's), rank 0's scene written and read back (timed
        on a sample of the union), and EXIT_S for the processes' ends."""
        job, stretch, device, alone, timeline = self.job, self.stretch, self.device, self.alone, self.timeline
        began = time.time()
        # the union, with each row's Adam state from the rank that fitted it (the refinement goes on from it)
        gathered = gather_union(self.trainer.model, self.trainer.optimizer, self.cameras.times, stretch,
                                carry=job.refine_fraction > 0 and job.carry_adam)
        union, gather_s = gathered.rows, gathered.gather_s
        gathered.rows = None  # `union` alone holds them (dropped below)
        self.extents = self.gather(alone["extent"])
        timeline.add("gather union", began)
        del self.trainer
        part = halo(union, alone["sh"][0], self.cameras.times, self.stretches, self.rank)
        rows = part.rows.to(device)
        model = model_of(union[rows], *alone["sh"]).to(device)
        moments = None if gathered.moments is None else gathered.moments[rows]
        gathered.moments = None  # a rank keeps its part only
        self.union_size = len(union)
        io_s = _time_scene_io(union, alone["sh"], self.cameras, self.outputs["scene"], self.history) \
            if self.rank == 0 and self.payload["times"]["deadline"] is not None else 0.0
        del union  # a rank keeps its part only
        own = slice(stretch.own_lo - stretch.lo, stretch.own_hi - stretch.lo)
        # the trainer's rule: frames stay on the GPU when they take at most a share of its free memory
        keep = frame_store(self.frames[own].nbytes, device).type == "cuda"
        frames = torch.as_tensor(self.frames[own], device=device if keep else "cpu")
        del self.frames
        cameras = self.cameras[stretch.own_lo:stretch.own_hi]
        measuring = time.time()
        self.merged_psnr = frame_psnr(model, frames, cameras, device)  # the union before refining: a diagnostic
        # the final measurement renders the whole scene, the one above this rank's part of it: a frame
        # costs at most in proportion (projection scales with the Gaussians, the raster with those seen)
        measure_s = (time.time() - measuring) * max(1.0, self.union_size / max(len(model), 1))
        timeline.add("measure before", measuring)
        self.refined = None
        self.reserve = None
        if job.refine_fraction > 0:
            end = self.payload["times"]["refine_end"]
            if end is not None:  # every rank's measured costs, the largest of them, and rank 0's scene
                costs = self.gather((gather_s + measure_s, io_s))
                self.reserve = dict(assemble_and_measure=round(max(c[0] for c in costs), 3),
                                    scene_io=round(costs[0][1], 3), exit=EXIT_S)
                end = self.payload["times"]["deadline"] - sum(self.reserve.values())
                self.reserve["refine_end"] = round(end - job.start_time, 3)  # seconds since the command started
            steps = max(1, round(job.refine_fraction * self.config.iterations))
            self.phase("train", 0, 1, "joint refinement")

            def log(row):
                self.history.append(row)
                write_csv(self.paths["csv"], self.history)
                self.report("row", row)

            refining = time.time()
            self.refined = refine(model, part, frames, cameras, self.config, gathered.rates, device, moments=moments,
                                  adam_steps=gathered.steps, steps=steps, until=end,
                                  start_wall=alone["seconds"], start_iteration=alone["iterations"], log_rows=log,
                                  tick=lambda iteration, wall: self.phase("train", 0, 1,
                                                                           f"joint refinement, step {iteration}"))
            timeline.add("refinement", refining)
            if self.refined.stopped_by is not None:
                raise FitInterrupted(self.paths["checkpoint"], self.refined.stopped_by, alone["iterations"])
        assembling = time.time()
        self.halo_size, self.shared_size = len(model), part.total
        self.final = model_of(assemble(model, part), *alone["sh"]).to(device)
        del model
        timeline.add("assemble", assembling)
        measuring = time.time()
        self.psnr = frame_psnr(self.final, frames, cameras, device)
        timeline.add("measure after", measuring)
        self.lap("refine")

    def finish(self) -> dict:
        """Rank 0 writes the scene, the merged log and plot; then every rank removes its checkpoint."""
        import torch.distributed as dist

        alone, refined, stretch = self.alone, self.refined, self.stretch
        steps, seconds = (refined.steps, refined.seconds) if refined is not None else (0, 0.0)
        host, gpu = peak_memory(self.device)
        mine = dict(rank=self.rank, frames=stretch.frames, own=[stretch.own_lo, stretch.own_hi], lo=stretch.lo,
                    hi=stretch.hi, iterations=alone["iterations"], train_seconds=round(alone["seconds"], 3),
                    steps_per_s=round(alone["iterations"] / max(alone["seconds"], 1e-9), 3), phase1_psnr=alone["psnr"],
                    merged_psnr=self.merged_psnr, frame_psnr=self.psnr, refine_steps=steps,
                    refine_seconds=round(seconds, 3), refine_steps_per_s=round(steps / max(seconds, 1e-9), 3),
                    merge_seconds=round(self.seconds.get("refine", 0.0), 3),  # gather, measure, refine, assemble
                    union=self.union_size, halo=self.halo_size, shared=self.shared_size,
                    history=self.history, peak_host_mb=host, peak_gpu_mb=gpu, gaussians=len(self.final),
                    extent=alone["extent"], reserve=self.reserve)
        timeline = self.timeline
        with timeline.span("gather logs"):
            everyone = self.gather(mine)
        summary = dict(rank=self.rank)
        if self.rank == 0:
            self.phase("save", 0, 2)
            with timeline.span("save"):
                summary = _write_outputs(self.job, everyone, self.stretches, self.cameras, self.payload, self.final,
                                         [] if refined is None else refined.rows, self.outputs, self.config,
                                         float(np.mean(self.extents)))
            self.phase("save", 1, 2)
        with timeline.span("wait for the scene" if self.rank else "barrier"):
            dist.barrier(group=self.control)  # the scene is written: the checkpoints have done their work
        tidying = time.time()
        self.paths["checkpoint"].unlink(missing_ok=True)
        self.lap("save")
        if self.rank == 0:  # the merge and the refinement count as training (shards info has them apart)
            seconds = dict(self.seconds)
            seconds["train"] = seconds.get("train", 0.0) + seconds.pop("refine", 0.0)
            summary["phase_seconds"] = seconds
            summary["peak_host_mb_by_phase"] = {k: v for k, v in self.peaks.items() if k != "refine"}
            self.phase("save", 2, 2)
        timeline.add("tidy", tidying)
        # every rank's phases so far, for rank 0's summary (torchrun: what its caller sees of the others)
        timelines = self.gather(timeline.events)
        if self.rank == 0:
            summary["timelines"] = {f"rank{r}": list(events) for r, events in enumerate(timelines)}
        return summary


def _time_scene_io(union: torch.Tensor, sh: tuple, cameras, scene: Path, history: list) -> float:
    """Rank 0, before the refinement: seconds to write a scene of the union's size and read it back
    (the parent's load_scene), and to draw the plot, as timed here on a sample of the union's rows
    (SAMPLE_IO_SHARE of them, at least MIN_SAMPLE_IO) written beside the scene and removed; the
    per-Gaussian time scaled to the whole union (so the sample's fixed costs count several times)."""
    from tomgs.io.scene import load_scene, save_scene

    n = len(union)
    if n == 0:
        return 0.0
    step = max(1, min(round(1 / SAMPLE_IO_SHARE), n // MIN_SAMPLE_IO))
    sample = model_of(union[::step], *sh)
    path = scene.with_name(f".{scene.stem}.io-sample{scene.suffix}")
    figure = scene.with_name(f".{scene.stem}.io-sample.png")
    began = time.perf_counter()
    try:
        save_scene(path, sample, cameras, {})
        load_scene(path)
        io = (time.perf_counter() - began) * n / len(sample)
        began = time.perf_counter()
        write_plot(figure, history)  # matplotlib's import and a figure like the run's
        return io + time.perf_counter() - began
    finally:
        path.unlink(missing_ok=True)
        figure.unlink(missing_ok=True)


def _write_outputs(job, everyone, stretches, cameras, payload, final, refine_rows, outputs, config, extent) -> dict:
    """Rank 0: the scene, the merged CSV and plot; the run's summary."""
    from tomgs.io.scene import save_scene, vertex_bytes

    frame_psnr = [p for rank in everyone for p in rank["frame_psnr"]]
    merged_before = [p for rank in everyone for p in rank["merged_psnr"]]
    clip_psnr = float(np.mean(frame_psnr))
    weights = [rank["own"][1] - rank["own"][0] for rank in everyone]
    phase1 = [[row for row in rank["history"] if int(row["iteration"]) <= rank["iterations"]] for rank in everyone]
    history = merged_history(phase1, weights)
    start_iteration = sum(rank["iterations"] for rank in everyone)
    start_wall = max(rank["train_seconds"] for rank in everyone)
    steps = everyone[0]["refine_steps"]
    refine_seconds = max(rank["refine_seconds"] for rank in everyone)
    for row in refine_rows:
        k = int(row["iteration"]) - everyone[0]["iterations"]
        history.append(dict(row, iteration=start_iteration + k * len(everyone), gaussians=len(final),
                            wall_s=round(start_wall + float(row["wall_s"]) - everyone[0]["train_seconds"], 3)))
    history.append(log_row(iteration=start_iteration + steps * len(everyone),
                           wall_s=round(start_wall + refine_seconds, 3),
                           train_psnr=history[-1]["train_psnr"] if history else "", clip_psnr=round(clip_psnr, 3),
                           clip_frames=len(frame_psnr), gaussians=len(final),
                           scene_bytes=vertex_bytes(len(final), final.max_sh_degree),
                           memory_mb=max(float(r["peak_gpu_mb"] or r["peak_host_mb"]) for r in everyone)))
    boundary = boundary_psnr(frame_psnr, stretches)
    shards = dict(ranks=len(everyone), overlap=stretches[0].hi - stretches[0].own_hi if len(stretches) > 1 else 0,
                  union=everyone[0]["union"], shared=everyone[0]["shared"],
                  refine_fraction=job.refine_fraction, refine_steps=steps, refine_seconds=round(refine_seconds, 3),
                  merged_psnr_before_refine=round(float(np.mean(merged_before)), 3), clip_psnr=round(clip_psnr, 3),
                  boundary=boundary, frame_psnr=[round(p, 3) for p in frame_psnr],
                  per_rank=[{k: rank[k] for k in ("rank", "frames", "own", "iterations", "train_seconds",
                                                  "steps_per_s", "phase1_psnr", "refine_steps_per_s",
                                                  "merge_seconds", "halo", "peak_host_mb", "peak_gpu_mb",
                                                  "reserve")}
                            for rank in everyone])
    notes = list(payload["notes"])
    notes.append(f"{len(everyone)} ranks: " + "; ".join(
        f"rank {r['rank']} {s.describe(cameras.frame_indices)}, {r['iterations']} iterations "
        f"({r['steps_per_s']:.1f}/s), {r['phase1_psnr'] if r['phase1_psnr'] is not None else '-'} dB alone"
        for r, s in zip(everyone, stretches)))
    notes.append(f"merged: {shards['merged_psnr_before_refine']:.2f} dB before the joint refinement, "
                 f"{clip_psnr:.2f} dB after {steps} steps on each rank ({refine_seconds:.1f} s); frames within "
                 f"{boundary['near']} of a boundary {boundary['boundary']} dB, the others {boundary['interior']} dB")
    info = dict(source=payload["source"], iterations=start_iteration + steps * len(everyone),
                train_seconds=round(start_wall + refine_seconds, 2), pose_seconds=round(payload["pose_seconds"], 2),
                clip_psnr=round(clip_psnr, 3), extent=extent, fps=payload["fps"], background=[0.0, 0.0, 0.0],
                config={k: v for k, v in vars(config).items()}, notes=notes, shards=shards)
    save_scene(outputs["scene"], final, cameras, info)
    write_csv(outputs["csv"], history)
    write_plot(outputs["plot"], history)
    return dict(clip_psnr=clip_psnr, iterations=info["iterations"], seconds=info["train_seconds"], history=history,
                notes=notes, shards=shards, peak_host_mb=max(r["peak_host_mb"] for r in everyone),
                peak_gpu_mb=(max(r["peak_gpu_mb"] for r in everyone) if everyone[0]["peak_gpu_mb"] is not None
                             else None))


def _identity_of(video) -> dict:
    """tomgs.train.clip.clip_identity of frames read without masks (a rank's stretch)."""
    return clip_identity(SimpleNamespace(indices=video.indices, frames=video.frames, masks=None))


def _shared_setup(job: Job, device, saved, phase, report, timeline: Timeline | None = None):
    """Rank 0: read the clip, estimate its cameras (or take them from a checkpoint of this run), and
    fix the budget's wall-clock times. Returns (payload for every rank, the clip)."""
    from tomgs.poses import estimate_cameras

    timeline = timeline or Timeline(job.start_time)
    phase("read", 0, 1)
    reading = time.time()
    clip = job.video if isinstance(job.video, Video) else read_video(
        job.video, frames=job.frames, max_side=job.max_side, masks=job.masks,
        progress=lambda done, total: phase("read", done, total))
    phase("read", 1, 1)
    timeline.add("read", reading)
    posing = time.time()
    began = time.perf_counter()
    cameras_dict = saved["clip"].get("cameras") if saved is not None else None
    if cameras_dict is None and job.resume:
        for path in (p["checkpoint"] for p in rank_paths(job.output, job.world)[1:]):
            if path.is_file():  # rank 0 never saved: another rank's checkpoint has the cameras
                cameras_dict = read_checkpoint(path)["clip"].get("cameras")
                break
    notes, points, colors, point_frames = [], np.zeros((0, 3)), np.zeros((0, 3), np.float32), None
    if cameras_dict is not None:
        cameras = Cameras.from_dict(cameras_dict, source="the checkpoint's cameras")
        if len(cameras) != len(clip):
            raise InputError(f"the checkpoints beside {job.output} were fitted on {len(cameras)} frames, this run "
                             f"reads {len(clip)}: resume with the --frames it was started with, or {START_OVER}")
    else:
        phase("poses", 0, 1)
        cameras, points, colors, pose_report = estimate_cameras(
            clip, method=job.poses, focal=job.focal,
            progress=lambda done, total: (report("poses", (done, total)), phase("poses", done, total)))
        notes = [f"poses: {pose_report.summary()}", *pose_report.notes]
        point_frames = pose_report.point_frames
        phase("poses", 1, 1)
    pose_seconds = spent = time.perf_counter() - began
    timeline.add("poses", posing)
    if saved is not None:
        pose_seconds = float(saved["clip"].get("pose_seconds", pose_seconds))
    height, width = clip.frames.shape[1:3]
    overlap = default_overlap(len(clip), job.world) if job.overlap is None else job.overlap
    stretches = plan_stretches(len(clip), job.world, overlap)
    largest = max(s.frames for s in stretches)
    plan, config = rank_plan(job.config, largest, height, width, height * width, device.type, job.auto_budget)
    times = dict(deadline=None, phase1_end=None, refine_end=None)
    if plan.budget > 0:
        now = time.time()
        deadline = job.start_time + plan.budget
        own = max(s.own_hi - s.own_lo for s in stretches)
        # what comes after the refinement, as modelled here to place the end of phase 1 (the refinement
        # itself ends by what the ranks measure before it: Rank.merge): the final measurement of a
        # rank's frames with the whole scene, the scene written and read back by the parent, the
        # processes ending; the scene about the ranks' starting clouds (their densification is
        # time-bound: on the H200s 2.44M Gaussians each after 72 s from 2.4M)
        scene = job.world * min(config.max_gaussians, config.init_points_per_frame * largest)
        after = EXIT_S + own * render_seconds(device.type, scene, height * width) + \
            2 * (SAVE_COST[0] + SAVE_COST[1] * scene)
        train_end = max(deadline - after, now + 2.0)
        fraction = job.refine_fraction
        times = dict(deadline=deadline, phase1_end=now + (1 - fraction) * (train_end - now),
                     refine_end=train_end if fraction > 0 else None, after_model=round(after, 3))
    payload = dict(cameras=cameras.to_dict(), points=np.asarray(points, dtype=np.float64).reshape(-1, 3),
                   colors=np.asarray(colors, dtype=np.float32).reshape(-1, 3),
                   point_frames=None if point_frames is None else np.asarray(point_frames, np.int64).reshape(-1, 2),
                   notes=notes, pose_seconds=round(pose_seconds, 3), pose_seconds_run=spent, fps=clip_fps(clip),
                   source=str(getattr(job.video, "path", job.video)), times=times)
    return payload, clip


def _read_early(job: Job, rank: int):
    """A rank's frames read before rank 0's cameras arrive, when the selection (--frames) names their
    source frame numbers without the source's length (a range from a start >= 0); None otherwise. The
    clip's frame count comes from its index (tomgs.io.video.probe_clip)."""
    if isinstance(job.video, Video):
        return None
    sel = parse_frames(job.frames)
    if sel.start is not None and sel.start < 0:
        return None
    count = probe_clip(job.video, job.frames, job.max_side)[0]
    overlap = default_overlap(count, job.world) if job.overlap is None else job.overlap
    stretch = plan_stretches(count, job.world, overlap)[rank]
    start, step = sel.start or 0, sel.step or 1
    numbers = slice(start + stretch.lo * step, start + (stretch.hi - 1) * step + 1, step)
    return read_video(job.video, frames=numbers, max_side=job.max_side)


def _read_stretch(job: Job, cameras, stretch) -> np.ndarray:
    """uint8 [F,H,W,3]: a rank's frames, read from the clip by their source frame numbers."""
    if isinstance(job.video, Video):
        return np.ascontiguousarray(job.video.frames[stretch.lo:stretch.hi])
    return read_video_for(job.video, cameras[stretch.lo:stretch.hi])


def _check_shard(shard, stretch, world: int, checkpoint) -> None:
    """A rank's checkpoint must be of this run's ranks and stretch."""
    if not isinstance(shard, dict):
        raise InputError(f"{checkpoint} is not a checkpoint of a sharded fit: {START_OVER}")
    if shard.get("world") != world:
        raise InputError(f"{checkpoint} was fitted with --gpus {shard.get('world')}, this run asks for --gpus {world}: "
                         f"resume with the --gpus it was started with, or {START_OVER}")
    if [shard.get(k) for k in ("lo", "hi", "own_lo", "own_hi")] != [stretch.lo, stretch.hi, stretch.own_lo,
                                                                     stretch.own_hi]:
        raise InputError(f"{checkpoint} was fitted on positions {shard.get('lo')}..{shard.get('hi')} of the clip, "
                         f"this run gives rank {stretch.rank} {stretch.lo}..{stretch.hi}: resume with the options it "
                         f"was started with, or {START_OVER}")




__all__ = ["Job", "Rank", "Timeline", "rank_plan", "run_rank", "spawned"]
