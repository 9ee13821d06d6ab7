"""Growth in stages (tomgs.train.growth): a stage ends when its training PSNR settles or its window runs
out, the limit doubles while a stage's Gaussians take away at least the quality's price of squared error
each, and a fit's trainer follows it."""

from __future__ import annotations

import math

import pytest

from tomgs.train import preset
from tomgs.train.config import START_SHARE
from tomgs.train.growth import MAX_STAGES, SETTLE_DB, SETTLE_INTERVALS, Growth, squared_error
from tomgs.train.sparsify import QUALITY_RULES

PRICE = QUALITY_RULES["default"].per_gaussian


def growth(quality="default", start=1000, cap=64_000, pixels=1e6, **kw):
    config = preset("default", quality=quality, max_gaussians=cap, densify_start_fraction=0.0,
                    densify_stop_fraction=0.6, **kw)
    return Growth(config, start, pixels)


def settle(g: Growth, progress: float, count: int, psnr: float) -> str | None:
    """Intervals at the limit with a flat training PSNR until the stage ends: what it returned."""
    for _ in range(SETTLE_INTERVALS + 1):
        done = g.update(progress, count, True, psnr)
    return done


def psnr_taking_away(psnr: float, worth: float, added: int, pixels: float) -> float:
    """The PSNR after `added` Gaussians each took `worth` of the clip's squared error away from `psnr`."""
    return -10 * math.log10(squared_error(psnr) - worth * added / pixels)


def test_the_limit_doubles_while_a_stage_pays_and_growth_stops_where_the_next_would_not():
    g = growth()
    assert g.staged and g.limit == 2000
    assert g.update(0.1, 1500, False, 20.0) is None  # not at the limit yet: no stage ends
    assert settle(g, 0.1, 2000, 20.0) == "grow" and g.limit == 4000  # the first stage always pays
    # each later stage takes away 4x, then 3x (expected of the next: 3 * 3 / 4), then 0.9x the price per Gaussian
    psnr, count = 20.0, 2000
    for ratio, expected in ((4.0, "grow"), (3.0, "grow"), (0.9, "stop")):
        psnr, count = psnr_taking_away(psnr, ratio * PRICE, count, 1e6), 2 * count
        assert settle(g, 0.2, count, psnr) == expected
        assert g.stages[-1][2] == pytest.approx(ratio * PRICE, rel=1e-6)
    assert g.limit == 16_000 and not g.staged and "under the price" in g.stopped
    assert g.update(0.3, 16_000, True, 40.0) is None  # stopped: nothing more


def test_growth_stops_where_the_stages_worth_falls_fast_even_above_the_price():
    g = growth()
    settle(g, 0.1, 2000, 20.0)
    psnr = psnr_taking_away(20.0, 8 * PRICE, 2000, 1e6)
    assert settle(g, 0.1, 4000, psnr) == "grow"
    psnr = psnr_taking_away(psnr, 1.5 * PRICE, 4000, 1e6)  # above the price, but the next: 1.5 * 1.5 / 8
    assert settle(g, 0.1, 8000, psnr) == "stop" and g.limit == 8000


def test_a_stage_ends_when_the_psnr_settles_or_when_its_window_runs_out():
    g = growth()
    climbing = [20.0 + 2 * SETTLE_DB * k for k in range(40)]  # never settles
    window = 0.6 / MAX_STAGES
    assert all(g.update(0.1, 2000, True, p) is None for p in climbing[:10])  # within the window
    assert g.update(0.1 + window, 2000, True, climbing[10]) == "grow"  # the window ran out
    g = growth()
    flat = [20.0] * (SETTLE_INTERVALS + 1)
    assert [g.update(0.1, 2000, True, p) for p in flat] == [None] * SETTLE_INTERVALS + ["grow"]


def test_max_quality_and_a_reached_cap_take_no_stage():
    g = growth("max")
    assert g.limit == 64_000 and not g.staged and settle(g, 0.1, 64_000, 20.0) is None
    g = growth(cap=3000)
    assert g.limit == 2000 and settle(g, 0.1, 2000, 20.0) == "grow" and g.limit == 3000 and not g.staged


def test_the_state_round_trips():
    g = growth()
    settle(g, 0.1, 2000, 20.0)
    g.update(0.2, 4000, True, 25.0)
    again = growth()
    again.load_state_dict(g.state_dict())
    assert again.state_dict() == g.state_dict()


def test_a_checkpoint_from_before_the_stages_resumes_grown_to_its_cap():
    """A checkpoint without the growth's state (or the densifier's limit) was grown toward the cap: its resume
    takes no stage, which would have put the limit back to twice the start."""
    from tests.train.test_sparsify import fit

    trainer, _ = fit("default", 30, max_gaussians=12_000)
    state = trainer.state_dict()
    del state["growth"], state["densifier"]["limit"]
    resumed, _ = fit("default", 1, max_gaussians=12_000)
    assert resumed.growth.staged
    resumed.load_checkpoint(state)
    assert resumed.densifier.limit == resumed.growth.limit == 12_000 and not resumed.growth.staged


def test_a_gpu_fit_below_max_starts_from_a_share_of_its_cap():
    for quality, wanted in (("max", 48_000), ("default", int(10_000_000 * START_SHARE) // 90)):
        config = preset("default", quality=quality, max_gaussians=10_000_000)
        assert config.points_per_frame(854 * 480, 90, "cuda") == wanted
        assert config.points_per_frame(854 * 480, 90, "cpu") == 2000  # a CPU's start is its own


def test_a_fit_below_max_grows_in_stages_within_each_limit():
    """The trainer hands the rule each interval's training PSNR (every Gaussian hot, so growth is quick): the
    default's stages end at their limits, each twice the last, and its notes say so; at "max" the densifier's
    limit is the cap."""
    from tests.train.test_sparsify import fit

    hot = dict(densify_stop_fraction=0.9, max_gaussians=12_000, grad_threshold=1e-7, densify_interval=25,
               sparsify_rounds=0)  # no prune rounds inside this long growth window
    trainer, result = fit("default", 200, **hot)
    stages = trainer.growth.stages
    assert len(stages) >= 3 and trainer.densifier.limit == trainer.growth.limit
    assert all(count <= 2 ** k * stages[0][0] for k, (count, _, _) in enumerate(stages))
    assert any(note.startswith("growth in stages: ") for note in result.notes)
    trainer, _ = fit("max", 1, **hot)
    assert not trainer.growth.staged and trainer.densifier.limit == 12_000


def test_a_falling_psnr_is_not_settled():
    """Right after its splits a stage's training PSNR falls, then climbs back: a flat or falling stretch
    inside that dip does not end the stage."""
    g = growth()
    dip = [20.0, 19.0, 18.5, 18.4, 18.4, 18.4, 18.4, 18.4, 18.4]  # fell 1.6 dB, then flat at the bottom
    assert all(g.update(0.1, 2000, True, p) is None for p in dip)
    climb = [18.4 + 0.5 * k for k in range(1, 5)] + [20.5] * (SETTLE_INTERVALS + 1)
    done = [g.update(0.1, 2000, True, p) for p in climb]
    assert done[-1] == "grow" and done[:-1] == [None] * (len(climb) - 1)


def test_a_negative_worth_waits_and_never_grows():
    """A stage whose PSNR is below the last stage's is inside its dip: it waits for the PSNR to come back
    (a later settled reading prices it); when its window runs out first, growth stops and says why. The
    ratio of a negative worth to the last one's turns no negative worth positive."""
    g = growth()
    settle(g, 0.1, 2000, 20.0)
    psnr = psnr_taking_away(20.0, 8 * PRICE, 2000, 1e6)
    assert settle(g, 0.1, 4000, psnr) == "grow"
    assert settle(g, 0.11, 8000, psnr - 0.5) is None  # settled below the last stage: no price read
    assert g.staged and g.limit == 8000 and g.stages[-1][0] == 4000
    window = 0.6 / MAX_STAGES
    assert g.update(0.11 + window, 8000, True, psnr - 0.5) == "stop"
    assert not g.staged and g.limit == 8000 and "had not won back its training PSNR" in g.stopped
    assert g.stages[-1][2] < 0


def test_a_worth_shrinking_faster_than_the_last_expects_less_never_more():
    g = growth()
    settle(g, 0.1, 2000, 20.0)
    psnr = psnr_taking_away(20.0, 4 * PRICE, 2000, 1e6)
    settle(g, 0.1, 4000, psnr)
    psnr = psnr_taking_away(psnr, 2.2 * PRICE, 4000, 1e6)  # about half the last worth: the next at about a quarter
    assert settle(g, 0.1, 8000, psnr) == "grow"  # 2.2 * 2.2 / 4 = 1.21 x the price
    psnr = psnr_taking_away(psnr, 3 * PRICE, 8000, 1e6)  # grew against the trend: expected at most its own worth
    assert settle(g, 0.1, 16000, psnr) == "grow" and g.stages[-1][2] == pytest.approx(3 * PRICE, rel=1e-6)
