"""One rank of a sharded fit (tomgs.train.multigpu.shards): the fit's Pipeline with a rank's hooks (its
process: tomgs.train.multigpu.group).

    read, cameras   rank 0 reads the clip and estimates the cameras as a one-process fit does and broadcasts
                    them; the others meanwhile read their stretch and warm up. Every rank checks its checkpoint
                    on resume, and all refuse together when one refuses, before anything is written
    init, train     phase 1: an ordinary Trainer on the stretch, its checkpoint and log beside the output
    after_training  the merge, the joint refinement (tomgs.train.multigpu.joint), the measurement of its frames
    save, result    rank 0 writes the scene, the merged CSV and plot; every rank removes its checkpoint
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np
import torch

from tomgs.cameras import Cameras
from tomgs.errors import InputError
from tomgs.metrics import frame_psnr
from tomgs.outputs import fit_output_paths
from tomgs.train.budget import Budget
from tomgs.train.checkpoint import FitInterrupted, read_checkpoint
from tomgs.train.clip import check_clip, check_options
from tomgs.train.log import write_csv
from tomgs.train.multigpu.job import Job, Timeline, camera_payload, checkpoint_cameras, rank_plan
from tomgs.train.multigpu.joint import EXIT_S, joint_trainer, refine_jointly, time_scene_io, write_outputs
from tomgs.train.multigpu.shards import (assemble, check_shard, default_overlap, gather_union, halo, identity_of,
                                         local_cameras, model_of, plan_stretches, rank_paths, read_early,
                                         stretch_frames, stretch_points)
from tomgs.train.phases import peak_memory
from tomgs.train.pipeline import Pipeline
from tomgs.train.trainer import Trainer
from tomgs.train.warm import WarmUp


class ShardedPipeline(Pipeline):
    """Rank `rank` of `job` on `device`: `control` its group for objects (gloo), `report(kind, payload)` what
    it tells the parent, `timeline` its phases. `run` returns its summary (a dict)."""

    def __init__(self, job: Job, rank: int, device: torch.device, control, report, timeline: Timeline | None = None):
        started = time.perf_counter() - (time.time() - job.start_time)
        super().__init__(job.request(device, report, started), rank_paths(job.output, job.world)[rank], None)
        self.job, self.rank, self.world, self.control, self.report = job, rank, job.world, control, report
        self.timeline = timeline or Timeline(job.start_time)
        self.outputs = fit_output_paths(job.output)
        self.payload, self.failure, self.errors, self.resumed = None, None, [], None
        self.early = self.early_identity = None  # a rank's early read (not rank 0's) and its identity

    def gather(self, value) -> list:
        """`value` of every rank, in rank order (the gloo group: plain Python objects)."""
        import torch.distributed as dist

        out = [None] * self.world
        dist.all_gather_object(out, value, group=self.control)
        return out

    def attempt(self, phase) -> None:
        """Rank 0's `phase`, unless one failed before; a failure becomes the payload the others receive instead
        of the cameras (they must not wait for a broadcast that never comes)."""
        if self.payload is not None:
            return
        try:
            phase()
        except InputError as e:
            self.payload = dict(error=str(e), input=True)
        except Exception as e:  # noqa: BLE001 - raised again on rank 0 after the broadcast
            self.payload, self.failure = dict(error=f"{type(e).__name__}: {e}", input=False), e

    # -- the phases' hooks -------------------------------------------------------------------------

    def plan(self) -> None:
        """Nothing before reading: rank 0 plans the stretches once it has the cameras (`share_cameras`)."""
        self.warming = None

    def read(self) -> None:
        """This rank's checkpoint read and checked (on resume); rank 0 reads the clip; the others read their
        stretch early where the selection allows and pay their first steps' one-off costs meanwhile."""
        self.report("started", dict(rank=self.rank, pid=os.getpid(), device=str(self.device)))
        if self.job.resume and self.paths["checkpoint"].is_file():
            try:
                self.resumed = read_checkpoint(self.paths["checkpoint"])
                check_options(self.resumed, self.job.options, self.job.config, self.paths["checkpoint"])
            except InputError as e:
                self.errors.append(str(e))
        if self.rank == 0:
            with self.timeline.span("read"):
                self.attempt(super().read)
            return
        try:
            with self.timeline.span("read early"):
                self.early = read_early(self.job, self.rank)
        except InputError as e:
            self.errors.append(str(e))
        if self.early is not None:
            with self.timeline.span("thumbnails"):  # what a checkpoint identifies them by
                self.early_identity = identity_of(self.early.indices, self.early.frames)
        self.warming = WarmUp(self.config, self.device)  # joined before phase 1's Trainer

    def saved_cameras(self) -> dict | None:
        return checkpoint_cameras(self.job, self.resumed)

    def cameras(self) -> None:
        """Rank 0's cameras and the budget's times broadcast; this rank's stretch, frames and checkpoint
        checked; every rank refuses together when one refuses."""
        import torch.distributed as dist

        if self.rank == 0:
            self.saved = self.resumed  # its pose seconds, as a one-process resume's
            with self.timeline.span("poses"):
                self.attempt(super().cameras)
            self.saved = None
            self.attempt(self.share_cameras)
        waiting = time.time()
        box = [self.payload]
        dist.broadcast_object_list(box, src=0, group=self.control)
        self.payload = payload = box[0]
        self.timeline.add("wait for cameras" if self.rank else "send cameras", waiting)
        began = time.time()
        if "error" in payload:
            if self.failure is not None:
                raise self.failure
            if payload["input"]:
                raise InputError(payload["error"])
            raise RuntimeError(f"rank 0 failed while reading the clip or estimating its cameras: {payload['error']}")
        self.state.cameras = cameras = Cameras.from_dict(payload["cameras"], source="rank 0's cameras")
        self.stretches = plan_stretches(len(cameras), self.world, self.overlap(len(cameras)))
        self.stretch = stretch = self.stretches[self.rank]
        sys.stderr.write(f"rank {self.rank}/{self.world} (pid {os.getpid()}, {self.device}): "
                         f"{stretch.describe(cameras.frame_indices)}\n")
        sys.stderr.flush()
        self.check_stretch()
        self.timeline.add("frames", began)  # its stretch read (or the early read's taken), checked, agreed
        self.saved = self.resumed
        self.lap("read")

    def overlap(self, count: int) -> int:
        return default_overlap(count, self.world) if self.job.overlap is None else self.job.overlap

    def share_cameras(self) -> None:
        """Rank 0: the payload every rank receives (tomgs.train.multigpu.job.camera_payload)."""
        self.payload = camera_payload(self.job, self.state, self.device.type, self.overlap(len(self.state.clip)))

    def check_stretch(self) -> None:
        """This rank's frames (shards.stretch_frames) and its checkpoint checked against them; every rank's refusal
        gathered, the first raised on every rank."""
        saved, stretch = self.resumed, self.stretch
        try:
            if saved is not None and not self.errors:
                check_shard(saved["clip"].get("shard"), stretch, self.world, self.paths["checkpoint"])
            self.frames, self.identity = stretch_frames(self.job, self.state.cameras, stretch, self.state.clip,
                                                        self.early, self.early_identity)
            self.state.clip = self.state.inputs = self.early = None  # rank 0: the rest of the clip goes now
            if saved is not None and not self.errors:
                check_clip(saved["clip"], self.identity, self.job.options, self.paths["checkpoint"])
        except InputError as e:
            self.errors.append(str(e))
        refused = [e for e in self.gather(self.errors[0] if self.errors else None) if e is not None]
        if refused:
            raise InputError(refused[0])

    def compile(self) -> None:
        """Nothing: a rank's first steps pay their one-off costs in the warm-up."""

    def init(self) -> None:
        """Phase 1's Trainer: an ordinary one on the stretch, in the stretch's own clip time, its draws its
        rank's, resumed from its checkpoint or starting over."""
        job, stretch, payload, frames = self.job, self.stretch, self.payload, self.frames
        if self.warming is not None:
            waiting = time.time()
            if self.warming.join() > 0.005:
                self.timeline.add("wait for the warm-up", waiting)
            self.timeline.add("warm up", self.warming.began, self.warming.ended)
            self.warming = None
        self.say("init", 0, 1)
        initialising = time.time()
        height, width = frames.shape[1:3]
        free = torch.cuda.mem_get_info(self.device)[0] - frames.nbytes if self.device.type == "cuda" else None
        _, config = rank_plan(job.config, stretch.frames, height, width, height * width, self.device.type,
                              job.auto_budget, free)
        self.config = config = config.replace(seed=config.seed + self.rank)  # the ranks draw differently
        points, colors, point_frames = stretch_points(payload["points"], payload["colors"], payload["point_frames"],
                                                      stretch)
        torch.manual_seed(config.seed)
        trainer = Trainer(frames, local_cameras(self.state.cameras, stretch), points, colors, config, self.device,
                          point_frames=point_frames, init_progress=lambda done, total: self.say("init", done, total))
        trainer.notes[:0] = list(payload["notes"])
        self.resume_or_start_over(trainer)
        trainer.clip = dict(self.identity, options=job.options, pose_seconds=payload["pose_seconds"],
                            cameras=payload["cameras"], source=payload["source"],
                            shard=dict(world=self.world, rank=self.rank, lo=stretch.lo, hi=stretch.hi,
                                       own_lo=stretch.own_lo, own_hi=stretch.own_hi))
        self.state.trainer = trainer
        self.say("init", 1, 1)
        self.lap("init")
        self.timeline.add("init", initialising)

    def training_budget(self) -> Budget:
        """Phase 1's: to its iterations, or to the end of phase 1 rank 0 set (a resume trains on as a
        one-process resume does)."""
        budget = Budget(iterations=self.config.iterations)
        budget.train_until(self.payload["times"]["phase1_end"], self.state.trainer.elapsed)
        return budget

    def train(self) -> None:
        training = time.time()
        super().train()
        self.timeline.add("phase 1", training)
        trainer = self.state.trainer
        measured = [row["clip_psnr"] for row in trainer.history if row["clip_psnr"] != ""]
        self.alone = dict(iterations=trainer.iteration, seconds=trainer.elapsed, extent=float(trainer.extent),
                          psnr=round(float(measured[-1]), 3) if measured else None,
                          sh=(trainer.model.max_sh_degree, trainer.model.sh_degree))
        self.history = list(trainer.history)
        self.state.result = None  # its model is phase 1's, which the merge hands on

    def after_training(self) -> None:
        """The union of every rank's owned Gaussians gathered on every rank; this rank's part of it (its Halo)
        refined jointly with the other ranks' (`refine`); the scene assembled from every part; this rank's
        own frames measured before and after."""
        job, stretch, device, alone, timeline = self.job, self.stretch, self.device, self.alone, self.timeline
        began = time.time()
        phase1, self.state.trainer = self.state.trainer, None
        gathered = gather_union(phase1.model, phase1.optimizer, self.state.cameras.times, stretch,
                                carry=job.refine_fraction > 0 and job.carry_adam)
        union, gather_s, gathered.rows = gathered.rows, gathered.gather_s, None  # `union` alone holds them
        del phase1
        self.extents = self.gather(alone["extent"])
        timeline.add("gather union", began)
        part = halo(union, alone["sh"][0], self.state.cameras.times, self.stretches, self.rank)
        rows = part.rows.to(device)
        model = model_of(union[rows], *alone["sh"]).to(device)
        moments, gathered.moments = None if gathered.moments is None else gathered.moments[rows], None
        self.union_size = len(union)
        io_s = time_scene_io(union, alone["sh"], self.state.cameras, self.outputs["scene"], self.history) \
            if self.rank == 0 and self.payload["times"]["deadline"] is not None else 0.0
        del union  # a rank keeps its part only
        cameras = self.state.cameras[stretch.own_lo:stretch.own_hi]
        own = self.frames[stretch.own_lo - stretch.lo:stretch.own_hi - stretch.lo]
        trainer = joint_trainer(model, own, cameras, self.config, gathered.rates, alone["extent"], device,
                                moments=moments, adam_steps=gathered.steps, seed=self.config.seed + 1000 + self.rank)
        del self.frames, model
        measuring = time.time()
        self.merged_psnr = frame_psnr(trainer.model, trainer.frames, cameras, device)  # a diagnostic
        # the final measurement renders the whole scene, this one this rank's part of it: a frame costs at most
        # in proportion (projection scales with the Gaussians, the raster with those seen)
        measure_s = (time.time() - measuring) * max(1.0, self.union_size / max(len(trainer.model), 1))
        timeline.add("measure before", measuring)
        self.refined = self.reserve = None
        if job.refine_fraction > 0:
            self.refine(trainer, part, gather_s + measure_s, io_s)
        assembling = time.time()
        self.halo_size, self.shared_size = len(trainer.model), part.total
        self.final = model_of(assemble(trainer.model, part), *alone["sh"]).to(device)
        timeline.add("assemble", assembling)
        measuring = time.time()
        self.psnr = frame_psnr(self.final, trainer.frames, cameras, device)
        timeline.add("measure after", measuring)
        self.lap("refine")

    def refine(self, trainer, part, measured_s: float, io_s: float) -> None:
        """The joint refinement (tomgs.train.multigpu.joint.refine_jointly) for refine_fraction of the
        iterations, or under a budget until what comes after it would reach the deadline: the largest of
        the ranks' measured costs (`measured_s`: the gather and the measurement), rank 0's scene written and
        read back (`io_s`) and EXIT_S for the processes' ends."""
        job, alone = self.job, self.alone
        end = self.payload["times"]["refine_end"]
        if end is not None:
            costs = self.gather((measured_s, io_s))
            self.reserve = dict(assemble_and_measure=round(max(c[0] for c in costs), 3),
                                scene_io=round(costs[0][1], 3), exit=EXIT_S)
            end = self.payload["times"]["deadline"] - sum(self.reserve.values())
            self.reserve["refine_end"] = round(end - job.start_time, 3)  # seconds since the command started
        self.say("train", 0, 1, "joint refinement")

        def log(row):
            self.history.append(row)
            write_csv(self.paths["csv"], self.history)
            self.report("row", row)

        refining = time.time()
        self.refined = refine_jointly(
            trainer, part, steps=max(1, round(job.refine_fraction * self.config.iterations)), until=end,
            start_wall=alone["seconds"], start_iteration=alone["iterations"], log_rows=log,
            tick=lambda iteration, wall: self.say("train", 0, 1, f"joint refinement, step {iteration}"))
        self.timeline.add("refinement", refining)
        if self.refined.stopped_by is not None:
            raise FitInterrupted(self.paths["checkpoint"], self.refined.stopped_by, alone["iterations"])

    def save(self) -> None:
        """Every rank's account gathered; rank 0 writes the scene, the merged log and plot; then every rank
        removes its checkpoint (the scene is written: they have done their work)."""
        import torch.distributed as dist

        timeline = self.timeline
        with timeline.span("gather logs"):
            everyone = self.gather(self.account())
        self.summary = dict(rank=self.rank)
        if self.rank == 0:
            self.say("save", 0, 2)
            with timeline.span("save"):
                self.summary = write_outputs(self.job, everyone, self.stretches, self.state.cameras, self.payload,
                                             self.final, [] if self.refined is None else self.refined.rows,
                                             self.outputs, self.config, float(np.mean(self.extents)))
            self.say("save", 1, 2)
        with timeline.span("wait for the scene" if self.rank else "barrier"):
            dist.barrier(group=self.control)
        tidying = time.time()
        self.paths["checkpoint"].unlink(missing_ok=True)
        self.lap("save")
        if self.rank == 0:  # the merge and the refinement count as training (shards info has them apart)
            seconds = dict(self.state.seconds)
            seconds["train"] = seconds.get("train", 0.0) + seconds.pop("refine", 0.0)
            self.summary["phase_seconds"] = seconds
            self.summary["peak_host_mb_by_phase"] = {k: v for k, v in self.state.peaks.items() if k != "refine"}
            self.say("save", 2, 2)
        timeline.add("tidy", tidying)

    def account(self) -> dict:
        """What rank 0's outputs need of this rank: its stretch, phase 1, the merge and refinement, memory."""
        alone, refined, stretch = self.alone, self.refined, self.stretch
        steps, seconds = (refined.steps, refined.seconds) if refined is not None else (0, 0.0)
        host, gpu = peak_memory(self.device)
        return dict(rank=self.rank, frames=stretch.frames, own=[stretch.own_lo, stretch.own_hi], lo=stretch.lo,
                    hi=stretch.hi, iterations=alone["iterations"], train_seconds=round(alone["seconds"], 3),
                    steps_per_s=round(alone["iterations"] / max(alone["seconds"], 1e-9), 3),
                    phase1_psnr=alone["psnr"], merged_psnr=self.merged_psnr, frame_psnr=self.psnr,
                    refine_steps=steps, refine_seconds=round(seconds, 3),
                    refine_steps_per_s=round(steps / max(seconds, 1e-9), 3),
                    merge_seconds=round(self.state.seconds.get("refine", 0.0), 3),  # gather, measure, refine, assemble
                    union=self.union_size, halo=self.halo_size, shared=self.shared_size, history=self.history,
                    peak_host_mb=host, peak_gpu_mb=gpu, gaussians=len(self.final), extent=alone["extent"],
                    reserve=self.reserve)

    def result(self) -> dict:
        """This rank's summary; rank 0's with every rank's phases so far (torchrun: what its caller sees of
        the others)."""
        timelines = self.gather(self.timeline.events)
        if self.rank == 0:
            self.summary["timelines"] = {f"rank{r}": list(events) for r, events in enumerate(timelines)}
        return self.summary


__all__ = ["ShardedPipeline"]
