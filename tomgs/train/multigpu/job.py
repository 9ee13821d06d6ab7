"""What a rank of a sharded fit is given and how its time is recorded: the Job (pickled to spawned
ranks), the plan of a stretch, and the Timeline of each process's phases."""

from __future__ import annotations

import time
from dataclasses import dataclass

from tomgs.train.multigpu.shards import REFINE_FRACTION
from tomgs.train.phases import tomgs_started
from tomgs.train.plan import make_plan


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


__all__ = ["Job", "Timeline", "rank_plan", "tomgs_start_epoch"]
