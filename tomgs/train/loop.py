"""A Trainer's run (Trainer.run): its steps, and after each the cadences, in this order:

    growth        every densify_interval steps of a fit growing in stages (Trainer.grow)
    quality       a round of the quality rule (tomgs.train.sparsify) when due, settled after the last change,
                  and affordable under a time limit
    budget        the end: the iterations, or the time limit less what the end costs (at most END_SHARE of it)
    measurement   the clip PSNR every eval_interval_s (further apart when slow; never right after a change),
                  over evenly spaced frames while every frame would cost too much; every frame at the end
    log           a CSV row every log_interval steps and with every measurement or round
    stop          SIGINT / SIGTERM: the step just finished saved, FitInterrupted raised
    checkpoint    every checkpoint_interval_s of training, written by a thread while training goes on

Times are seconds of training (a resumed run's earlier ones included), as the Budget counts them.
"""

from __future__ import annotations

import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from tomgs.errors import counted
from tomgs.train.budget import Budget
from tomgs.train.checkpoint import CheckpointWriter, FitInterrupted, StopSignals
from tomgs.train.log import write_csv
from tomgs.train.plan import COMPACT_SHARE, EVAL_OVERHEAD, ROUND_OVERHEAD, ROUND_PASSES
from tomgs.train.sparsify import take_round

# A save may cost at most this fraction of the training time: with slow saves (millions of
# Gaussians, a slow disk) checkpoints are spaced to 1 / CHECKPOINT_OVERHEAD times a save's duration.
CHECKPOINT_OVERHEAD = 0.05
CHEAP_EVAL = 1.0  # seconds: a measurement this quick is taken whenever it is due
# Before the last, a measurement the run cannot yet pay for in full covers evenly spaced frames: as
# many as EVAL_OVERHEAD allows, or up to EVAL_FRAMES that take CHEAP_EVAL, never fewer than
# MIN_EVAL_FRAMES (a long clip's curve starts in its first minute)
EVAL_FRAMES = 64
MIN_EVAL_FRAMES = 8
# A budget's end (the compaction and the last clip PSNR) keeps at most this share of the training time: when
# they would cost more, the compaction is left out and the last measurement covers evenly spaced frames
END_SHARE = 0.1
RENDER_SHARE = 0.5  # a forward render's time over a training step's, until a measurement says


@dataclass
class RunHooks:
    """Where a run saves and whom it tells. checkpoint: the periodic and interrupted saves' path (None:
    none). log_csv: the CSV log, rewritten at each row. progress(row): each CSV row (a KeyboardInterrupt
    it raises stops the run like Ctrl-C). tick(iteration, seconds, text): after every step and every
    frame measured, a display's heartbeat."""

    checkpoint: Path | None = None
    log_csv: Path | None = None
    progress: Callable | None = None
    tick: Callable | None = None


def eval_frames(count: int, now: float, frame_seconds: float) -> int:
    """How many of `count` frames a clip PSNR taken `now` seconds into the run covers when a frame takes
    `frame_seconds`: all when that is under CHEAP_EVAL or EVAL_OVERHEAD of the run so far; else what
    EVAL_OVERHEAD pays for, or up to EVAL_FRAMES that take CHEAP_EVAL, whichever is more; 0 (wait) while
    that is under MIN_EVAL_FRAMES."""
    if frame_seconds * count < CHEAP_EVAL or EVAL_OVERHEAD * now >= frame_seconds * count:
        return count
    wanted = max(int(EVAL_OVERHEAD * now / frame_seconds), min(int(CHEAP_EVAL / frame_seconds), EVAL_FRAMES))
    return min(wanted, count) if wanted >= min(MIN_EVAL_FRAMES, count) else 0


def spread(total: int, count: int) -> np.ndarray:
    """int [count]: `count` of `total` frames evenly spaced, the first and last among them (count >= 1)."""
    return np.unique(np.linspace(0, total - 1, count).round().astype(np.int64))


class TrainingRun:
    """One call of Trainer.run: the trainer, its Budget and RunHooks, and the cadences' clocks."""

    def __init__(self, trainer, budget: Budget, hooks: RunHooks):
        c = trainer.config
        self.trainer, self.budget, self.hooks = trainer, budget, hooks
        self.tick = hooks.tick or (lambda iteration, seconds, text: None)
        self.start = time.perf_counter() - trainer.elapsed
        measured = [r["wall_s"] for r in trainer.history if r["clip_psnr"] != ""]  # a resume keeps the schedule
        self.next_eval = measured[-1] + c.eval_interval_s if measured else 0.0
        self.next_checkpoint = trainer.elapsed + c.checkpoint_interval_s  # nothing to lose at the first step
        checkpoint = hooks.checkpoint
        self.saved = Path(checkpoint) if checkpoint is not None and Path(checkpoint).is_file() else None
        self.settle = max(c.densify_interval // 2, 1)
        self.step_seconds = None  # running mean of a step's time (the first, which loads kernels, left out)
        self.failures = {}  # what could not be written: "log" / "checkpoint" -> (times, the latest OSError)
        self.began_at = trainer.elapsed  # training seconds before this run (a resume's)
        self.writer = self.stop = None

    def run(self):
        """Train to the budget's iterations or time limit; the trainer's FitResult."""
        trainer = self.trainer
        # the periodic checkpoints are written while training goes on; leaving the block waits for the last
        with CheckpointWriter() as self.writer, \
                StopSignals(checkpoint=lambda: self.writer.done or self.saved) as self.stop:
            while not self.budget.done(trainer.iteration):
                now = self.step()
                if trainer.iteration % trainer.config.densify_interval == 0:
                    trainer.grow()
                rounded = self.quality_round(now)
                out_of_time, last, count = self.ending(now)
                self.measure_and_log(now, last, count, rounded)
                if self.stop.signum is not None:
                    self.stop_here(self.stop.signum)
                self.checkpoint_when_due()
                if out_of_time:
                    self.note_time_limit()
                    break
        self.count_failed()
        self.note_failures()
        if self.stop.signum is not None:  # arrived after the loop's last look: still a step boundary
            self.stop_here(self.stop.signum)
        trainer.elapsed = time.perf_counter() - self.start
        return trainer.run_result()

    def clock(self) -> float:
        """Seconds of training now."""
        return time.perf_counter() - self.start

    def say(self, text: str) -> None:
        """`text` to the tick, at this step and time."""
        self.tick(self.trainer.iteration, self.clock(), text)

    # -- the cadences ---------------------------------------------------------------------------

    def step(self) -> float:
        """A training step at the budget's progress; returns the seconds of training after it."""
        trainer = self.trainer
        before = self.clock()
        trainer.progress = self.budget.progress(trainer.iteration, before)
        trainer.step()
        now = self.clock()
        if trainer.iteration > 1:
            self.step_seconds = now - before if self.step_seconds is None else \
                0.9 * self.step_seconds + 0.1 * (now - before)
        self.tick(trainer.iteration, now, trainer.status())
        return now

    def frame_seconds(self) -> float:
        """A frame of the clip PSNR's seconds: the last measurement's, or RENDER_SHARE of a step's before one."""
        return self.trainer.eval_frame_seconds or RENDER_SHARE * (self.step_seconds or 0.0)

    def settled(self) -> bool:
        """Whether the clip PSNR has settled since the last densification, prune or reset (it dips by 2-3 dB for a
        few dozen steps after one, a saw-tooth of the schedule rather than of the fit)."""
        return self.trainer.iteration - self.trainer.densifier.changed_at >= self.settle

    def quality_round(self, now: float) -> tuple | None:
        """A round of the quality rule when it is due, settled and affordable: (the clip PSNR it measured, the frames,
        the Gaussians before it), or None."""
        trainer, sparsifier = self.trainer, self.trainer.sparsifier
        frame_seconds = self.frame_seconds()
        if not (self.settled() and self.round_fits(self.budget.training_left(now), frame_seconds)
                and (not self.budget.limited or self.round_affordable(now, frame_seconds))
                and sparsifier.due(trainer.progress)):
            return None
        size = len(trainer.model)
        began = time.perf_counter()
        measured = take_round(trainer, sparsifier, lambda text: self.tick(trainer.iteration, now, text))
        sparsifier.seconds += time.perf_counter() - began
        if measured is None:
            return None
        self.next_eval = now + max(trainer.config.eval_interval_s, (time.perf_counter() - began) / EVAL_OVERHEAD)
        return (*measured, size)

    def end_costs(self, frame_seconds: float) -> tuple[float, float]:
        """(the compaction's, the last full clip PSNR's) estimated seconds, a frame of the clip PSNR taking
        `frame_seconds`."""
        trainer = self.trainer
        full = frame_seconds * trainer.num_frames
        return (COMPACT_SHARE * full if trainer.config.compact_pixels > 0 else 0.0), full

    def round_fits(self, left: float, frame_seconds: float) -> bool:
        """Whether a round of the quality rule (ROUND_PASSES clip PSNRs) and the run's end fit in the `left`
        seconds of the limit (inf: none), once the rounds' window has come; the first that does not ends
        the rounds, said in the notes."""
        trainer, sparsifier = self.trainer, self.trainer.sparsifier
        full = frame_seconds * trainer.num_frames
        if not sparsifier.active or trainer.progress < sparsifier.start or \
                ROUND_PASSES * full + sum(self.end_costs(frame_seconds)) <= left:
            return True
        if not sparsifier.stopped:
            sparsifier.stopped = "the time left"
            trainer.notes.append(f"quality rounds left out from {left:.0f} s before the time limit: a round (~"
                                 f"{ROUND_PASSES * full:.0f} s) and the end did not fit (--quality max keeps every "
                                 f"Gaussian without them)")
        return False

    def round_affordable(self, now: float, frame_seconds: float) -> bool:
        """Under a time limit, whether the rounds taken so far and the next (ROUND_PASSES clip PSNRs) cost at most
        ROUND_OVERHEAD of the `now` seconds trained (a round of a long clip takes seconds). A round that waits
        takes the slot due when it is affordable; the slots passed meanwhile are skipped."""
        trainer = self.trainer
        return trainer.sparsifier.seconds + ROUND_PASSES * frame_seconds * trainer.num_frames <= ROUND_OVERHEAD * now

    def ending(self, now: float) -> tuple[bool, bool, int]:
        """(out of time, the last step, the frames a clip PSNR taken now covers): the run ends at its
        iterations, or where its end (`end`) would reach the time limit; at the last step the end runs here."""
        trainer, budget = self.trainer, self.budget
        frame_seconds = self.frame_seconds()
        costs = self.end_costs(frame_seconds)
        out_of_time = budget.limited and budget.training_until <= now + min(sum(costs),
                                                                            END_SHARE * budget.training_until)
        last = trainer.iteration == budget.iterations or out_of_time
        count = eval_frames(trainer.num_frames, now, frame_seconds)
        if last:
            count = self.end(budget.training_left(now), frame_seconds, now)
        return out_of_time, last, count

    def end(self, left: float, frame_seconds: float, now: float) -> int:
        """The end of a run with `left` seconds of its limit (inf: none): the compaction, when it fits with a
        clip PSNR of MIN_EVAL_FRAMES frames beside it, then the frames the last clip PSNR can cover in what
        remains (every frame when it fits, else evenly spaced ones); what was cut short goes in the notes.
        Returns that frame count."""
        trainer = self.trainer
        compact, full = self.end_costs(frame_seconds)
        if compact and compact + frame_seconds * min(MIN_EVAL_FRAMES, trainer.num_frames) <= left:
            trainer.compact(lambda text: self.tick(trainer.iteration, now, text))
            left -= compact
        elif compact:
            trainer.notes.append(f"kept every Gaussian: leaving out those that no frame shows (~{compact:.0f} s) "
                                 f"did not fit in the {max(left, 0):.0f} s the budget left")
        if full <= left:
            return trainer.num_frames
        count = min(max(int(left / max(frame_seconds, 1e-9)), 1), trainer.num_frames)
        trainer.notes.append(f"the final clip PSNR covers {counted(count, 'evenly spaced frame')} of "
                             f"{trainer.num_frames}: the budget left {max(left, 0):.0f} s for it (`tomgs eval` "
                             f"measures every frame)")
        return count

    def measure_and_log(self, now: float, last: bool, count: int, rounded: tuple | None) -> None:
        """The clip PSNR when due (and at the last step), and a CSV row at the log's cadence, with a
        measurement or after a round."""
        trainer, c = self.trainer, self.trainer.config
        measure = last or (now >= self.next_eval and count > 0 and self.settled())
        if not (trainer.iteration % c.log_interval == 0 or measure or rounded):
            return
        clip, size = None, None
        if rounded and not measure:  # the round's pass measured the clip before its prune
            clip, size = rounded[:2], rounded[2]
        if measure:
            frames = None if count == trainer.num_frames else spread(trainer.num_frames, count)
            began = time.perf_counter()
            values = trainer.clip_psnr(lambda text: self.tick(trainer.iteration, now, text), frames)
            seconds = time.perf_counter() - began
            clip, trainer.eval_frame_seconds = (float(np.mean(values)), len(values)), seconds / len(values)
            self.next_eval = now + max(c.eval_interval_s, seconds / EVAL_OVERHEAD)
        if last:
            trainer.flush_measurements()  # no draw follows: the last row has every step's PSNR
        row = trainer.log_row(now, clip, size)
        trainer.history.append(row)
        if self.hooks.log_csv is not None:
            self.write_log()
        if self.hooks.progress is not None:
            try:
                self.hooks.progress(row)
            except KeyboardInterrupt:  # the caller's Ctrl-C, also at a step boundary
                self.stop.request(signal.SIGINT)

    def write_log(self) -> None:
        """The CSV log as of now; a write that fails (a full disk) is noted, and training goes on."""
        try:
            write_csv(self.hooks.log_csv, self.trainer.history)
        except OSError as e:
            self.failures["log"] = (self.failures.get("log", (0,))[0] + 1, e)

    def checkpoint_when_due(self) -> None:
        """A checkpoint every checkpoint_interval_s of training, spaced so that what training waits for costs
        at most CHECKPOINT_OVERHEAD of it."""
        trainer, checkpoint = self.trainer, self.hooks.checkpoint
        if checkpoint is None or self.clock() < self.next_checkpoint:
            return
        trainer.elapsed = self.clock()
        self.tick(trainer.iteration, trainer.elapsed, "saving a checkpoint")
        began = time.perf_counter()
        trainer.checkpoint_in_background(checkpoint, self.writer)
        self.count_failed()
        cost = time.perf_counter() - began  # what training waited for
        self.next_checkpoint = self.clock() + max(trainer.config.checkpoint_interval_s, cost / CHECKPOINT_OVERHEAD)

    def count_failed(self) -> None:
        """Count the checkpoint the writer could not write (a full disk: training goes on) and say it."""
        self.writer.wait()
        if self.writer.failed is not None:
            error, self.writer.failed = self.writer.failed, None
            self.failures["checkpoint"] = (self.failures.get("checkpoint", (0,))[0] + 1, error)
            self.tick(self.trainer.iteration, self.trainer.elapsed, f"checkpoint not written ({error.strerror})")

    def stop_here(self, signum) -> None:
        """Save the step just finished (a step boundary) and raise FitInterrupted; when that save fails (a full
        disk), the last complete checkpoint is the one to resume."""
        trainer, checkpoint = self.trainer, self.hooks.checkpoint
        if checkpoint is None:
            raise FitInterrupted(None, signum)
        self.writer.wait()
        trainer.elapsed = self.clock()
        try:
            trainer.save_checkpoint(checkpoint)
        except OSError as e:
            raise FitInterrupted(self.writer.done or self.saved, signum,
                                 unsaved=f"{e.filename}: {e.strerror}") from None
        raise FitInterrupted(checkpoint, signum, trainer.iteration)

    def note_time_limit(self) -> None:
        limit, began_at = self.budget.training_until, self.began_at
        this_run = f"{limit - began_at:.0f} s of training in this run, {limit:.0f} s in all" \
            if began_at > 0 else f"{limit:.0f} s"
        self.trainer.notes.append(f"training stopped after {counted(self.trainer.iteration, 'iteration')} at its "
                                  f"time limit ({this_run})")

    def note_failures(self) -> None:
        last = self.writer.done or self.saved
        for what, (times, error) in self.failures.items():
            kept = f"; the last complete one is {last}" if what == "checkpoint" and last else ""
            self.trainer.notes.append(f"the {what} could not be written {times} time{'s' if times > 1 else ''} "
                                      f"({error.filename}: {error.strerror}): training went on{kept}")


__all__ = ["CHECKPOINT_OVERHEAD", "END_SHARE", "RunHooks", "TrainingRun", "eval_frames", "spread"]
