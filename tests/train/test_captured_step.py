"""tomgs.train.captured_step: a training step replayed from a CUDA graph (issued from Python on a CPU)
updates what the eager step updates, binds the model, Adam and the densifier to memory of its own across
densifications and checkpoints, drops a step whose keys overflowed (and learns the bound), refuses a
frame outside the renderer's contract, and falls back where it cannot serve."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from tomgs.render.captured import remember_total
from tomgs.errors import InputError, RenderError
from tomgs.train import Trainer
import tomgs.train.captured_step as captured_step
from tomgs.train.captured_step import (RING, CapturedStep, keys_capacity, keys_fit, keys_needed, rows_capacity,
                                       rows_fit, unsupported)
from scenes import devices
from tests.train.test_train import CPU, small_config, synthetic_clip

DEVICES = devices()
CLIP = {}  # the tests' clip, made once


def clip():
    if not CLIP:
        CLIP["clip"] = synthetic_clip(4, 40, 24)
    return CLIP["clip"]


def pair(device: str, **settings):
    """(eager trainer, captured trainer) of one seeded start, a GPU's step settings on any device."""
    images, cams, points, colors = clip()
    base = dict(sparse_adam=True, alive_index=False) | settings
    trainers = tuple(Trainer(images, cams, points, colors, small_config(200, captured_step=captured, **base),
                             torch.device(device)) for captured in (False, True))
    # turned and stretched alike: an isotropic start's rotations take gradients of rounding noise alone
    g = torch.Generator().manual_seed(3)
    n = len(trainers[0].model)
    turn, stretch = 0.3 * torch.randn(n, 4, generator=g), 0.4 * torch.randn(n, 3, generator=g)
    for trainer in trainers:
        with torch.no_grad():
            trainer.model.quats.add_(turn.to(device))
            trainer.model.log_scales.add_(stretch.to(device))
    return trainers


def state_of(trainer: Trainer) -> dict:
    """Parameters, Adam moments and step counts, the densifier's statistics: copies on the host."""
    out = {}
    for group in trainer.optimizer.param_groups:
        (p,) = group["params"]
        state = trainer.optimizer.state.get(p, {})
        out[group["name"]] = p.detach().cpu().clone()
        for key in ("exp_avg", "exp_avg_sq"):
            out[f"{group['name']}.{key}"] = state[key].cpu().clone() if key in state else torch.zeros_like(p).cpu()
        out[f"{group['name']}.step"] = float(state.get("step", 0.0))
    for key, value in trainer.densifier.statistics().items():
        out[f"densifier.{key}"] = value.cpu().clone()
    return out


def assert_same(got: dict, want: dict, device: str, exact: bool = True):
    """The captured trainer's state against the eager one's: bit for bit on a CPU (same kernels, one thread)
    where `exact`, else to float32 rounding. On a GPU the gradients sum by atomics in no fixed order:
    moments and statistics to 1e-3 of their norm, parameters to 1e-3 but for 2% of their elements (an Adam
    step of eps 1e-15 is about lr times the gradient's sign, which a gradient summing to nearly zero may
    flip)."""
    assert got.keys() == want.keys()
    for key, value in want.items():
        if isinstance(value, float):
            assert got[key] == value, key
        elif device == "cpu" and exact:
            assert torch.equal(got[key], value), key
        elif device == "cpu":
            scale = float(value.abs().max()) if value.numel() else 0.0
            torch.testing.assert_close(got[key], value, rtol=1e-3, atol=1e-3 * scale + 1e-7, msg=key)
        elif "." in key:
            assert float((got[key] - value).norm()) <= 1e-3 * float(value.norm()) + 1e-12, key
        else:
            apart = ~torch.isclose(got[key], value, rtol=1e-3, atol=1e-5)
            assert int(apart.sum()) <= max(2, value.numel() // 50), (key, int(apart.sum()), value.numel())


def step_both(eager: Trainer, captured: Trainer, steps: int = 1):
    for _ in range(steps):
        eager.step()
        captured.step()


def test_capacities_hold_the_model_and_its_frames():
    assert rows_capacity(1000, 10**6, growing=True) == 1250
    assert rows_capacity(1000, 1100, growing=True) == 1100  # the cap is exact: no row past it
    assert rows_capacity(1000, 900, growing=True) == 1000  # a model past its cap still fits
    assert rows_capacity(1000, 10**6, growing=False) == 1000  # nothing will grow: no padding
    assert rows_fit(1250, 1000, True) and rows_fit(1000, 1000, False)
    assert not rows_fit(999, 1000, True)  # grown past the rows
    assert not rows_fit(2001, 1000, True)  # pruned to under half
    assert rows_fit(1060, 1000, False) and not rows_fit(1100, 1000, False)  # settled: 1/16 of padding at most
    assert keys_needed(8000, 1.0) == 8000 and keys_needed(8000, 1.5) == 12000
    assert keys_needed(8000, 0.5) == 8000  # a pruned model's frames: the bound still holds
    assert keys_capacity(8000) == 10000
    assert keys_fit(10000, 8000) and keys_fit(16000, 8000)
    assert not keys_fit(0, 100)  # none captured yet
    assert not keys_fit(9000, 9001)  # frames may need more (a recent one did, or the model grew)
    assert not keys_fit(16_001, 8000)  # far above the need: the padded sort pays for each key


@pytest.fixture
def no_eager_steps(monkeypatch):
    """Captured from the first step the bound allows (not after EAGER_STEPS eager ones)."""
    monkeypatch.setattr(captured_step, "EAGER_STEPS", 0)


@pytest.mark.parametrize("device", DEVICES)
def test_a_captured_step_updates_what_an_eager_step_does(device, no_eager_steps):
    """From one seeded start, steps on the same frames: the captured trainer's parameters, Adam moments (the
    first step's are its gradients), step counts and densifier statistics equal the eager trainer's, bit for
    bit on a CPU. No densification: the buffers hold the model's rows exactly (no padding)."""
    eager, captured = pair(device, densify_start_fraction=2.0)
    assert captured.captured is not None and eager.captured is None
    eager.step()  # counts a frame of this size: the captured trainer's first step is captured
    assert captured.captured.ready()
    captured.step()
    assert captured.captured.steps == 1 and captured.captured.captures == 1
    assert captured.captured.rows == len(captured.model)
    assert_same(state_of(captured), state_of(eager), device)
    step_both(eager, captured, 11)
    assert captured.captured.steps == 12
    assert_same(state_of(captured), state_of(eager), device)
    eager.flush_measurements()
    captured.flush_measurements()
    assert_same(dict(psnr=captured.sampler.psnr), dict(psnr=eager.sampler.psnr), device)


@pytest.mark.parametrize("device", DEVICES)
def test_a_captured_step_follows_densification_and_checkpoints(device):
    """After EAGER_STEPS eager steps, densification replaces the model's tensors (copied into the step's
    buffers; a capture only past their rows, or where the frames may need more keys), and a checkpoint
    loaded between steps replaces the optimizer: the captured trainer keeps updating what the eager one
    does (to float32 rounding: torch's CPU activations round a padded tensor's tail apart), none dropped."""
    settings = dict(grad_threshold=1e-5, densify_start_fraction=0.05, densify_interval=10, max_gaussians=6000)
    eager, captured = pair(device, **settings)
    sizes = []
    for i in range(50):
        eager.progress = captured.progress = i / 200
        step_both(eager, captured)
        sizes.append((len(captured.model), captured.captured.rows))
        if i == 40:  # both resume from the eager trainer's state
            saved = copy.deepcopy(eager.state_dict())
            eager.load_checkpoint(copy.deepcopy(saved))
            captured.load_checkpoint(saved)
    step = captured.captured
    assert step.steps == 50 - captured_step.EAGER_STEPS
    assert len(captured.model) > 1732  # it densified while captured
    assert any(rows > n for n, rows in sizes)  # padding while the model may grow
    assert step.captures <= 6  # not at every step after a densification
    step.settle()
    assert step.dropped == 0
    if device == "cpu":
        assert len(captured.model) == len(eager.model)
        assert_same(state_of(captured), state_of(eager), device, exact=False)
    else:  # the atomics' order moves gradients near the threshold across it: the two clouds differ a little
        assert len(captured.model) == pytest.approx(len(eager.model), rel=0.02)
        assert np.mean(captured.clip_psnr()) == pytest.approx(np.mean(eager.clip_psnr()), abs=0.1)
    # the model, Adam and the densifier hold views of the step's buffers: eager code reads and writes them
    buffers = step._buffers
    assert captured.model.means.data_ptr() == buffers["params"]["means"].data_ptr()
    assert captured.densifier.grad_sum.data_ptr() == buffers["statistics"]["grad_sum"].data_ptr()


@pytest.mark.parametrize("device", DEVICES)
def test_a_step_whose_keys_overflowed_updates_nothing_and_is_captured_again(device, no_eager_steps):
    """A bound far below the frames' totals (as after a sudden growth): the step renders with too few keys,
    its update is dropped on the device (parameters, moments and statistics untouched, its PSNR NaN), the
    host learns the total RING // 2 steps later, counts it dropped and captures again with room for it."""
    eager, captured = pair(device, densify_start_fraction=2.0)
    eager.step()
    captured.step()
    step = captured.captured
    for _ in range(16):
        remember_total(step._frame, 1)  # the bound's last frames all tiny
    before = state_of(captured)
    captures = step.captures
    psnr = captured.captured.run(0, True, False).clone()
    assert step.captures == captures + 1 and step.keys == keys_capacity(1 + 256)
    assert torch.isnan(psnr).item()
    after = state_of(captured)
    for key, value in before.items():
        if not key.endswith(".step"):  # Adam counted the step on the host
            assert torch.equal(after[key], value), key
    step.settle()
    assert step.dropped == 1
    psnr = captured.captured.run(0, True, False)
    assert step.captures == captures + 2 and step.keys > keys_capacity(1 + 256)
    assert not torch.isnan(psnr).item()
    step.settle()
    assert step.dropped == 1


@pytest.mark.parametrize("device", DEVICES)
def test_a_frame_outside_the_contract_is_refused_when_its_flags_are_read(device, no_eager_steps):
    """A parameter gone NaN (a diverged fit): the frame's flags refuse it on the device (nothing updated) and
    the host raises RenderError when it reads them, within RING steps."""
    eager, captured = pair(device, densify_start_fraction=2.0)
    eager.step()
    captured.step()
    with torch.no_grad():
        captured.model.opacity_logits[5] = float("nan")
    means = captured.model.means.detach().clone()
    with pytest.raises(RenderError, match="opacities"):
        for _ in range(RING):
            captured.step()
    assert torch.equal(captured.model.means.detach(), means)


def test_the_captured_step_serves_only_where_it_can():
    images, cams, points, colors = clip()
    dense = Trainer(images, cams, points, colors, small_config(10, sparse_adam=False, alive_index=False), CPU)
    assert "dense Adam" in unsupported(dense)
    indexed = Trainer(images, cams, points, colors, small_config(10, sparse_adam=True, alive_index=True), CPU)
    assert "alive index" in unsupported(indexed)
    weights = torch.ones(images.shape[:3]).numpy()
    layer = Trainer(images, cams, points, colors, small_config(10, sparse_adam=True, alive_index=False), CPU,
                    weights=weights)
    assert "weights" in unsupported(layer)
    with pytest.raises(InputError, match="dense Adam"):
        Trainer(images, cams, points, colors, small_config(10, sparse_adam=False, captured_step=True), CPU)
    # off by default on a CPU (on by default only on a GPU)
    plain = Trainer(images, cams, points, colors, small_config(10, sparse_adam=True, alive_index=False), CPU)
    assert unsupported(plain) is None and plain.captured is None
    assert isinstance(Trainer(images, cams, points, colors, small_config(10, sparse_adam=True, alive_index=False,
                                                                          captured_step=True), CPU).captured,
                      CapturedStep)


def test_a_run_with_captured_steps_ends_like_an_eager_one():
    """Trainer.run with captured steps (the loop's logs, the lagged sampler, the last measurement): a seeded
    run of a set number of iterations with densification ends at the eager run's clip PSNR and size."""
    images, cams, points, colors = clip()
    results = [Trainer(images, cams, points, colors, small_config(60, sparse_adam=True, alive_index=False,
                                                                  captured_step=captured), CPU).run()
               for captured in (False, True)]
    assert len(results[0].model) == len(results[1].model)
    assert results[1].clip_psnr == pytest.approx(results[0].clip_psnr, abs=0.05)
    assert not any("captured steps updated nothing" in note for note in results[1].notes)


def test_the_train_step_benchmark_runs_on_a_cpu():
    from benchmarks import train_step

    (row,) = train_step.main(["--smoke"]).values()
    assert row["steps_per_s"]["eager"] > 0 and row["steps_per_s"]["captured"] > 0
    assert row["fit"]["captured"]["clip_psnr"] == pytest.approx(row["fit"]["eager"]["clip_psnr"], abs=0.05)


@pytest.mark.parametrize("device", DEVICES)
def test_by_default_a_gpu_fit_captures_its_steps_where_it_can_and_any_fit_runs_where_it_cannot(device):
    """captured_step=None (the default): a GPU fit with SeenAdam is captured; one it cannot serve (dense Adam)
    steps eagerly without a word; a CPU fit steps eagerly."""
    images, cams, points, colors = clip()
    dev = torch.device(device)
    default = Trainer(images, cams, points, colors, small_config(10, sparse_adam=True, alive_index=False), dev)
    assert isinstance(default.captured, CapturedStep) == (dev.type == "cuda")
    dense = Trainer(images, cams, points, colors, small_config(10, sparse_adam=False), dev)
    assert dense.captured is None
