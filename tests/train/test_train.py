"""The trainer on CPU: a synthetic clip fits, the sampler favours bad frames, the cap holds,
a seeded run repeats exactly, and an interrupted run resumed from its checkpoint ends where an
uninterrupted one does."""

from __future__ import annotations

import copy
import math
import subprocess
import sys
import time
import weakref

import numpy as np
import pytest
import torch

from tomgs.demo import demo_scene
from tomgs.model import GaussianModel
from tomgs.render.sequence import render_sequence
from tomgs.train import Trainer, preset
from tomgs.train.checkpoint import read_checkpoint
from tomgs.train.densify import Densifier
from tomgs.train.init import initial_model
from tomgs.train.optim import SeenAdam
from tomgs.train.sampler import FrameSampler
from tomgs.train.loop import RunHooks
from tomgs.train.budget import Budget
from scenes import devices

CPU = torch.device("cpu")


def synthetic_clip(frames: int, width: int, height: int):
    """Frames of the demo scene (a static room and a moving ball) with its known cameras, and a
    sparse cloud taken from the scene, as the tracker would give."""
    gaussians, cams = demo_scene(num_frames=frames, width=width, height=height)
    images = np.stack([(img.numpy() * 255 + 0.5).astype(np.uint8)
                       for _, img, _ in render_sequence(gaussians, cams, background=(0.05, 0.05, 0.08))])
    points = gaussians["means"][::7].double().numpy()
    return images, cams, points, np.full((len(points), 3), 0.5, dtype=np.float32)


def small_config(iterations: int, **kw):
    settings = dict(iterations=iterations, log_interval=25, eval_interval_s=1e9, init_points_per_frame=300,
                    max_gaussians=4000, densify_start_fraction=50 / iterations, densify_stop_fraction=0.75,
                    densify_interval=50)
    return preset("quick", **settings | kw)


@pytest.mark.slow  # a long fit
@pytest.mark.parametrize("sparse_adam", [False, True])
def test_synthetic_clip_fits_to_30db(sparse_adam):
    images, cams, points, colors = synthetic_clip(4, 48, 27)
    result = Trainer(images, cams, points, colors, small_config(400, sparse_adam=sparse_adam), CPU).run()
    assert result.clip_psnr >= 30.0, result.history[-3:]
    assert len(result.model) <= 4000
    psnrs = [row["train_psnr"] for row in result.history]
    assert psnrs[-1] > psnrs[0] + 10  # it learned, it did not start there


def test_adam_is_sparse_on_a_gpu_and_dense_on_a_cpu_unless_asked():
    """On a CPU both are SeenAdam (dense: over every row), never torch.optim.Adam, whose making imports
    torch._dynamo (seconds of a fit's start)."""
    images, cams, points, colors = synthetic_clip(2, 24, 14)
    for asked, sparse in ((None, False), (True, True), (False, False)):
        trainer = Trainer(images, cams, points, colors, small_config(10, sparse_adam=asked), CPU)
        assert trainer.sparse_adam is sparse and type(trainer.optimizer) is SeenAdam
        trainer.step()


@pytest.mark.parametrize("device", devices())
def test_seen_adam_is_adam_on_the_rows_in_view(device):
    """SeenAdam against torch's Adam in float64 on fresh random gradients: seen rows take Adam's
    step, unseen rows keep their values and moments; parameters of 1-3 axes, 45 columns (the SH of
    degree 3) and an empty one, and more parameters than one launch takes (tomgs/kernels/adam.py SLOTS);
    moments replaced by other tensors (a checkpoint loaded) and a parameter replaced (densification)
    between steps; a step with no rows named (`step()`) is dense Adam, moving every row (those without a
    gradient by their momentum). On every device the tests run on."""
    g = torch.Generator().manual_seed(7)
    n = 40
    params = [torch.randn(n, 3, generator=g), torch.randn(n, generator=g), torch.randn(n, 1, 3, generator=g),
              torch.zeros(n, 0, 3), torch.randn(n, 15, 3, generator=g)] + [torch.randn(n, 1 + i % 4, generator=g)
                                                                         for i in range(7)]
    ours = [p.clone().to(device).requires_grad_(True) for p in params]
    ref = [p.double().requires_grad_(True) for p in params]
    opt = SeenAdam([dict(params=[p], lr=0.01 * (i + 1)) for i, p in enumerate(ours)], eps=1e-15)
    adam = torch.optim.Adam([dict(params=[p], lr=0.01 * (i + 1)) for i, p in enumerate(ref)], eps=1e-15)
    for step in range(6):
        if step == 2:  # other tensors for the moments: the kept descriptors must not write the old ones
            for p in ours:
                state = opt.state[p]
                if state:
                    state["exp_avg"], state["exp_avg_sq"] = state["exp_avg"].clone(), state["exp_avg_sq"].clone()
        if step == 4:  # another parameter tensor, its state moved over, as densification does
            new = ours[0].detach().clone().requires_grad_(True)
            opt.param_groups[0]["params"][0] = new
            opt.state[new] = opt.state.pop(ours[0])
            ours[0] = new
        seen = torch.ones(n, dtype=torch.bool) if step == 0 else torch.rand(n, generator=g) < 0.4
        scale = 1e4 if step == 3 else 1.0  # a spike: Adam's normalisation must hold it
        for p, q in zip(ours, ref):
            grad = torch.randn(p.shape, generator=g, dtype=torch.float64) * scale
            grad *= seen.view(-1, *([1] * (p.dim() - 1)))
            p.grad, q.grad = grad.float().to(device), grad
        kept = [(q.detach().clone(), {k: v.clone() for k, v in adam.state[q].items()}) for q in ref]
        adam.step()
        if step == 5:  # dense: every row steps, the unseen ones (no gradient) by their momentum
            opt.step()
            continue
        with torch.no_grad():  # Adam on the seen rows only: put the unseen rows back
            for q, (value, state) in zip(ref, kept):
                q[~seen] = value[~seen]
                for key in ("exp_avg", "exp_avg_sq"):
                    if key in state:
                        adam.state[q][key][~seen] = state[key][~seen]
        opt.step(seen.to(device))
    for p, q in zip(ours, ref):
        assert torch.isfinite(p).all()
        assert torch.allclose(p.double().cpu(), q, atol=1e-5)
        if p.numel():
            assert torch.allclose(opt.state[p]["exp_avg"].double().cpu(), adam.state[q]["exp_avg"], atol=1e-5)
    with pytest.raises(ValueError, match="rows"):
        opt.step(torch.ones(n + 1, dtype=torch.bool, device=device))
    with pytest.raises(ValueError, match="betas and eps"):
        SeenAdam([dict(params=[ours[0]]), dict(params=[ours[1]], betas=(0.5, 0.9))])


def test_seen_adam_loads_its_own_state_and_torch_adams():
    """SeenAdam loads the state_dict of torch's Adam (a CPU fit's checkpoint resumed on a GPU) and
    its own, and goes on with the same step as the optimiser that saved it; a state of other group
    sizes or other betas is refused."""
    g = torch.Generator().manual_seed(11)
    n = 16
    start = [torch.randn(n, 3, generator=g), torch.randn(n, generator=g)]
    grads = [[torch.randn(p.shape, generator=g) for p in start] for _ in range(4)]
    everything = torch.ones(n, dtype=torch.bool)

    def make(kind):
        params = [p.clone().requires_grad_(True) for p in start]
        groups = [dict(params=[p], lr=0.01 * (i + 1), name=f"p{i}") for i, p in enumerate(params)]
        return params, (SeenAdam(groups, eps=1e-15) if kind == "seen" else torch.optim.Adam(groups, eps=1e-15))

    def take(params, opt, step_grads):
        for p, grad in zip(params, step_grads):
            p.grad = grad.clone()
        opt.step(everything) if isinstance(opt, SeenAdam) else opt.step()
        opt.zero_grad(set_to_none=True)
        assert all(p.grad is None for p in params)

    for first, second in (("adam", "seen"), ("seen", "seen")):
        params, opt = make(first)
        for step_grads in grads[:3]:
            take(params, opt, step_grads)
        saved = copy.deepcopy(opt.state_dict())  # as a file would give it: not the live moments
        assert [group["name"] for group in saved["param_groups"]] == ["p0", "p1"]
        assert float(saved["state"][0]["step"]) == 3
        others, other = make(second)
        with torch.no_grad():
            for mine, theirs in zip(others, params):
                mine.copy_(theirs)
        other.load_state_dict(saved)
        take(params, opt, grads[3])
        take(others, other, grads[3])
        for mine, theirs in zip(others, params):
            assert torch.allclose(mine, theirs, rtol=0, atol=1e-6), (first, second)
        if second == "seen":
            assert all(other.state[p]["step"].device.type == "cpu" for p in others)
    _, seen = make("seen")
    with pytest.raises(ValueError, match="groups of other sizes"):
        seen.load_state_dict(dict(state={}, param_groups=saved["param_groups"][:1]))
    wrong = [dict(group, betas=(0.5, 0.9)) for group in saved["param_groups"]]
    with pytest.raises(ValueError, match="betas"):
        seen.load_state_dict(dict(state={}, param_groups=wrong))


@pytest.mark.parametrize("saving", [True, False])
def test_a_checkpoint_resumes_with_the_other_adam(saving):
    """A trainer's checkpoint made with sparse Adam (a GPU's default) resumes with dense Adam (a CPU's:
    SeenAdam over every row) and the other way round: the moments carry over and the next step runs
    (torch's Adam and SeenAdam read each other's state: the test above)."""
    images, cams, points, colors = synthetic_clip(2, 24, 14)
    saver = Trainer(images, cams, points, colors, small_config(20, sparse_adam=saving), CPU)
    for _ in range(3):
        saver.step()
    state = saver.state_dict()
    resumed = Trainer(images, cams, points, colors, small_config(20, sparse_adam=not saving), CPU)
    resumed.load_checkpoint(state)
    assert resumed.sparse_adam is not saving and type(resumed.optimizer) is SeenAdam
    for group in resumed.optimizer.param_groups:
        (p,) = group["params"]
        saved = saver.optimizer.state[saver.model.parameters_by_name()[group["name"]]]
        assert saved or not p.numel()  # only an empty parameter (SH rest at degree 0) has no moments
        if saved:
            assert torch.equal(resumed.optimizer.state[p]["exp_avg_sq"], saved["exp_avg_sq"])
    resumed.step()
    assert resumed.iteration == saver.iteration + 1
    assert all(torch.isfinite(p).all() for p in resumed.model.parameters_by_name().values())


def test_seen_adam_does_not_import_torch_dynamo():
    """torch.optim.Optimizer's first add_param_group imports torch._dynamo (seconds in a fit's first
    minute); SeenAdam goes without it: made, stepped, saved and loaded in a fresh interpreter."""
    code = ("import sys, torch\n"
            "from tomgs.train.optim import SeenAdam\n"
            "p = torch.nn.Parameter(torch.zeros(4, 3))\n"
            "opt = SeenAdam([dict(params=[p], lr=0.1, name='x')])\n"
            "p.grad = torch.ones(4, 3)\n"
            "opt.step(torch.ones(4, dtype=torch.bool))\n"
            "opt.load_state_dict(opt.state_dict())\n"
            "assert float(p[0, 0]) < 0\n"
            "print('torch._dynamo' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


def test_initial_points_per_frame_respect_device_frame_size_and_cap():
    config = preset("default", quality="max")  # a GPU fit below max starts smaller: tests/train/test_growth.py
    assert config.points_per_frame(854 * 480, 90, "cuda") == 48000
    # a longer clip starts from 5M Gaussians in all, never from fewer than 16,000 a frame
    assert config.points_per_frame(854 * 480, 200, "cuda") == 25000
    assert config.points_per_frame(1920 * 1080, 900, "cuda") == 16000
    assert config.points_per_frame(854 * 480, 90, "cpu") == 2000  # serial kernels: fewer, more steps
    assert config.points_per_frame(128 * 72, 32, "cuda") == 128 * 72 // 5  # small frames: one per 5 pixels
    assert config.replace(max_gaussians=10_000_000).points_per_frame(854 * 480, 2000, "cuda") == 2500  # half the cap
    # the automatic cap grows with the clip (47M for 2000 frames of 480p), the start stays under half of it
    assert config.points_per_frame(854 * 480, 2000, "cuda") == config.cap(2000, 854 * 480, "cuda") // 4000
    assert config.replace(init_points_per_frame=300).points_per_frame(100, 5) == 300  # asked for: as given
    assert config.replace(max_gaussians=10).points_per_frame(100, 90) == 1


def test_sampler_favours_low_psnr_frames():
    sampler = FrameSampler(4, "inverse_psnr", seed=3)
    for frame, value in enumerate([20.0, 40.0, 40.0, 40.0]):
        sampler.update(frame, value)
    counts = np.bincount([sampler.sample() for _ in range(4000)], minlength=4)
    assert counts[0] > 1.7 * counts[1:].mean()  # p ~ 1/PSNR: twice as likely
    uniform = FrameSampler(4, "uniform", seed=3)
    counts = np.bincount([uniform.sample() for _ in range(4000)], minlength=4)
    assert counts.min() > 900


def test_unseen_frames_count_as_the_worst():
    sampler = FrameSampler(3, seed=0)
    sampler.update(0, 30.0)
    p = sampler.probabilities()
    assert p[1] == p[2] and p[1] >= p[0]


def test_the_sampler_keeps_its_distribution_until_a_psnr_changes():
    """probabilities() is kept between draws and rebuilt when a PSNR is heard or a state loaded."""
    sampler = FrameSampler(5, seed=1)
    first = sampler.probabilities()
    assert sampler.probabilities() is first and torch.allclose(first, torch.full((5,), 0.2, dtype=torch.float64))
    sampler.update(2, 10.0)
    sampler.update(0, 40.0)
    second = sampler.probabilities()
    assert second is not first and second[0] < second[2]  # frame 0 is rendered better
    state = sampler.state_dict()
    sampler.update(0, 5.0)
    assert sampler.probabilities()[0] > second[0]
    sampler.load_state_dict(state)
    assert torch.equal(sampler.probabilities(), second)


def test_densification_threshold_by_device_unless_given():
    """A GPU fit grows its cloud within the first minute (1e-4), a CPU fit keeps 3DGS's 2e-4; a given
    threshold, and the paper preset's, hold on every device."""
    assert Densifier(preset("default"), 1.0, 1, "cpu").settings.threshold == 2e-4
    assert Densifier(preset("default"), 1.0, 1, CPU).settings.threshold == 2e-4
    assert preset("default").threshold("cuda") == 1e-4
    assert preset("default", grad_threshold=3e-4).threshold("cuda") == 3e-4
    assert preset("paper").threshold("cuda") == preset("paper").threshold("cpu") == 2e-4


@pytest.mark.parametrize("with_rows", [False, True])
def test_the_densifiers_statistics_add_each_visible_gaussians_ndc_gradient_norm(with_rows):
    """observe (one Warp launch) against the float64 formula: per visible Gaussian, |dL/dmean2d| in NDC
    units added to its sum and one view to its count, over two frames; with rows (the alive index's
    frames), a rendered row's statistics reach its Gaussian, a row listed twice adds both."""
    n, g = 30, torch.Generator().manual_seed(3)
    densifier = Densifier(preset("quick"), extent=1.0, num_gaussians=n, device=CPU)
    want_sum, want_seen = torch.zeros(n, dtype=torch.float64), torch.zeros(n, dtype=torch.float64)
    for width, height in ((64, 40), (33, 17)):
        rows = torch.tensor([0, 2, 3, 3, 7, 11, 12, 20, 29]) if with_rows else None
        m = n if rows is None else len(rows)
        means2d = torch.zeros(m, 2, requires_grad=True)
        (means2d * torch.randn(m, 2, generator=g) * 10.0 ** torch.randint(-6, 2, (m, 1), generator=g)).sum().backward()
        visible = torch.rand(n, generator=g) < 0.7
        visible[3] = True  # listed twice with rows
        densifier.observe(dict(means2d=means2d, width=width, height=height, rows=rows), visible)
        scaled = means2d.grad.double() * torch.tensor([width / 2.0, height / 2.0], dtype=torch.float64)
        where = torch.arange(n) if rows is None else rows
        hit = visible[where]
        want_sum.index_add_(0, where[hit], scaled.norm(dim=-1)[hit])
        want_seen.index_add_(0, where[hit], torch.ones(int(hit.sum()), dtype=torch.float64))
    assert torch.allclose(densifier.grad_sum.double(), want_sum, rtol=1e-6, atol=0.0)
    assert torch.equal(densifier.seen.double(), want_seen) and want_seen[3] == (4 if with_rows else 2)
    densifier.observe(dict(means2d=torch.zeros(n, 2, requires_grad=True), width=8, height=8), visible)  # no grad
    assert torch.allclose(densifier.grad_sum.double(), want_sum, rtol=1e-6, atol=0.0)


@pytest.mark.parametrize("cap", [60, 100, 1000])
def test_densification_never_exceeds_the_cap(cap):
    g = torch.Generator().manual_seed(0)
    model = GaussianModel.from_points(torch.randn(50, 3, generator=g), torch.rand(50, 3, generator=g),
                                      torch.rand(50, generator=g), 0.5, max_sh_degree=1)
    model.log_scales.data[:25] = -1.0  # large: split; the rest small: clone
    model.log_scales.data[25:] = -8.0
    optimizer = torch.optim.Adam([dict(params=[p], lr=1e-3, name=n) for n, p in model.parameters_by_name().items()])
    sum(p.sum() for p in model.parameters()).backward()
    optimizer.step()  # give Adam moments that must follow the rows
    config = preset("quick", max_gaussians=cap, percent_dense=0.01)
    densifier = Densifier(config, extent=1.0, num_gaussians=50, device=CPU)
    for _ in range(5):
        densifier.grad_sum.fill_(1.0)
        densifier.seen.fill_(1.0)
        densifier.step(model, optimizer)
        assert len(model) <= cap
        for group in optimizer.param_groups:
            param = group["params"][0]
            assert param.shape[0] == len(model)
            assert optimizer.state[param]["exp_avg"].shape == param.shape
    assert len(model) > 50  # it did densify, up to the cap





@pytest.mark.parametrize("share", [False, True])
def test_a_clone_or_split_shares_its_sources_opacity_when_asked(share):
    """With share_opacity a clone's two Gaussians (the source and its copy, coincident) composite to the
    source's opacity, 1 - (1 - a')^2 = a, and so does each pair of a split's samples; without it both keep a.
    (Opacities from 0.018, above the prune's, to 1 - 1e-6.)"""
    n, g = 40, torch.Generator().manual_seed(5)
    logits = torch.linspace(-4.0, 13.8, n)
    model = GaussianModel.from_points(torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g),
                                      torch.rand(n, generator=g), 0.5, max_sh_degree=0)
    with torch.no_grad():
        model.opacity_logits.copy_(logits)
        model.log_scales[: n // 2] = -1.0  # large: split
        model.log_scales[n // 2:] = -8.0  # small: clone
        model.t_means.copy_(torch.arange(n) / n)  # a label that copies travel with
    optimizer = torch.optim.Adam([dict(params=[p], lr=1e-3, name=k) for k, p in model.parameters_by_name().items()])
    densifier = Densifier(preset("quick", max_gaussians=10 * n, share_opacity=share), extent=1.0, num_gaussians=n,
                          device=CPU)
    densifier.grad_sum.fill_(1.0)
    densifier.seen.fill_(1.0)
    densifier.step(model, optimizer)
    source = torch.sigmoid(logits.double())
    labels = (model.t_means.detach() * n).round().long()
    opacity = torch.sigmoid(model.opacity_logits.detach().double())
    assert len(model) == 2 * n and torch.isfinite(model.opacity_logits).all()
    for i in range(n):
        rows = opacity[labels == i]
        assert len(rows) == 2 and torch.allclose(rows[0], rows[1])
        covered = 1 - (1 - rows[0]) ** 2 if share else rows[0]
        assert torch.allclose(covered, source[i], rtol=1e-5, atol=1e-7), (i, float(covered), float(source[i]))

def test_shared_opacity_logits_are_finite_and_exact_at_every_finite_logit():
    from tomgs.train.densify import shared_opacity_logits

    logits = torch.tensor([-1e30, -80.0, -17.0, -3.0, 0.0, 3.0, 17.0, 80.0, 1e30])
    shared = shared_opacity_logits(logits)
    assert torch.isfinite(shared[1:-1]).all() and (shared[1:] >= shared[:-1]).all()
    a, b = torch.sigmoid(logits[2:-2].double()), torch.sigmoid(shared[2:-2].double())
    assert torch.allclose(1 - (1 - b) ** 2, a, rtol=1e-5)
    assert torch.allclose(shared[1], torch.tensor(-80.0 - math.log(2)), atol=1e-4)  # a' -> a / 2 for small a


def test_under_the_cap_the_largest_gradients_densify_first():
    model = GaussianModel.from_points(torch.zeros(40, 3), torch.rand(40, 3), torch.rand(40), 0.5, max_sh_degree=0,
                                      sizes=torch.full((40,), 1e-4))  # all small: clones
    optimizer = torch.optim.Adam([dict(params=[p], lr=1e-3, name=n) for n, p in model.parameters_by_name().items()])
    densifier = Densifier(preset("quick", max_gaussians=45), extent=1.0, num_gaussians=40, device=CPU)
    densifier.grad_sum.copy_(torch.linspace(1.0, 2.0, 40))  # the last five are the hottest
    densifier.seen.fill_(1.0)
    with torch.no_grad():
        model.t_means.copy_(torch.arange(40) / 40.0)  # a label that copies travel with
    densifier.step(model, optimizer)
    assert len(model) == 45
    assert sorted(model.t_means[40:].tolist()) == pytest.approx((torch.arange(35, 40) / 40.0).tolist())


def _between_frames_model():
    """Six Gaussians, the first four with narrow windows: [0] and [2] on frames, [1] and [3] between
    them (alive inside the clip, at no frame); [4] wide, [5] transparent."""
    model = GaussianModel.from_points(torch.zeros(6, 3), torch.rand(6, 3), torch.full((6,), 0.9), 0.5, max_sh_degree=0)
    with torch.no_grad():
        model.t_means.copy_(torch.tensor([0.25, 0.375, 0.5, 0.625, 0.5, 0.5]))
        model.log_t_scales.copy_(torch.tensor([0.01, 0.01, 0.01, 0.01, 10.0, 10.0]).log())
        model.opacity_logits[5] = -10.0
    optimizer = torch.optim.Adam([dict(params=[p], lr=1e-3, name=n) for n, p in model.parameters_by_name().items()])
    return model, optimizer


def test_gaussians_dead_at_every_training_frame_are_pruned():
    """With the training frames' times a window between two frames goes: it can never be seen, so
    never learn again; without them (any clip time) it stays."""
    times = [0.0, 0.25, 0.5, 0.75, 1.0]
    model, optimizer = _between_frames_model()
    assert Densifier(preset("quick"), 1.0, 6, CPU).prune(model, optimizer) == 1  # the transparent one
    assert Densifier(preset("quick"), 1.0, 5, CPU, times=times[::-1]).prune(model, optimizer) == 2
    assert model.t_means.tolist() == pytest.approx([0.25, 0.5, 0.5])
    assert optimizer.param_groups[0]["params"][0].shape[0] == 3
    model, optimizer = _between_frames_model()
    assert Densifier(preset("quick", temporal=False), 1.0, 6, CPU, times=times).prune(model, optimizer) == 1


@pytest.mark.parametrize("progress, cap, resumes", [(0.3, 6, True), (0.8, 6, False), (0.3, 2, False)])
def test_room_freed_under_the_cap_is_densified_again_inside_the_window(progress, cap, resumes):
    """A reached cap stops densification; a prune inside the densification window that frees rows lets
    it go on into them, up to the cap again; after the window, or still at the cap, it stays stopped."""
    config = preset("quick", max_gaussians=cap, densify_interval=10, densify_start_fraction=0.1,
                    densify_stop_fraction=0.75, percent_dense=1.0)
    model, optimizer = _between_frames_model()
    densifier = Densifier(config, 1.0, 6, CPU, times=[0.0, 0.25, 0.5, 0.75, 1.0])
    densifier.capped = True
    visible = torch.ones(6, dtype=torch.bool)
    means2d = torch.zeros(6, 2, requires_grad=True)
    densifier.step_post_backward(model, optimizer, dict(means2d=means2d, width=8, height=8), visible, 100, progress)
    assert len(model) == 3 and densifier.capped is not resumes
    assert densifier.collecting(progress) is resumes
    densifier.grad_sum.fill_(1.0)
    densifier.seen.fill_(1.0)
    means2d = torch.zeros(3, 2, requires_grad=True)
    densifier.step_post_backward(model, optimizer, dict(means2d=means2d, width=8, height=8), visible[:3], 110, progress)
    assert len(model) == (6 if resumes else 3) and densifier.capped


@pytest.mark.parametrize("iteration, progress, due", [(100, 0.01, False), (100, 0.04, True), (101, 0.2, False),
                                                      (1_000_000, 0.49, True), (100, 0.5, False)])
def test_densification_follows_run_progress_not_iteration_counts(iteration, progress, due):
    """Under a time budget a run may do few iterations: the window is a fraction of the run."""
    config = preset("default", densify_interval=100, densify_start_fraction=0.04, densify_stop_fraction=0.5)
    assert Densifier(config, 1.0, 1, CPU).due(iteration, progress) is due


def run_clip(iterations, interrupt_at=None, checkpoint=None, resume_from=None, on_row=None, **config):
    images, cams, points, colors = synthetic_clip(3, 32, 18)
    trainer = Trainer(images, cams, points, colors, small_config(iterations, **config), CPU)
    if resume_from is not None:
        trainer.load_checkpoint(resume_from)

    def progress(row):
        if on_row is not None:
            on_row(row)
        if row["iteration"] == interrupt_at:
            raise KeyboardInterrupt

    return trainer.run(hooks=RunHooks(checkpoint=checkpoint, progress=progress))


@pytest.mark.slow  # a long fit
def test_seeded_run_repeats_and_resume_matches(tmp_path):
    """A seeded CPU run repeats exactly: measured at every step or never (the clock sets when a clip PSNR
    is taken, and measuring must not change what the sampler draws), and resumed from a checkpoint
    written mid-run (the steps' measurements the sampler has not heard yet travel with it)."""
    straight = run_clip(100)
    again = run_clip(100, eval_interval_s=0.0)
    assert sum(r["clip_psnr"] != "" for r in again.history) > sum(r["clip_psnr"] != "" for r in straight.history)
    for name, value in straight.model.parameters_by_name().items():
        assert torch.equal(value, again.model.parameters_by_name()[name]), name

    checkpoint = tmp_path / "run.ckpt"
    with pytest.raises(KeyboardInterrupt):
        run_clip(100, interrupt_at=50, checkpoint=checkpoint)
    assert read_checkpoint(checkpoint)["sampler"]["pending"]  # 50 steps: two past a flush
    resumed = run_clip(100, checkpoint=checkpoint, resume_from=checkpoint)
    assert resumed.iterations == 100
    for name, value in straight.model.parameters_by_name().items():
        assert torch.equal(value, resumed.model.parameters_by_name()[name]), name
    assert [r["iteration"] for r in resumed.history] == [r["iteration"] for r in straight.history]


def background_writes(monkeypatch, kept: dict, seconds: float = 0.0, error: Exception | None = None):
    """Checkpoints every step, written by the thread after `seconds` (training runs on meanwhile and changes
    its own tensors), or failing with `error`; a copy of each written there is kept by iteration in `kept`."""
    import tomgs.train.checkpoint as checkpoints
    import tomgs.train.loop as loop

    write = checkpoints.write_checkpoint

    def slow(path, state):
        time.sleep(seconds)
        if error is not None:
            raise error
        written = write(path, state)
        kept[state["iteration"]] = read_checkpoint(written)
        return written

    monkeypatch.setattr(checkpoints, "write_checkpoint", slow)
    monkeypatch.setattr(loop, "CHECKPOINT_OVERHEAD", 1e12)  # no spacing by the wait: one every step


def test_a_checkpoint_written_while_training_goes_on_holds_its_own_step(tmp_path, monkeypatch):
    """The periodic checkpoints are written by a thread while the next steps change the parameters and
    the optimiser's moments in place: each must hold the step it was taken at, exactly as a checkpoint
    written at that step with training stopped (the interrupt's)."""
    kept = {}
    background_writes(monkeypatch, kept, seconds=0.02)
    run_clip(60, checkpoint=tmp_path / "every.ckpt", checkpoint_interval_s=0.0)
    assert sorted(kept) == list(range(1, 61))
    with pytest.raises(KeyboardInterrupt):
        run_clip(60, interrupt_at=30, checkpoint=tmp_path / "stopped.ckpt", log_interval=1)
    stopped = read_checkpoint(tmp_path / "stopped.ckpt")
    for name, value in stopped["params"].items():
        assert torch.equal(value, kept[30]["params"][name]), name
    moments = list(zip(stopped["optimizer"]["state"].values(), kept[30]["optimizer"]["state"].values()))
    assert moments and all(torch.equal(a[k], b[k]) for a, b in moments for k in a), "optimiser moments differ"
    assert torch.equal(stopped["densifier"]["grad_sum"], kept[30]["densifier"]["grad_sum"])
    assert not torch.equal(kept[30]["params"]["means"], kept[31]["params"]["means"])  # the next step moved them


def test_an_interrupt_waits_for_the_checkpoint_being_written(tmp_path, monkeypatch):
    """SIGINT's checkpoint is written after the one in progress: a slow earlier write must not land last."""
    kept = {}
    background_writes(monkeypatch, kept, seconds=0.1)
    checkpoint = tmp_path / "run.ckpt"
    with pytest.raises(KeyboardInterrupt):
        run_clip(60, interrupt_at=30, checkpoint=checkpoint, checkpoint_interval_s=0.0, log_interval=1)
    assert max(kept) == 29
    assert read_checkpoint(checkpoint)["iteration"] == 30


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("pinned_max", [None, 1])
def test_a_background_checkpoint_copies_what_the_training_stream_had_queued_cuda(tmp_path, monkeypatch, pinned_max):
    """The writer's copies to the host run on a stream of their own: they must wait for the clones queued on
    the training's stream before the event (kept busy here, so a copy that did not wait reads them unwritten),
    and training's own tensors, changed in place right after, must not reach the file. They go through pinned
    memory, unless a storage is larger than PINNED_STORAGE_MAX (1 byte: every one)."""
    import tomgs.train.checkpoint as checkpoint
    from tomgs.train.checkpoint import CheckpointWriter, own_copies

    if pinned_max is not None:
        monkeypatch.setattr(checkpoint, "PINNED_STORAGE_MAX", pinned_max)
    pinned, empty = [], torch.empty
    monkeypatch.setattr(torch, "empty", lambda *a, **k: (pinned.append(1) if k.get("pin_memory") else None,
                                                         empty(*a, **k))[1])
    images, cams, points, colors = synthetic_clip(2, 24, 14)
    trainer = Trainer(images, cams, points, colors, small_config(10), torch.device("cuda"))
    want = {name: p.detach().cpu() for name, p in trainer.model.parameters_by_name().items()}
    state = trainer.state_dict()
    torch.cuda._sleep(400_000_000)  # the training stream busy for ~0.2 s before the clones run
    copies, ready = own_copies(state), torch.cuda.Event()
    ready.record()
    with CheckpointWriter() as writer:
        writer.submit(tmp_path / "run.ckpt", copies, ready)
        with torch.no_grad():
            for p in trainer.model.parameters_by_name().values():
                p.add_(1.0)
    written = read_checkpoint(tmp_path / "run.ckpt")
    for name, value in want.items():
        assert torch.equal(written["params"][name], value), name
    device_storages = {t.untyped_storage().data_ptr() for t in checkpoint._tensors(copies) if t.is_cuda}
    assert len(pinned) == (len(device_storages) if pinned_max is None else 0)


def test_the_clip_psnr_renders_again_a_frame_that_overflowed_its_keys(monkeypatch):
    """clip_psnr issues its frames without waiting for their counts, reading each EVAL_AHEAD frames later; a
    frame that needed more intersections than the bound its size had (the Gaussians grew since it was counted)
    is rendered again, waiting, so its PSNR is the full frame's."""
    from tomgs.train.trainer import EVAL_AHEAD

    images, cams, points, colors = synthetic_clip(EVAL_AHEAD + 3, 48, 27)
    trainer = Trainer(images, cams, points, colors, small_config(10), CPU)
    trainer.clip_psnr()  # counts every frame of this size: the next ones need not wait
    with torch.no_grad():
        trainer.model.log_scales += 1.5  # 4.5 times as wide: many more tiles each
    waited, issued, unread, buffers, held = [], [], [], [], []
    render = Trainer.render

    def spy(self, k, defer=False, **kw):
        if not defer:
            waited.append(k)
        unread.append(sum(counts.known() is None for counts in issued))  # frames in flight before this one
        held.append(sum(ref() is not None for ref in buffers))  # earlier frames' rasterizer buffers still held
        image, alpha, meta = render(self, k, defer=defer, **kw)
        if meta["counts"] is not None:
            issued.append(meta["counts"])
        buffers.append(weakref.ref(meta["means2d"]))
        return image, alpha, meta

    monkeypatch.setattr(Trainer, "render", spy)
    activations = []
    render_inputs = trainer.model.render_inputs
    monkeypatch.setattr(trainer.model, "render_inputs", lambda: (activations.append(1), render_inputs())[1])
    got = trainer.clip_psnr()
    assert waited, "no frame overflowed: the case does not test the second render"
    # read that many frames behind, the activated parameters made once: what is in flight stays bounded
    assert max(unread) == EVAL_AHEAD and len(activations) == 1
    assert max(held) == 0, held  # a frame in flight keeps its image and counts, not the rasterizer's buffers
    want = [float(trainer.frame_psnr(k, render(trainer, k)[0])) for k in range(trainer.num_frames)]
    assert np.allclose(got, want, rtol=0, atol=1e-4), (got, want)


def clocked_run(monkeypatch, limit: float, step_seconds, frame_seconds=None):
    """A run of a 4-frame clip under a `limit` of fake seconds: step k takes step_seconds(k) of them, and
    the clip PSNR's frames are known to take `frame_seconds` each (None: not measured yet). Returns
    (result, fake seconds at the last step, the frames each clip PSNR covered)."""
    clock, stepped, covered = [0.0], [0.0], []

    def step(self):
        clock[0] += step_seconds(self.iteration)
        stepped[0] = clock[0]
        self.iteration += 1

    def clip_psnr(self, tick=None, frames=None):
        frames = range(self.num_frames) if frames is None else frames
        covered.append(len(frames))
        clock[0] += (frame_seconds or 0.0) * len(frames)
        return [20.0] * len(frames)

    images, cams, points, colors = synthetic_clip(4, 32, 18)
    # quality max: the end's timing alone (the quality rule's rounds would take fake seconds of their own)
    trainer = Trainer(images, cams, points, colors, small_config(100_000, quality="max"), CPU)
    trainer.eval_frame_seconds = frame_seconds
    monkeypatch.setattr(time, "perf_counter", lambda: clock[0])
    monkeypatch.setattr(Trainer, "step", step)
    monkeypatch.setattr(Trainer, "clip_psnr", clip_psnr)
    monkeypatch.setattr(Trainer, "compact", lambda self, tick=None: 0)
    result = trainer.run(Budget(iterations=trainer.config.iterations, training_until=limit))
    monkeypatch.undo()
    return result, stepped[0], covered


def test_slow_first_steps_do_not_end_training_early(monkeypatch):
    """Two slow first steps (a busy machine, kernels loading) made the end's estimate exceed the limit and
    stopped training after 2 of them; the end keeps at most END_SHARE of the limit."""
    from tomgs.train.loop import END_SHARE

    result, trained, covered = clocked_run(monkeypatch, 200.0, lambda k: 30.0 if k < 3 else 1.0)
    assert trained >= (1 - END_SHARE) * 200.0 - 1.0, (trained, result.iterations, result.notes)
    assert covered[-1] == 4 and result.clip_frames == 4  # the end fitted: every frame measured


def test_a_short_end_measures_fewer_frames_and_says_so(monkeypatch):
    """A clip PSNR whose frames take 8 s each (20 s left for the end): training still runs to the end's share
    of the limit; the compaction is left out and the last measurement covers the frames that fit, in notes."""
    result, trained, covered = clocked_run(monkeypatch, 200.0, lambda k: 1.0, frame_seconds=8.0)
    assert trained >= 179.0, (trained, result.notes)
    assert covered[-1] == result.clip_frames == 2, covered
    assert result.history[-1]["clip_frames"] == 2
    assert any("kept every Gaussian" in note for note in result.notes), result.notes
    assert any("covers 2 evenly spaced frames of 4: the budget left" in note for note in result.notes), result.notes


def test_tracked_points_start_alive_over_the_frames_that_saw_them():
    images, cams, points, colors = synthetic_clip(9, 32, 18)
    spans = np.zeros((len(points), 2), dtype=np.int64)
    spans[:, 1] = 8
    spans[0] = (1, 7)
    spans[1] = (2, 2)  # seen in one frame: the narrowest window the per-frame points get too
    trainer = Trainer(images, cams, points, colors, small_config(10), CPU, point_frames=spans)
    t_means, t_scales = trainer.model.t_means.detach(), trainer.model.t_scales.detach()
    times = cams.times
    assert float(t_means[0]) == pytest.approx((times[1] + times[7]) / 2)
    assert float(t_scales[0]) == pytest.approx((times[7] - times[1]) / 2)
    assert float(t_means[1]) == pytest.approx(times[2])
    assert float(t_scales[1]) == pytest.approx(preset("quick").init_t_scale_frames / 8)
    assert float(t_scales[2]) == pytest.approx(0.5)  # seen throughout: sigma half the clip
    unknown = Trainer(images, cams, points, colors, small_config(10), CPU).model
    assert torch.allclose(unknown.t_means.detach()[:len(points)], torch.tensor(0.5))
    assert torch.allclose(unknown.t_scales.detach()[:len(points)], torch.tensor(1.0))


def sliding_camera_clip(frames: int, width: int, height: int, slide: float, rng):
    """Random frames, and cameras (fx 60) sliding `slide` along x over the clip."""
    from tomgs.cameras import Cameras

    images = rng.integers(0, 255, (frames, height, width, 3), dtype=np.uint8)
    c2w = np.tile(np.eye(4), (frames, 1, 1))
    c2w[:, 0, 3] = np.linspace(0, slide, frames)
    K = np.array([[60.0, 0, width / 2], [0, 60.0, height / 2], [0, 0, 1]])
    return images, Cameras(c2w, K, width, height, np.linspace(0, 1, frames), np.arange(frames))


def _tilted_plane_clip(frames=10, width=64, height=48, count=300):
    """A camera sliding sideways over the plane z = 4 + x / 2, and `count` tracked points on it."""
    rng = np.random.default_rng(0)
    images, cams = sliding_camera_clip(frames, width, height, 0.5, rng)
    xy = rng.uniform(-2, 2, (count, 2))
    return images, cams, np.c_[xy, 4 + xy[:, 0] / 2], np.full((count, 3), 0.5, np.float32)


def test_per_frame_points_start_on_the_surface_the_tracked_points_lie_on():
    """init_depth "tracks": each frame's points start at the depth its tracked points give where they
    are (on a tilted plane, to the grid's interpolation error without the jitter, and spread by the jitter
    around it), sized by that depth; "median" puts them at the frame's median depth; a frame that sees too
    few points falls back to it."""
    images, cams, points, colors = _tilted_plane_clip()
    config = small_config(10).replace(init_points_per_frame=500, max_gaussians=100_000)

    def depth_error(model, log=False):
        m = model.means.detach().double().numpy()[len(points):]
        plane = 4 + m[:, 0] / 2
        return np.log(m[:, 2] / plane) if log else np.abs(m[:, 2] - plane) / plane

    exact = Trainer(images, cams, points, colors, config.replace(init_depth_jitter=0.0), CPU).model
    flat = Trainer(images, cams, points, colors, config.replace(init_depth="median", init_depth_jitter=0.0), CPU).model
    assert np.median(depth_error(exact)) < 0.015 < 0.12 < np.median(depth_error(flat))  # 0.006 and 0.13
    assert np.percentile(depth_error(exact), 90) < 0.08 < 0.2 < np.percentile(depth_error(flat), 90)
    # the jitter: log-depth spread by its sigma around the surface (the grid's error adds little to it)
    tracks = Trainer(images, cams, points, colors, config, CPU).model
    median = Trainer(images, cams, points, colors, config.replace(init_depth="median"), CPU).model
    sigma = config.init_depth_jitter
    assert abs(np.median(depth_error(tracks, log=True))) < 0.1 * sigma
    assert abs(depth_error(tracks, log=True).std() - sigma) < 0.1 * sigma
    # sized by their own depth: one sample's share of the image, sqrt(64 * 48 / 500) px at fx 60
    depths = tracks.means.detach().double().numpy()[len(points):, 2]
    sizes = tracks.scales.detach().double().numpy()[len(points):, 0]
    assert np.allclose(sizes, depths * math.sqrt(64 * 48 / 500) / 60, rtol=1e-5)
    assert np.ptp(median.scales.detach().numpy()[len(points):, 0]) == 0  # one size for all

    spans = np.tile([0, 9], (len(points), 1))
    spans[:, 0] = 5  # frames 0-4 see no tracked point: their median depth, as before
    seen_late = Trainer(images, cams, points, colors, config, CPU, point_frames=spans).model
    first = seen_late.means.detach().double().numpy()[len(points):len(points) + 5 * 500]
    as_median = median.means.detach().double().numpy()[len(points):len(points) + 5 * 500]
    assert np.allclose(first, as_median, rtol=1e-6)
    later = seen_late.means.detach().double().numpy()[len(points) + 5 * 500:]
    assert np.allclose(later, tracks.means.detach().double().numpy()[len(points) + 5 * 500:], rtol=1e-6)

    with pytest.raises(ValueError, match="init_depth must be one of tracks, median"):
        config.replace(init_depth="sparse")
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="init_depth_jitter must be between 0 and 1"):
            config.replace(init_depth_jitter=bad)


def test_a_depth_grid_samples_a_linear_function_exactly():
    from tomgs.train.init import sample_grid

    gh, gw, width, height = 7, 11, 100.0, 60.0
    ys, xs = torch.meshgrid(torch.linspace(0, height, gh, dtype=torch.float64),
                            torch.linspace(0, width, gw, dtype=torch.float64), indexing="ij")
    grid = 0.3 * xs - 0.7 * ys + 2
    u = torch.tensor([0.0, 0.5, 37.2, 99.9, 100.0, 120.0, -3.0], dtype=torch.float64)
    v = torch.tensor([0.0, 59.5, 12.8, 0.1, 60.0, 70.0, -1.0], dtype=torch.float64)
    expected = 0.3 * u.clamp(0, width) - 0.7 * v.clamp(0, height) + 2  # clamped to the image
    assert torch.allclose(sample_grid(grid, u, v, int(width), int(height)), expected, atol=1e-12)


def test_initial_cloud_is_built_a_frame_at_a_time_not_on_the_host():
    """The initial cloud goes straight into float32 arrays on the training device, so the
    host never holds the whole cloud (the old float64 lists and their concatenations held ~100 bytes
    a point: 1.8 GB for 900 frames of 8,000 points on a GPU, before the model's own host copy)."""
    import tracemalloc

    frames, width, height, per_frame = 60, 64, 48, 1000
    rng = np.random.default_rng(0)
    images, cams = sliding_camera_clip(frames, width, height, 1.0, rng)
    points = rng.normal(size=(200, 3)) + [0, 0, 4]
    config = small_config(10).replace(init_points_per_frame=per_frame, max_gaussians=10 * frames * per_frame)
    trainer = Trainer(images, cams, points, np.full((200, 3), 0.5, np.float32), config, CPU)
    tracemalloc.start()
    try:
        model, _, _ = initial_model(trainer.frames, cams, trainer.config, CPU, points,
                                    np.full((200, 3), 0.5, np.float32))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    total = frames * per_frame + 200
    assert len(model) == total
    assert peak < total * 4  # less than one float32 per point in Python / NumPy memory (old: ~100 bytes)


@pytest.mark.parametrize("frames, size", [(6, (48, 32)), (8, (40, 32))])
def test_frames_and_cameras_that_disagree_are_refused(frames, size):
    from tomgs.errors import InputError

    images, cams, points, colors = synthetic_clip(8, 48, 32)
    other = np.zeros((frames, size[1], size[0], 3), np.uint8)
    with pytest.raises(InputError, match="one camera per frame"):
        Trainer(other, cams, points, colors, small_config(10), CPU)
    Trainer(images, cams, points, colors, small_config(10), CPU)  # agreeing: accepted


def test_a_first_run_s_compilation_is_in_the_plan_and_its_budget(monkeypatch, tmp_path):
    """A machine that has not compiled these kernels for the device gets a compile phase in the plan,
    its estimate counted against the budget (training gets less) and said in the plan line; the
    marker a finished fit leaves in Warp's kernel cache ends that."""
    import warp as wp

    from tomgs import runtime
    from tomgs.train.plan import COMPILE_COST, make_plan

    config = preset("default", max_seconds=240.0)
    plain, _ = make_plan(config, 40, 96, 160, 96 * 160, "cpu")
    first, _ = make_plan(config, 40, 96, 160, 96 * 160, "cpu", compiles=True)
    assert "compile" not in plain.phases and first.phases["compile"] == COMPILE_COST["cpu"]
    assert first.phases["train"] <= plain.phases["train"] - COMPILE_COST["cpu"] + 0.1  # the start shrinks a little too
    assert "compiling kernels first (first run only" in first.summary() and "compiling" not in plain.summary()
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
    assert not runtime.kernels_compiled("cpu")
    runtime.mark_kernels_compiled("cpu")
    assert runtime.kernels_compiled("cpu") and not runtime.kernels_compiled("cuda")


def test_a_gradient_hook_sees_each_step_and_its_changes_reach_adam():
    """Trainer.gradient_hook(frame, PSNR, seen) runs after each eager step's backward, before Adam: a hook that
    zeroes every gradient and marks nothing seen leaves the parameters where they were; without it they move."""
    images, cams, points, colors = synthetic_clip(3, 32, 18)
    trainer = Trainer(images, cams, points, colors, small_config(10, densify_start_fraction=1.0), CPU)
    heard = []

    def frozen(k, psnr, seen):
        heard.append((k, float(psnr), seen.dtype, seen.shape))
        for p in trainer.model.parameters_by_name().values():
            if p.grad is not None:
                p.grad.zero_()
        seen.zero_()

    before = {k: v.detach().clone() for k, v in trainer.model.parameters_by_name().items()}
    trainer.gradient_hook = frozen
    for _ in range(3):
        trainer.step()
    assert len(heard) == 3
    assert all(0 <= k < 3 and math.isfinite(p) and dtype == torch.bool for k, p, dtype, _ in heard)
    after = trainer.model.parameters_by_name()
    assert all(torch.equal(before[k], after[k].detach()) for k in before)
    trainer.gradient_hook = None
    trainer.step()
    assert not torch.equal(before["means"], trainer.model.means.detach())
