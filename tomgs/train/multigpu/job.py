"""What a rank of a sharded fit is given and how its time is recorded: the Job (pickled to spawned
ranks), the plan of a stretch, what rank 0 broadcasts to every rank (`camera_payload`), and the
Timeline of each process's phases."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from tomgs.errors import InputError
from tomgs.train.budget import shard_times
from tomgs.train.checkpoint import START_OVER, read_checkpoint
from tomgs.train.clip import clip_fps
from tomgs.train.multigpu.joint import EXIT_S
from tomgs.train.multigpu.shards import REFINE_FRACTION, default_overlap, plan_stretches, rank_paths
from tomgs.train.phases import tomgs_started
from tomgs.train.plan import SAVE_COST, duration, make_plan, render_seconds


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

    def request(self, device, report, started: float):
        """The FitRequest of this job's rank on `device` (tomgs.train.pipeline), its callbacks through
        `report(kind, payload)`; `started`: this process's time.perf_counter() at the command's start."""
        from tomgs.train.pipeline import FitRequest

        return FitRequest(self.video, self.output, self.config, device, started, self.options, masks=self.masks,
                          frames=self.frames, max_side=self.max_side, poses=self.poses, focal=self.focal,
                          auto_budget=self.auto_budget, progress=lambda row: report("row", row),
                          pose_progress=lambda done, total: (report("poses", (done, total)),
                                                             report("phase", ("poses", done, total, None))),
                          phases=lambda name, done, total, text=None: report("phase", (name, done, total, text)))


def rank_plan(config, frames: int, height: int, width: int, source: int, device_type: str, auto_budget: bool,
              free=None):
    """(FitPlan, config) of one rank's stretch of `frames` frames (tomgs.train.plan.make_plan; its cameras
    come from rank 0, so none are estimated in its time)."""
    return make_plan(config, frames, height, width, source, device_type, poses_estimated=False,
                     auto_budget=auto_budget, free_bytes=free)



@dataclass
class ShardPlan:
    """A sharded fit's plan: one rank's (tomgs.train.plan.FitPlan, for its stretch) and the stretches."""

    rank_plan: object
    frames: int
    world: int
    device: str
    stretches: list = field(default_factory=list)
    refine_fraction: float = REFINE_FRACTION

    def __getattr__(self, name):  # budget, eta, phases, reasons, ...: the rank's plan's
        if name == "rank_plan":
            raise AttributeError(name)
        return getattr(self.rank_plan, name)

    def summary(self) -> str:
        p = self.rank_plan
        sizes = sorted({s.frames for s in self.stretches})
        each = "-".join(str(n) for n in (sizes[0], sizes[-1])) if len(sizes) > 1 else str(sizes[0])
        work = (f"{p.iterations:,} iterations or {duration(p.budget)}, whichever comes first"
                if p.budget > 0 else f"{p.iterations:,} iterations")
        return (f"plan: {self.frames} frames of {p.width}x{p.height} on {self.world} x {self.device}, a stretch of "
                f"{each} frames each, {work}, the last {self.refine_fraction:.0%} of training joint; start from "
                f"{p.points_per_frame * self.frames:,} Gaussians, cap {p.cap:,} per rank; ETA {duration(p.eta)}")


def sharded_plan(job: Job) -> ShardPlan:
    """The plan printed before the ranks start: the largest stretch's, from the clip's index."""
    from tomgs.io import Video
    from tomgs.io.video import probe_clip

    if isinstance(job.video, Video):
        count, height, width = job.video.frames.shape[:3]
        source = height * width
    else:
        count, height, width, source = probe_clip(job.video, job.frames, job.max_side)
    overlap = default_overlap(count, job.world) if job.overlap is None else job.overlap
    stretches = plan_stretches(count, job.world, overlap)
    largest = max(s.frames for s in stretches)
    plan, _ = rank_plan(job.config, largest, height, width, source, job.device_type, job.auto_budget)
    return ShardPlan(plan, count, job.world, job.device_type, stretches, job.refine_fraction)


def checkpoint_cameras(job: Job, resumed: dict | None) -> dict | None:
    """The cameras (Cameras.to_dict) of this run's checkpoints: rank 0's (`resumed`, its state), or another
    rank's when rank 0 never saved; None when the job does not resume or none has any."""
    if resumed is not None:
        return resumed["clip"].get("cameras")
    if not job.resume:
        return None
    for path in (p["checkpoint"] for p in rank_paths(job.output, job.world)[1:]):
        if path.is_file():
            return read_checkpoint(path)["clip"].get("cameras")
    return None


def camera_payload(job: Job, state, device_type: str, overlap: int) -> dict:
    """What rank 0 broadcasts once it has the clip and its cameras (`state`, a tomgs.train.pipeline.FitState):
    the cameras, the tracker's points, the notes, the clip's facts, and the budget's times
    (tomgs.train.budget.shard_times) for the largest stretch's plan."""
    clip, cameras = state.clip, state.cameras
    if len(cameras) != len(clip):
        raise InputError(f"the checkpoints beside {job.output} were fitted on {len(cameras)} frames, this run "
                         f"reads {len(clip)}: resume with the --frames it was started with, or {START_OVER}")
    height, width = clip.frames.shape[1:3]
    stretches = plan_stretches(len(clip), job.world, overlap)
    largest = max(s.frames for s in stretches)
    plan, config = rank_plan(job.config, largest, height, width, height * width, device_type, job.auto_budget)
    # what follows the refinement, as modelled to place the end of phase 1: the final measurement of a rank's
    # frames with the whole scene (about the ranks' starting clouds), the scene written and read back by the
    # parent, the processes ending (the refinement itself ends by what is measured then)
    own = max(s.own_hi - s.own_lo for s in stretches)
    scene = job.world * min(config.max_gaussians, config.init_points_per_frame * largest)
    after = EXIT_S + own * render_seconds(device_type, scene, height * width) + \
        2 * (SAVE_COST[0] + SAVE_COST[1] * scene)
    point_frames = None if state.point_frames is None else np.asarray(state.point_frames, np.int64).reshape(-1, 2)
    return dict(cameras=cameras.to_dict(), points=np.asarray(state.points, dtype=np.float64).reshape(-1, 3),
                colors=np.asarray(state.colors, dtype=np.float32).reshape(-1, 3), point_frames=point_frames,
                notes=state.notes, pose_seconds=round(state.pose_seconds, 3), fps=clip_fps(clip),
                source=str(getattr(job.video, "path", job.video)),
                times=shard_times(plan.budget, job.start_time, after, job.refine_fraction))


__all__ = ["Job", "ShardPlan", "Timeline", "camera_payload", "checkpoint_cameras", "rank_plan", "sharded_plan",
           "tomgs_start_epoch"]
