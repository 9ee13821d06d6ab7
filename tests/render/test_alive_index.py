"""tomgs.render.alive: the index of the Gaussians that may be alive at each frame. It lists a superset of
what projection finds alive, for any window; its memory stays within its bound; a frame's work
follows its alive count; training with it takes the steps training without it takes; render_sequence
renders with it what a render of every Gaussian gives."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.train.test_train import small_config, synthetic_clip
from tomgs.render import alive
from tomgs.constants import ALPHA_MIN
from tomgs.model import GaussianModel
from tomgs.render.frame import project_stage, rasterize
from tomgs.render.sequence import render_sequence
from tomgs.temporal import alive_radius
from tomgs.train import Trainer
from tomgs.train.optim import SeenAdam

CPU = torch.device("cpu")
K = torch.tensor([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])


def kernel_alive(opacities, t_means, t_scales, t: float) -> torch.Tensor:
    """bool [N]: alive at t as the projection kernel decides it (float32, t as hi + lo)."""
    n = opacities.shape[0]
    out = project_stage(torch.zeros(n, 3) + torch.tensor([0.0, 0.0, 3.0]), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                        torch.full((n, 3), 0.1), opacities, t_means, t_scales, torch.eye(4), K, 32, 24, t)
    return out["opacities_t"] >= ALPHA_MIN


def as_set(rows, n: int) -> set:
    return set(range(n)) if rows is None else set(rows.tolist())


def extreme_windows(n: int, times: np.ndarray, seed: int = 0):
    """float32 (opacities, t_means, t_scales) [n]: random windows, a fifth of them extreme (sigma 0,
    huge or inf; opacity at and around 1/255; centres far outside the clip, NaN) and a fifth ending
    within float32 rounding of a frame time."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 1, n)
    m = rng.uniform(-0.3, 1.3, n)
    sigma = np.exp(rng.uniform(np.log(1e-5), np.log(3.0), n))
    e = n // 5
    a[:e] = rng.choice([ALPHA_MIN, np.float32(ALPHA_MIN), ALPHA_MIN * (1 + 1e-6), ALPHA_MIN * (1 - 1e-6), 1.0, 0.0], e)
    sigma[:e] = rng.choice([0.0, 1e-30, 1e-7, 0.05, 1e3, 1e30, np.inf], e)
    m[:e] = rng.choice([-1e6, -3.0, -1e-3, 0.0, 0.5, 1.0, 1.0 + 1e-3, 4.0, 1e6, np.nan], e)
    # windows whose edge falls on a frame time: float32 rounding decides, the index must list them
    edge = slice(e, 2 * e)
    r = alive_radius(a[edge], sigma[edge])
    m[edge] = rng.choice(times, e) + rng.choice([-1.0, 1.0], e) * r
    return tuple(torch.from_numpy(x.astype(np.float32)) for x in (a, m, sigma))


@pytest.mark.parametrize("seed", [0, 1])
def test_index_lists_every_gaussian_projection_finds_alive(seed):
    rng = np.random.default_rng(seed)
    times = np.linspace(0.0, 1.0, 41)
    times = np.concatenate([times, times[[3, 3, 17]]])  # repeated times (a clip may hold them)
    rng.shuffle(times)
    n = 3000
    a, m, sigma = extreme_windows(n, times, seed)
    index = alive.index_of(a, m, sigma, times)
    rendered = []
    for k, t in enumerate(times):
        rows = index.rows(k)
        if rows is not None:
            assert (rows[1:] > rows[:-1]).all()  # ascending, no Gaussian twice
        listed = as_set(rows, n)
        found = set(torch.nonzero(kernel_alive(a, m, sigma, float(t)))[:, 0].tolist())
        assert found <= listed, (k, sorted(found - listed)[:10])
        rendered.append(len(listed))
    assert np.mean(rendered) < 0.6 * n  # a subset, not the cloud
    assert index.entries <= alive.ENTRIES_PER_GAUSSIAN * n


@pytest.mark.parametrize("seed", [0, 1])
def test_bucket_sizes_are_weighed_as_the_per_gaussian_sums(seed):
    """The build weighs each bucket size (entries, frames rendered) and counts each bucket's
    Gaussians from two histograms of where windows start and stop: the per-Gaussian sums exactly."""
    rng = np.random.default_rng(seed)
    times = np.concatenate([np.linspace(0.0, 1.0, 41), [0.3, 0.3, 0.9]])
    rng.shuffle(times)
    count = len(times)
    a, m, sigma = extreme_windows(3000, times, seed)
    start, stop = alive._frame_span(*alive.windows(a, m, sigma), torch.as_tensor(np.sort(times)))
    listed = stop > start
    starts_at, stops_at = alive._spans_histogram(start, stop, listed, count)
    for size in (1, 2, 3, 4, 7, 16, 43, 44):
        b_first, b_last = start // size, (stop - 1) // size
        entries = int(torch.where(listed, b_last - b_first + 1, 0).sum())
        work = int(torch.where(listed, torch.clamp_max((b_last + 1) * size, count) - b_first * size, 0).sum())
        assert alive._entries_and_work(starts_at, stops_at, size, count) == (entries, work), size
    index = alive.index_of(a, m, sigma, times)
    b_first, b_last = start // index.size, (stop - 1) // index.size
    per_bucket = [int((listed & (b_first <= b) & (b <= b_last)).sum()) for b in range(index.num_buckets)]
    assert np.diff(index.offsets).tolist() == per_bucket


def test_index_memory_is_bounded_and_chunks_build_the_same(monkeypatch):
    n, times = 2000, np.linspace(0.0, 1.0, 300)
    g = torch.Generator().manual_seed(2)
    m = torch.rand(n, generator=g)
    a = torch.full((n,), 0.9)
    for sigma, buckets in ((torch.full((n,), 1e3), 1),  # alive throughout: one bucket, all of them
                           (torch.full((n,), 1e-4), 300),  # alive a frame or so: one bucket per frame
                           (torch.where(torch.arange(n) % 2 == 0, 1e3, 1e-3), None),  # half of each
                           (10.0 ** (-4 + 4 * torch.rand(n, generator=g)), None)):
        index = alive.index_of(a, m, sigma, times)
        assert index.entries <= alive.ENTRIES_PER_GAUSSIAN * n
        assert index.nbytes <= (alive.ENTRIES_PER_GAUSSIAN + 2) * 4 * n  # int32 ids and bucket ranges
        if buckets is not None:
            assert index.num_buckets == buckets
        if buckets == 1:
            assert index.entries == n and index.rows(0) is None
        monkeypatch.setattr(alive, "CHUNK_ENTRIES", 97)  # many small chunks: the same index
        again = alive.index_of(a, m, sigma, times)
        monkeypatch.undo()
        assert torch.equal(again.ids, index.ids) and again.offsets == index.offsets


def short_lived(n: int, share: float, seed: int = 0):
    """float32 (opacities, t_means, t_scales) [n]: each alive over `share` of the clip, centres uniform."""
    g = torch.Generator().manual_seed(seed)
    a = torch.full((n,), 0.8)
    sigma = torch.full((n,), share / 2 / float(np.sqrt(2 * np.log(255 * 0.8))))
    return a, torch.rand(n, generator=g) * (1 + share) - share / 2, sigma


def test_a_frames_work_follows_its_alive_count():
    """A clip where each frame sees ~10% of the Gaussians alive projects ~10%, not N: in the index,
    in render_sequence and in a training step."""
    from tomgs.cameras import Cameras

    n, frames = 4000, 100
    a, m, sigma = short_lived(n, 0.1)
    times = np.linspace(0.0, 1.0, frames)
    index = alive.index_of(a, m, sigma, times)
    alive_counts = [int(kernel_alive(a, m, sigma, float(t)).sum()) for t in times]
    listed = [len(as_set(index.rows(k), n)) for k in range(frames)]
    assert 0.08 * n < np.mean(alive_counts) < 0.12 * n
    assert all(c <= r for c, r in zip(alive_counts, listed))
    assert np.mean(listed) <= 1.25 * np.mean(alive_counts)  # buckets of frames add a little

    g = torch.Generator().manual_seed(1)
    gaussians = dict(means=torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 3.0]),
                     quats=torch.randn(n, 4, generator=g), scales=torch.full((n, 3), 0.03), opacities=a,
                     colors=torch.rand(n, 3, generator=g), t_means=m, t_scales=sigma)
    cams = Cameras.create(np.repeat(np.eye(4)[None], frames, 0), K.numpy().astype(np.float64), 32, 24)
    projected = {k: len(meta["rows"]) for k, _, meta in render_sequence(gaussians, cams, range(0, frames, 9))}
    assert all(alive_counts[k] <= p <= 1.5 * alive_counts[k] + 40 for k, p in projected.items()), projected

    images = np.zeros((frames, 24, 32, 3), dtype=np.uint8)
    model = GaussianModel.from_points(gaussians["means"], gaussians["colors"], m, sigma, max_sh_degree=0,
                                      sizes=torch.full((n,), 0.03))
    with torch.no_grad():
        model.opacity_logits.fill_(float(np.log(0.8 / 0.2)))
    # training lists what Adam can move into a frame before the index looks again: under SeenAdam
    # a step or two, under dense Adam (a CPU's default) also the coasting after them (~32 learning rates,
    # of the windows' width at 2e-2 since session 32: 2.9x the alive count here, 2.5x at 1e-2)
    for sparse, most in ((True, 1.6), (False, 3.2)):
        trainer = Trainer(images, cams, np.zeros((0, 3)), np.zeros((0, 3), np.float32),
                          small_config(10, sparse_adam=sparse), CPU, initial=(model, 1.0))
        for k in (0, 37, 99):
            _, _, meta = trainer.render(k)
            assert alive_counts[k] <= meta["radii"].shape[0] <= most * alive_counts[k] + 40
            assert meta["rows"].shape == (meta["radii"].shape[0],)


def test_adam_reach_bounds_what_adam_does():
    """adam_reach against torch's Adam and SeenAdam run on 512 rows with gradient histories from
    tiny to growing geometrically, then the steps it bounds: s steps with any gradient (spikes of
    random size and sign) and, for Adam, 400 with zero gradient (coasting). The bound holds, and is
    within a few times of what the worst row does."""
    g = torch.Generator().manual_seed(4)
    n, history = 512, 1500  # late enough that Adam's bias corrections no longer shrink the steps
    scale = 10.0 ** (-6 + 8 * torch.rand(n, generator=g))
    growth = torch.where(torch.arange(n) % 4 == 0, 1.3, 1.0)  # a quarter: |m| / sqrt(v) near its limit
    noise = torch.rand(n, generator=g)  # per row: from pure noise (0) to one steady sign (1)

    def run(kind: str, spikes: int):
        p = torch.nn.Parameter(torch.randn(n, generator=g))
        group = dict(params=[p], lr=0.01, name="t_means")
        opt = torch.optim.Adam([group], eps=1e-15) if kind == "adam" else SeenAdam([group], eps=1e-15)
        step = (lambda: opt.step()) if kind == "adam" else (lambda: opt.step(torch.ones(n, dtype=torch.bool)))
        for j in range(history):
            sign = torch.where(torch.rand(n, generator=g) < noise, 1.0, torch.sign(torch.randn(n, generator=g)))
            p.grad = sign * scale * growth ** max(j - history + 40, 0)
            step()
        bound = alive.adam_reach(p, opt.param_groups[0], opt.state[p], None, dense=kind == "adam", spikes=spikes)
        start, far = p.detach().double().clone(), torch.zeros(n, dtype=torch.float64)
        for j in range(spikes + (400 if kind == "adam" else 0)):
            if j < spikes:
                p.grad = torch.sign(torch.randn(n, generator=g)) * scale * 10.0 ** (8 * torch.rand(n, generator=g) - 2)
            else:
                p.grad = torch.zeros(n)
            step()
            far = torch.maximum(far, (p.detach().double() - start).abs())
        return far, bound

    for kind, spikes in (("adam", 0), ("adam", 1), ("adam", 2), ("seen", 1), ("seen", 2)):
        far, bound = run(kind, spikes)
        assert bool((far <= bound).all()), (kind, spikes, float((far / bound).max()))
        assert float((far / bound).max()) > 0.3, (kind, spikes)  # and not loose by orders of magnitude


def compare_steps(trainer, frames) -> float:
    """Largest difference in loss and gradients between a render of the indexed rows and of all N,
    from the trainer's current parameters, over `frames`."""
    params = list(trainer.model.parameters_by_name().values())
    worst = 0.0
    for k in frames:
        out = []
        for index in (trainer.alive, None):
            saved, trainer.alive = trainer.alive, index
            image, alpha, meta = trainer.render(k)
            trainer.alive = saved
            loss = trainer.loss(k, image, alpha, trainer.target(k, image))
            grads = torch.autograd.grad(loss, params, allow_unused=True)
            out.append((image.detach(), loss.detach(), [torch.zeros_like(p) if v is None else v
                                                        for p, v in zip(params, grads)]))
        (image, loss, grads), (full_image, full_loss, full_grads) = out
        worst = max(worst, float((image - full_image).abs().max()), float((loss - full_loss).abs()))
        for v, w in zip(grads, full_grads):
            if v.numel():  # sh_rest at degree 0 has no columns
                worst = max(worst, float(((v - w).abs() / (1 + w.abs())).max()))
    return worst


@pytest.mark.parametrize("sparse, lookahead, faster", [(False, False, 1.0), (True, True, 3.0)])
def test_training_with_the_index_takes_the_steps_training_without_takes(sparse, lookahead, faster):
    """Over 60 steps where the windows move (short windows, no headroom, the temporal learning rates
    x `faster`) and densification changes the set: at every step each Gaussian projection finds alive
    at any frame is in that frame's rows, and the loss and gradients equal those of a render of all
    N to 1e-6. CPU (dense Adam, checks read at once) and GPU (SeenAdam, read a step late) settings."""
    steps, frames = 60, 16
    images, cams, points, colors = synthetic_clip(frames, 32, 18)
    config = small_config(steps, sparse_adam=sparse, lr_t_means=1e-3 * faster, lr_t_scales=1e-2 * faster,
                          grad_threshold=1e-7, init_t_scale_frames=0.7).replace(
        densify_interval=20, densify_start_fraction=0.3, max_gaussians=3000)
    trainer = Trainer(images, cams, points, colors, config, CPU)
    trainer.alive.lookahead, trainer.alive.headroom = lookahead, 0.0
    start_means = trainer.model.t_means.detach().clone()
    sizes, movers, worst, subsets = {len(trainer.model)}, 0, 0.0, 0
    for step in range(steps):
        model = trainer.model
        for k in range(frames):
            rows = trainer.alive.rows(k, model, trainer.optimizer, trainer.iteration)  # what step k would use
            subsets += rows is not None
            inputs = model.render_inputs()
            found = kernel_alive(*(inputs[x].detach() for x in ("opacities", "t_means", "t_scales")), trainer.times[k])
            assert set(torch.nonzero(found)[:, 0].tolist()) <= as_set(rows, len(model)), (step, k)
        if step % 6 == 0:
            worst = max(worst, compare_steps(trainer, [step % frames, (step * 5 + 3) % frames]))
        trainer.progress = step / steps  # what Trainer.run sets: the densification schedule reads it
        trainer.step()
        sizes.add(len(trainer.model))
        movers = max(movers, 0 if trainer.alive.movers is None else len(trainer.alive.movers))
    assert worst <= 1e-6
    assert len(sizes) > 1 and movers > 0 and subsets > steps * frames / 2  # densified, escaped, a subset
    kept = min(len(start_means), len(trainer.model))
    moved = float((trainer.model.t_means.detach()[:kept] - start_means[:kept]).abs().max())
    assert moved > 0.5 / (frames - 1)  # windows moved by half a frame and more


@pytest.mark.parametrize("sparse", [False, True])
def test_a_step_with_the_index_is_a_step_without(sparse):
    """One step from the same start, with and without the index: same parameters, Adam moments and
    densification statistics (the subset's meta mapped back to all N)."""
    images, cams, points, colors = synthetic_clip(12, 32, 18)
    runs = []
    for use in (True, False):
        config = small_config(20, sparse_adam=sparse, alive_index=use, init_t_scale_frames=0.7)
        trainer = Trainer(images, cams, points, colors, config, CPU)
        for _ in range(3):
            trainer.step()
        runs.append(trainer)
    with_index, without = runs
    assert with_index.alive is not None and without.alive is None
    assert with_index.render(2)[2]["rows"] is not None  # a subset really rendered
    for name, p in with_index.model.parameters_by_name().items():
        q = without.model.parameters_by_name()[name]
        torch.testing.assert_close(p.detach(), q.detach(), rtol=1e-6, atol=1e-6)
        ours, theirs = with_index.optimizer.state[p], without.optimizer.state[q]
        assert set(ours) == set(theirs)  # sh_rest at degree 0: no gradient, no state in either
        for key in set(ours) & {"exp_avg", "exp_avg_sq"}:
            torch.testing.assert_close(ours[key], theirs[key], rtol=1e-5, atol=1e-9)
    torch.testing.assert_close(with_index.densifier.grad_sum, without.densifier.grad_sum, rtol=1e-5, atol=1e-9)
    assert torch.equal(with_index.densifier.seen, without.densifier.seen)


def test_render_sequence_with_the_index_renders_what_all_gaussians_render():
    """Frames out of order and repeated, an SH cloud, and a per-frame cloud: every image equals a
    render of every Gaussian, bit for bit."""
    from tomgs.cameras import Cameras

    n, frames = 600, 30
    a, m, sigma = short_lived(n, 0.15, seed=3)
    g = torch.Generator().manual_seed(5)
    gaussians = dict(means=torch.randn(n, 3, generator=g) * 0.4 + torch.tensor([0.0, 0.0, 3.0]),
                     quats=torch.randn(n, 4, generator=g), scales=torch.full((n, 3), 0.08), opacities=a,
                     colors=torch.randn(n, 4, 3, generator=g) * 0.5, t_means=m, t_scales=sigma)
    c2w = np.repeat(np.eye(4)[None], frames, 0)
    c2w[:, 0, 3] = np.linspace(-0.2, 0.2, frames)
    cams = Cameras.create(c2w, K.numpy().astype(np.float64), 32, 24)
    order = [29, 3, 4, 4, 17, 0, 18, 5]
    subsets = 0
    for source in (gaussians, lambda k: gaussians):
        for (k, image, meta), want in zip(render_sequence(source, cams, order, background=(0.1, 0.2, 0.3)), order):
            assert k == want
            full, _, _ = rasterize(**gaussians, viewmat=cams.viewmats(CPU)[k], K=K, width=32, height=24,
                                   t=float(cams.times[k]), background=torch.tensor([0.1, 0.2, 0.3]))
            assert torch.equal(image, full.clamp(0, 1)), k
            subsets += meta["rows"] is not None and len(meta["rows"]) < n // 2
    assert subsets == 2 * len(order)


@pytest.mark.parametrize("dense, spikes, headroom", [(True, 0, 0.0), (True, 1, 4.0), (False, 1, 0.0), (False, 2, 4.0)])
def test_the_bound_kernel_keeps_the_torch_formula(dense, spikes, headroom):
    """tomgs/kernels/alive.py against alive.reach_reference (windows) and AliveIndex.covers (the
    check) on random states: moments from none to a v that underflowed under a live m, a temporal
    learning rate of 0, opacities across 1/255, NaN and far centres."""
    g = torch.Generator().manual_seed(6)
    n = 4000
    model = GaussianModel.from_points(torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g),
                                      torch.rand(n, generator=g) * 1.4 - 0.2, 0.02, max_sh_degree=0)
    with torch.no_grad():
        model.log_t_scales.copy_(torch.randn(n, generator=g) * 2 - 4)
        model.opacity_logits.copy_(torch.randn(n, generator=g) * 4 - 3)  # many near and below 1/255
        model.t_means[:20] = float("nan")
        model.t_means[20:40] = 1e6
    groups = [dict(params=[p], lr=0.0 if name == "log_t_scales" else 0.01 * (1 + i), name=name)
              for i, (name, p) in enumerate(model.parameters_by_name().items())]
    optimizer = torch.optim.Adam(groups, eps=1e-15) if dense else SeenAdam(groups, eps=1e-15)
    for name in ("t_means", "opacity_logits", "log_t_scales"):
        p = getattr(model, name)
        m = torch.randn(n, generator=g) * 10.0 ** (-4 * torch.rand(n, generator=g))
        v = m.square() * 10.0 ** (2 * torch.rand(n, generator=g) - 1.5)
        m[:100], v[100:200] = 0.0, 0.0  # no momentum; v underflowed under a live m
        optimizer.state[p] = dict(step=torch.tensor(50.0), exp_avg=m, exp_avg_sq=v)
    index = alive.TrainingIndex(np.linspace(0, 1, 31), dense=dense, lookahead=False)
    first, last = index.reach(model, optimizer, spikes, headroom)
    want_first, want_last = alive.reach_reference(model, optimizer, None, spikes=spikes, dense=dense,
                                                  headroom=headroom)
    never = ~(first <= last)  # alive at no time: first > last, or NaN (torch gives NaN where m is)
    assert torch.equal(never, ~(want_first <= want_last))
    for got, want in ((first[~never], want_first[~never]), (last[~never], want_last[~never])):
        same = got == want  # infinite ends
        close = torch.isclose(got, want, rtol=1e-4, atol=1e-7)  # r in float32 there, float64 here
        assert bool((same | close).all()), (got[~(same | close)][:5], want[~(same | close)][:5])
    assert bool(torch.isinf(first[~never]).any() and torch.isfinite(first).any() and never.any())
    # the check: a narrower index than the reach, so that some rows escape
    built = alive.build(*alive.reach_reference(model, optimizer, None, spikes=0, dense=False), index.times)
    index.index, index.stale, index.lookahead = built, False, bool(spikes)
    rows = torch.arange(0, n, 3, dtype=torch.int32)
    moved = torch.rand(len(rows), generator=g) < 0.7  # the rows the step gave a gradient: only they are checked
    want = moved & ~built.covers(*alive.reach_reference(model, optimizer, rows, spikes=int(spikes > 0), dense=dense),
                                 rows)
    index.check(model, optimizer, rows, moved)  # read at once (settle) without lookahead
    if index.lookahead:
        _, where, count, _ = index.pending
        assert int(count[0]) == int(want.sum()) > 0
        index.settle()
    escaped = rows[want].tolist()
    if len(escaped) > alive.MOVER_SHARE * n:
        assert index.stale and index.movers is None
    else:
        assert not index.stale and index.movers.tolist() == escaped
        assert bool((index.index.b_first[rows[want]] == 0).all())  # listed everywhere from now on


def test_the_index_is_used_where_it_pays():
    """On a CPU a trainer indexes by default; on a GPU it renders every Gaussian (tomgs.render.alive.pays_on:
    on the H100 the gathers cost more than projection's culling), unless asked either way. A
    sequence of one cloud's frames is indexed on a GPU from SEQUENCE_FRAMES frames."""
    from tomgs.render.alive import pays_on

    assert pays_on(torch.device("cpu")) and pays_on("cpu")
    assert not pays_on(torch.device("cuda")) and not pays_on("cuda:1")
    # rendering one cloud: its index pays for its build over a few tens of frames on a GPU
    assert alive.pays_for_sequence("cpu", 1) and alive.pays_for_sequence("cuda", alive.SEQUENCE_FRAMES)
    assert not alive.pays_for_sequence("cuda:1", alive.SEQUENCE_FRAMES - 1)
    images, cams, points, colors = synthetic_clip(3, 24, 14)
    for asked, indexed in ((None, True), (False, False), (True, True)):
        trainer = Trainer(images, cams, points, colors, small_config(5, alive_index=asked), torch.device("cpu"))
        assert (trainer.alive is not None) is indexed
