"""A fit's time (tomgs.train.budget): the one reader of max_seconds and the iteration stop, the deadline,
what training may take, progress, and a sharded fit's times."""

from __future__ import annotations

import math
import time

import pytest

from tomgs.train import preset
from tomgs.train.budget import UNTIL_BUDGET, Budget, budget_iterations, shard_times
from tomgs.train.plan import make_plan


def test_a_budget_asked_for_trains_until_it_unless_the_iterations_were_asked_for_too():
    assert budget_iterations(preset("quick")) == 600  # no budget: the iterations
    assert budget_iterations(preset("quick", max_seconds=60.0)) == UNTIL_BUDGET
    assert budget_iterations(preset("quick", max_seconds=60.0, stop_at_iterations=True)) == 600


def test_the_plan_makes_the_budget_from_the_start():
    plan, config = make_plan(preset("quick", max_seconds=90.0), 40, 96, 160, 96 * 160, "cpu")
    started = time.perf_counter() - 10.0  # the command started 10 s ago
    budget = plan.budget_from(started)
    assert (budget.seconds, budget.iterations, budget.started) == (90.0, config.iterations, started)
    assert budget.iterations == UNTIL_BUDGET and budget.deadline == started + 90.0
    assert 79.0 < budget.left() <= 80.0


def test_training_takes_what_the_deadline_leaves_less_the_reserve_and_at_least_a_second():
    budget = Budget(60.0, 1000, started=time.perf_counter() - 20.0)
    limit = budget.train_for(elapsed=5.0, reserve=2.0)  # a resume: 5 s trained before
    assert limit == budget.training_until and 5.0 + 37.0 < limit <= 5.0 + 38.0 and budget.limited
    late = Budget(60.0, 1000, started=time.perf_counter() - 100.0)  # past its deadline already
    assert late.train_for(elapsed=0.0, reserve=2.0) == 1.0
    none = Budget(0.0, 1000)
    assert none.train_for(elapsed=3.0, reserve=2.0) == 0.0 and not none.limited and none.deadline is None
    assert none.left() == math.inf and none.training_left(100.0) == math.inf


def test_progress_is_the_further_of_iterations_and_time():
    budget = Budget(iterations=1000, training_until=100.0)
    assert budget.progress(100, 50.0) == 0.5 and budget.progress(800, 50.0) == 0.8
    assert Budget(iterations=1000).progress(250, 1e6) == 0.25  # no limit: by iterations alone
    assert budget.training_left(30.0) == 70.0 and budget.done(1000) and not budget.done(999)


def test_a_trainer_alone_reads_max_seconds_as_its_training_time():
    budget = Budget.of_training(preset("quick", max_seconds=12.5))
    assert (budget.iterations, budget.training_until, budget.seconds) == (600, 12.5, 0.0)


def test_a_phase_ends_at_a_wall_clock_time():
    budget = Budget(iterations=10)
    assert 6.9 < budget.train_until(time.time() + 5.0, elapsed=2.0) <= 7.0
    assert budget.train_until(time.time() - 5.0, elapsed=2.0) == 3.0  # already past: a second
    assert budget.train_until(None, elapsed=2.0) == 0.0


def test_a_sharded_fit_splits_the_training_between_phase_1_and_the_refinement():
    start = time.time()
    times = shard_times(100.0, start, after=10.0, refine_fraction=0.2)
    train_end = start + 90.0
    assert times["deadline"] == start + 100.0 and times["refine_end"] == pytest.approx(train_end)
    now = times["phase1_end"] - 0.8 * (train_end - times["phase1_end"]) / 0.2  # phase 1: 80% of what is left
    assert abs(now - start) < 1.0
    assert shard_times(0.0, start, 10.0, 0.2) == dict(deadline=None, phase1_end=None, refine_end=None)
    assert shard_times(100.0, start, 10.0, 0.0)["refine_end"] is None
