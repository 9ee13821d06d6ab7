"""How many Gaussians a fit keeps: each Gaussian's importance over the clip against a float64 brute-force
sum, the quality rule's decisions, and fits at each quality level (the size in the log, "max" as before)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import tomgs
from tomgs.cameras import Cameras
from tomgs.io.scene import vertex_bytes
from tomgs.model import GaussianModel, stored_opacities, stored_scales, stored_t_scales
from tomgs.train import Trainer, preset
from tomgs.train.sparsify import QUALITY_RULES, Sparsifier, importance
from scenes import random_scene

CPU = torch.device("cpu")
GEOMETRY = ("means", "quats", "scales", "opacities", "t_means", "t_scales")


def tiny_clip(seed: int, frames: int = 4, n: int = 150, sh_degree: int = 0):
    """(model, cameras, uint8 frames [T,H,W,3]): random_scene's Gaussians (clusters, off screen, behind the
    camera, at the near plane; random temporal windows, some alive at one frame only) seen by a camera
    sliding sideways over `frames` frames at times k / (frames - 1), and frames of noise."""
    scene = random_scene(seed, n=n, sh_degree=sh_degree)
    g = torch.Generator().manual_seed(seed)
    t_scales = scene["t_scales"].clone()
    t_scales[: n // 5] = 0.02  # alive around one frame
    model = GaussianModel(
        means=scene["means"], quats=scene["quats"], log_scales=stored_scales(scene["scales"]),
        opacity_logits=stored_opacities(scene["opacities"]),
        sh_dc=(torch.rand(n, 1, 3, generator=g, dtype=torch.float64) - 0.5) * 3,
        sh_rest=torch.randn(n, (sh_degree + 1) ** 2 - 1, 3, generator=g, dtype=torch.float64) * 0.3,
        t_means=scene["t_means"], log_t_scales=stored_t_scales(t_scales), sh_degree=sh_degree)
    c2w = torch.linalg.inv(scene["viewmat"]).numpy()
    c2ws = np.stack([c2w.copy() for _ in range(frames)])
    c2ws[:, 0, 3] += np.linspace(-0.15, 0.15, frames)
    cameras = Cameras(c2w=c2ws, K=scene["K"].numpy(), width=scene["width"], height=scene["height"],
                      times=np.linspace(0.0, 1.0, frames), frame_indices=np.arange(frames))
    images = torch.randint(0, 256, (frames, scene["height"], scene["width"], 3), generator=g, dtype=torch.uint8)
    return model, cameras, images.numpy()


def brute_force_importance(model: GaussianModel, cameras: Cameras, weights=None) -> torch.Tensor:
    """float64 [N]: sum over frames and pixels of each Gaussian's blend weight alpha * T (times the pixel's
    loss weight), its temporal opacity at the frame's time inside alpha, by the dense float64 reference: the
    gradient of the (weighted) red channel's sum with respect to its red colour is exactly that sum."""
    inputs = {k: v.detach().double() for k, v in model.render_inputs().items() if k != "colors"}
    total = torch.zeros(len(model), dtype=torch.float64)
    for k in range(len(cameras)):
        ones = torch.ones(len(model), 3, dtype=torch.float64, requires_grad=True)
        viewmat = torch.linalg.inv(torch.as_tensor(cameras.c2w[k]))
        image, _, _ = tomgs.rasterize_reference(**inputs, colors=ones, viewmat=viewmat,
                                                K=torch.as_tensor(cameras.K), width=cameras.width,
                                                height=cameras.height, t=float(np.float32(cameras.times[k])))
        red = image[..., 0] if weights is None else image[..., 0] * torch.as_tensor(weights[k], dtype=torch.float64)
        red.sum().backward()
        total += ones.grad[:, 0]
    return total


@pytest.mark.parametrize("alive_index", [True, False])
@pytest.mark.parametrize("seed", range(3))
def test_importance_is_the_brute_force_sum_over_frames_and_pixels(seed, alive_index):
    """Fresh random scenes (seed 2: SH degree 1, whose colours differ per view, and loss weights that
    leave pixels unsupervised): the trainer's pass gives every Gaussian its float64 brute-force sum, those
    seen at no frame exactly 0, and the frames' PSNRs are the clip PSNR's."""
    sh_degree = 1 if seed == 2 else 0
    model, cameras, images = tiny_clip(seed, sh_degree=sh_degree)
    weights = None
    if seed == 2:
        weights = np.random.default_rng(seed).random(images.shape[:3]).astype(np.float32)
        weights[:, :, : images.shape[2] // 3] = 0.0  # a third of each frame unsupervised
        weights = np.rint(weights * 255) / 255  # as the trainer stores them (uint8)
    config = preset("quick", alive_index=alive_index, sh_degree=sh_degree)
    trainer = Trainer(images, cameras, np.zeros((0, 3)), np.zeros((0, 3), np.float32), config, CPU,
                      initial=(model, 1.0), weights=weights)
    got, psnrs = importance(trainer)
    want = brute_force_importance(trainer.model, cameras, weights)
    assert got.shape == want.shape == (len(model),)
    assert float(want.max()) > 1.0 and int((want == 0).sum()) > 0  # bright ones, and ones never seen
    torch.testing.assert_close(got.double(), want, rtol=1e-3, atol=1e-3 * float(want.max()))
    assert torch.equal(got == 0, want == 0)
    # the temporal factor: those alive around one frame gain nothing from the others
    one_frame = torch.arange(len(model)) < len(model) // 5
    assert float(want[one_frame].max()) > 0.1
    assert psnrs == pytest.approx(trainer.clip_psnr(), abs=1e-3)


def test_a_gaussian_is_judged_on_the_frames_it_is_alive_at():
    """One Gaussian in view at every frame, alive at one of four: its importance is its one frame's
    pixels' worth, o(t) * exp(-power) summed over the pixels, counted by hand in float64."""
    _, cameras, images = tiny_clip(0)
    c2w = torch.as_tensor(cameras.c2w[1])
    one = lambda value: torch.tensor([value], dtype=torch.float64)  # noqa: E731
    model = GaussianModel(means=(c2w[:3, :3] @ torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64) + c2w[:3, 3])[None],
                          quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]), log_scales=stored_scales(one(0.05)).repeat(1, 3)
                          .reshape(1, 3), opacity_logits=stored_opacities(one(0.3)), sh_dc=torch.zeros(1, 1, 3),
                          sh_rest=torch.zeros(1, 0, 3), t_means=one(cameras.times[1]),
                          log_t_scales=stored_t_scales(one(0.05)))  # dead a third of the clip away
    trainer = Trainer(images, cameras, np.zeros((0, 3)), np.zeros((0, 3), np.float32), preset("quick"), CPU,
                      initial=(model, 1.0))
    got, _ = importance(trainer)
    # by hand: the camera looks down +z at the mean 2 units ahead; EWA gives sigma_px = fx s / z, +0.3 px dilation
    K = cameras.K
    sx, sy = K[0, 0] * 0.05 / 2.0, K[1, 1] * 0.05 / 2.0
    a, c = sx * sx + 0.3, sy * sy + 0.3
    ys, xs = np.mgrid[0:cameras.height, 0:cameras.width] + 0.5
    dx, dy = K[0, 2] - xs, K[1, 2] - ys
    alpha = 0.3 * np.exp(-0.5 * (dx * dx / a + dy * dy / c))
    alpha = np.where(alpha >= 1 / 255, np.minimum(alpha, 0.99), 0.0)
    assert float(got[0]) == pytest.approx(float(alpha.sum()), rel=2e-3)


def rule(quality="default", **kw):
    return Sparsifier(preset("default", **dict(quality=quality, sparsify_share=0.25) | kw), pixels=800)


def test_rounds_are_spread_over_their_window_and_never_back_to_back():
    s = rule(sparsify_start_fraction=0.5, sparsify_stop_fraction=0.9, sparsify_rounds=4)
    assert [p for p in (0.0, 0.49, 0.5, 0.55, 0.6, 0.61, 0.85, 0.86, 0.95) if s.due(p)] == [0.5, 0.6, 0.85]
    # 0.7's slot passed while no step looked (a slow round): skipped, not taken late
    assert not rule(quality="max").due(0.6) and not rule(sparsify_rounds=0).due(0.6)


def test_the_rule_takes_a_prune_that_costs_less_than_the_level_allows_and_halves_the_share_after_one_it_refuses():
    s = rule()
    per_halving = QUALITY_RULES["default"].per_halving
    assert s.propose(10_000, 40.0) == 2_500
    halving = math.log2(10_000 / 7_500)
    assert s.judge(10_000, 2_500, 40.0, 40.0 - 0.9 * per_halving * halving)  # cheap enough: taken
    assert s.propose(7_500, 40.2) == 1_875
    assert not s.judge(7_500, 1_875, 40.2, 40.2 - 1.1 * per_halving * math.log2(7_500 / 5_625))  # too dear
    assert s.propose(7_500, 40.3) == 937 and not s.stopped  # half the share
    for remove, then in ((937, 468), (468, 234)):
        assert not s.judge(7_500, remove, 40.3, 30.0)
        assert s.propose(7_500, 40.3) == then
    assert not s.judge(7_500, 234, 40.3, 30.0) and "would cost" in s.stopped  # the share below MIN_SHARE
    assert s.propose(7_500, 40.3) == 0
    assert [c for c, _ in s.measured] == [10_000, 7_500, 7_500, 7_500, 7_500, 7_500]


def test_the_rule_refuses_a_prune_below_the_best_round_and_stops_at_the_floor():
    s = rule()
    in_all = QUALITY_RULES["default"].in_all
    assert s.propose(10_000, 40.0)
    assert s.judge(10_000, 2_500, 40.0, 40.0 - 0.1)
    assert s.propose(7_500, 40.0 - in_all + 0.05)  # recovered less than it lost: the next prune dips below
    assert not s.judge(7_500, 1_875, 40.0 - in_all + 0.05, 40.0 - in_all - 0.01)
    s = rule()
    count = 10_000
    while (remove := s.propose(count, 40.0)):
        assert s.judge(count, remove, 40.0, 40.0)
        count -= remove
    assert count == s.floor == 100 and "floor" in s.stopped  # 800 pixels / 8


def test_the_rules_state_round_trips():
    s = rule()
    s.due(0.6)
    s.judge(10_000, s.propose(10_000, 40.0), 40.0, 30.0)  # refused
    again = rule()
    again.load_state_dict(s.state_dict())
    assert again.state_dict() == s.state_dict() and again.share == 0.125 and not again.due(0.6) and again.due(0.7)


def fit(quality: str, iterations: int = 300, **kw):
    from tests.train.test_train import small_config, synthetic_clip

    images, cams, points, colors = synthetic_clip(4, 48, 27)
    torch.manual_seed(0)
    trainer = Trainer(images, cams, points, colors, small_config(iterations, quality=quality, **kw), CPU)
    return trainer, trainer.run()


def test_the_default_quality_keeps_fewer_gaussians_and_logs_their_size():
    """The default prunes by importance in rounds whose clip PSNR the log carries; "max" takes no round.
    Every row gives the scene file's bytes for its Gaussians."""
    full_trainer, full = fit("max")
    trainer, thin = fit("default")
    assert full_trainer.sparsifier.measured == [] and len(trainer.sparsifier.measured) >= 3
    assert len(thin.model) < 0.8 * len(full.model)
    assert thin.clip_psnr > full.clip_psnr - 3.0
    # the log's clip PSNRs: the first step's (eval_interval_s is 1e9), each round's, the end's
    measured = [r for r in thin.history if r["clip_psnr"] != ""][1:-1]
    assert [(r["gaussians"], r["clip_psnr"]) for r in measured] == [
        (c, round(p, 3)) for c, p in trainer.sparsifier.measured]
    for result in (full, thin):
        assert all(r["scene_bytes"] == vertex_bytes(r["gaussians"], 0) for r in result.history)
        assert result.history[-1]["gaussians"] == len(result.model)


def test_under_a_time_limit_the_rounds_cost_at_most_their_share_of_the_training():
    """A round costs ROUND_PASSES passes over the clip: under a limit it waits until the rounds taken and it
    fit in ROUND_OVERHEAD of the training so far (a 289-frame 720p clip's eight took a third of a minute's
    training); a fit by iterations alone (no limit) takes every round on its slot."""
    from tomgs.train.budget import Budget
    from tomgs.train.loop import RunHooks, TrainingRun
    from tomgs.train.plan import ROUND_OVERHEAD, ROUND_PASSES

    trainer, _ = fit("default", 1)
    run = TrainingRun(trainer, Budget(training_until=60.0), RunHooks())
    round_seconds = ROUND_PASSES * 0.01 * trainer.num_frames  # a frame of the clip PSNR takes 10 ms
    assert not run.round_affordable(0.9 * round_seconds / ROUND_OVERHEAD, 0.01)
    assert run.round_affordable(1.1 * round_seconds / ROUND_OVERHEAD, 0.01)
    trainer.sparsifier.seconds = 2 * round_seconds  # two taken: the third waits until three are affordable
    assert not run.round_affordable(2.9 * round_seconds / ROUND_OVERHEAD, 0.01)
    assert run.round_affordable(3.1 * round_seconds / ROUND_OVERHEAD, 0.01)
    state = trainer.sparsifier.state_dict()
    again, _ = fit("default", 1)
    again.sparsifier.load_state_dict(state)
    assert again.sparsifier.seconds == 2 * round_seconds


def test_the_cli_offers_the_quality_levels_and_refuses_others(tmp_path):
    from click.testing import CliRunner

    from tomgs.cli import main
    from tomgs.train.config import QUALITIES

    fit_command = main.commands["fit"]
    option = next(p for p in fit_command.params if p.name == "quality")
    assert tuple(option.type.choices) == QUALITIES == tuple(QUALITY_RULES)
    result = CliRunner().invoke(main, ["fit", str(tmp_path / "none.mp4"), "-o", str(tmp_path / "s.ply"),
                                       "--quality", "best"])
    assert result.exit_code == 2 and "best" in result.output
    with pytest.raises(ValueError, match="quality must be one of compact, default, max"):
        preset("default", quality="best")
