"""A fit's time: the one reader of TrainConfig.max_seconds and of the iteration stop.

A budget is the whole fit's wall-clock seconds from its start (reading, poses, training and saving);
training takes what the other phases leave of it (`Budget.train_for`). A Trainer used alone
(`Budget.of_training`) reads max_seconds as its training's seconds. The iterations a budget asked for
are UNTIL_BUDGET, more than any budget holds, unless the config stops at its iterations too
(TrainConfig.stop_at_iterations: the iterations were asked for).

Times: `started` and `deadline` are time.perf_counter() values; `training_until` counts the
Trainer's seconds of training (a resumed run's earlier ones included), 0: no limit.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

# the iterations of a fit whose budget was asked for (TrainConfig.stop_at_iterations False): more than any
# budget holds, so the budget alone ends the training and its schedules follow the clock
UNTIL_BUDGET = 2**31 - 1


def asked_seconds(config) -> float:
    """The whole fit's seconds the config asks for (TrainConfig.max_seconds; 0: none)."""
    return float(config.max_seconds)


def asked_iterations(config) -> bool:
    """Whether the config's iterations were asked for: a budget stops at them too, and none is chosen for
    them (TrainConfig.stop_at_iterations)."""
    return bool(config.stop_at_iterations)


def budget_iterations(config) -> int:
    """The iterations a fit under the config's budget trains for: UNTIL_BUDGET under a budget whose
    iterations were not asked for, else config.iterations."""
    if asked_seconds(config) > 0 and not asked_iterations(config):
        return UNTIL_BUDGET
    return int(config.iterations)


@dataclass
class Budget:
    """seconds: the whole fit's wall-clock budget from `started` (0: none); chosen: the plan picked it;
    iterations: where training stops at the latest; training_until: the Trainer's seconds of training at
    which it stops (0: no limit; set by `train_for` / `train_until`)."""

    seconds: float = 0.0
    iterations: int = UNTIL_BUDGET
    started: float = field(default_factory=time.perf_counter)
    chosen: bool = False
    training_until: float = 0.0

    @classmethod
    def of_training(cls, config) -> "Budget":
        """A Trainer used alone: config.iterations, and config.max_seconds of training."""
        return cls(iterations=int(config.iterations), training_until=asked_seconds(config))

    @property
    def deadline(self) -> float | None:
        """time.perf_counter() at the budget's end, or None without one."""
        return self.started + self.seconds if self.seconds > 0 else None

    def left(self) -> float:
        """Seconds from now to the deadline (inf without one)."""
        return math.inf if self.seconds <= 0 else self.deadline - time.perf_counter()

    def train_for(self, elapsed: float, reserve: float) -> float:
        """Training's limit when it starts now with `elapsed` seconds of earlier training (a resume's) and
        `reserve` seconds kept for what follows it (saving): what the deadline leaves, at least a second.
        Returns training_until (0: no limit)."""
        if self.seconds > 0:
            self.training_until = elapsed + max(self.left() - reserve, 1.0)
        return self.training_until

    def train_until(self, end: float | None, elapsed: float) -> float:
        """Training's limit when it must end at the time.time() value `end` (None: no limit) and starts now
        with `elapsed` seconds of earlier training. Returns training_until."""
        self.training_until = 0.0 if end is None else elapsed + max(end - time.time(), 1.0)
        return self.training_until

    @property
    def limited(self) -> bool:
        """Whether training has a time limit."""
        return self.training_until > 0

    def progress(self, iteration: int, seconds: float) -> float:
        """The fraction of training done at `iteration` after `seconds` of training: of the iterations or
        of the time limit, whichever is further."""
        by_time = seconds / self.training_until if self.training_until > 0 else 0.0
        return max(iteration / self.iterations, by_time)

    def training_left(self, seconds: float) -> float:
        """Seconds of training left after `seconds` of it (inf without a limit)."""
        return self.training_until - seconds if self.training_until > 0 else math.inf

    def done(self, iteration: int) -> bool:
        """Whether training has reached its iterations."""
        return iteration >= self.iterations


def shard_times(seconds: float, start_time: float, after: float, refine_fraction: float) -> dict:
    """A sharded fit's times (time.time() values, the same on every rank; None without a budget of `seconds`
    from `start_time`): deadline; phase1_end, the end of every rank's own training; refine_end, the end of the
    joint refinement (`refine_fraction` of the training; None without one), which ends by its costs as
    measured then (tomgs.train.multigpu.rank); `after`, the seconds modelled for what follows the refinement."""
    if seconds <= 0:
        return dict(deadline=None, phase1_end=None, refine_end=None)
    now = time.time()
    deadline = start_time + seconds
    train_end = max(deadline - after, now + 2.0)
    return dict(deadline=deadline, phase1_end=now + (1 - refine_fraction) * (train_end - now),
                refine_end=train_end if refine_fraction > 0 else None, after_model=round(after, 3))


__all__ = ["UNTIL_BUDGET", "Budget", "asked_iterations", "asked_seconds", "budget_iterations", "shard_times"]
