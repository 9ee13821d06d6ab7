"""tomgs.temporal: the one temporal-opacity formula, in torch and numpy, against float64 by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tomgs.constants import ALPHA_MIN
from tomgs.temporal import (alive_at, alive_between, alive_radius, alive_window, clip_time_to_frames,
                            frames_to_clip_time, opacity_at, peak_opacity, peak_opacity_at)


def by_hand(a: float, m: float, sigma: float, t: float) -> float:
    """o(t) in float64, written out from DESIGN.md."""
    return a * math.exp(-((t - m) ** 2) / (2 * sigma**2))


def random_windows(n: int, seed: int = 0):
    """float64 (a, m, sigma) [n]: opacities across 1/255, centres in and around the clip, sigmas over
    many decades."""
    rng = np.random.default_rng(seed)
    a = np.concatenate([rng.uniform(0, 1, n - n // 4), rng.uniform(0.5, 2.0, n // 4) / 255])
    m = rng.uniform(-0.5, 1.5, n)
    sigma = np.exp(rng.uniform(np.log(1e-4), np.log(1e2), n))
    return a, m, sigma


def test_numpy_and_torch_agree_with_the_formula_by_hand():
    a, m, sigma = random_windows(2000)
    for t in (0.0, 0.37, 1.0, -3.0):
        want = np.array([by_hand(*row, t) for row in zip(a, m, sigma)])
        got_np = opacity_at(a, m, sigma, t)
        got_64 = opacity_at(*(torch.from_numpy(x) for x in (a, m, sigma)), t)
        got_32 = opacity_at(*(torch.from_numpy(x).float() for x in (a, m, sigma)), t)
        assert isinstance(got_np, np.ndarray) and got_np.dtype == np.float64
        assert got_64.dtype == torch.float64 and got_32.dtype == torch.float32
        np.testing.assert_allclose(got_np, want, rtol=1e-12, atol=1e-300)
        np.testing.assert_allclose(got_64.numpy(), want, rtol=1e-12, atol=1e-300)
        # float32 against float64 of the same (rounded) inputs: the relative error grows with z^2
        a32, m32, s32, t32 = (np.float32(x).astype(np.float64) for x in (a, m, sigma, t))
        want32 = np.array([by_hand(*row, t32) for row in zip(a32, m32, s32)])
        z2 = ((t32 - m32) / s32) ** 2
        close = z2 < 50
        err = np.abs(got_32.numpy()[close] - want32[close])
        assert (err <= 1e-6 * (1 + z2[close]) * want32[close] + 1e-30).all()
        assert np.array_equal(alive_at(a, m, sigma, t), want >= ALPHA_MIN)
        got = alive_at(*(torch.from_numpy(x) for x in (a, m, sigma)), t)
        assert torch.equal(got, torch.from_numpy(want >= ALPHA_MIN))


def test_scalars_and_per_gaussian_times():
    assert opacity_at(0.5, 0.2, 0.1, 0.2) == 0.5
    assert opacity_at(0.5, 0.2, 0.1, 0.3) == pytest.approx(by_hand(0.5, 0.2, 0.1, 0.3), rel=1e-15)
    t = torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64)
    got = opacity_at(torch.full((3,), 0.8, dtype=torch.float64), torch.full((3,), 0.5, dtype=torch.float64),
                     torch.full((3,), 0.25, dtype=torch.float64), t)
    assert got.tolist() == pytest.approx([by_hand(0.8, 0.5, 0.25, v) for v in t.tolist()], rel=1e-15)


def test_below_alpha_min_never_alive():
    a = np.array([0.0, 1e-30, ALPHA_MIN * (1 - 1e-12), np.nextafter(ALPHA_MIN, 0)])
    m, sigma = np.full(4, 0.5), np.array([1e-30, 1.0, 1e30, 0.1])
    for t in (0.5, 0.0, 1.0, 1e9):
        assert not alive_at(a, m, sigma, t).any()
    assert not alive_between(a, m, sigma, -1e30, 1e30).any()
    first, last = alive_window(a, m, sigma)
    assert (first > last).all() and np.isneginf(alive_radius(a, sigma)).all()
    # torch, float32: the same
    at = torch.tensor(a[[0, 1, 3]], dtype=torch.float32).clamp_max(float(np.float32(ALPHA_MIN) * (1 - 1e-6)))
    mt, st = torch.full((3,), 0.5), torch.tensor([1e-30, 1.0, 1e30])
    assert not alive_at(at, mt, st, 0.5).any() and not alive_between(at, mt, st, -1e30, 1e30).any()
    first, last = alive_window(at, mt, st)
    assert (first > last).all()


def test_exactly_alpha_min_is_alive_only_at_the_centre():
    a, m, sigma = np.array([ALPHA_MIN]), np.array([0.25]), np.array([0.1])
    assert alive_at(a, m, sigma, 0.25).all() and not alive_at(a, m, sigma, 0.25 + 1e-6).any()  # 1e-9 rounds exp(-z^2/2) to 1
    assert alive_radius(a, sigma).tolist() == [0.0]
    assert alive_between(a, m, sigma, 0.0, 0.25).all() and not alive_between(a, m, sigma, 0.26, 1.0).any()


@pytest.mark.filterwarnings("ignore:overflow encountered")  # z^2 is inf for sigma 1e-300: o = 0, as it should
def test_tiny_and_huge_temporal_scales():
    a = np.array([0.5, 0.5, 0.5, 0.5])
    m = np.array([0.3, 0.3, 0.3, 0.3])
    sigma = np.array([1e-300, 1e-30, 1e30, 1e300])
    o = opacity_at(a, m, sigma, 0.3 + 1e-12)
    assert o.tolist() == [0.0, 0.0, 0.5, 0.5]
    assert alive_at(a, m, sigma, 0.3).all()  # z = 0 at the centre, whatever sigma
    r = alive_radius(a, sigma)
    assert r[0] < 1e-299 and r[1] < 1e-29 and r[2] > 1e30 and r[3] > 1e300
    assert alive_between(a, m, sigma, 0.0, 0.2).tolist() == [False, False, True, True]
    # float32: sigma past float32's range is inf (alive everywhere), below it 0 (alive nowhere, 0 / 0 at m)
    a32, m32 = torch.full((4,), 0.5), torch.full((4,), 0.3)
    s32 = torch.tensor([0.0, 1e-38, 1e38, float("inf")])
    assert alive_at(a32, m32, s32, 0.0).tolist() == [False, False, True, True]
    assert alive_between(a32, m32, s32, 0.0, 0.2).tolist() == [False, False, True, True]
    first, last = alive_window(a32, m32, s32)
    assert torch.isinf(first[3]) and torch.isinf(last[3]) and first[3] < 0 < last[3]


def test_window_edges():
    a, m, sigma = random_windows(3000, seed=1)
    ok = a >= ALPHA_MIN
    a, m, sigma = a[ok], m[ok], sigma[ok]
    r = alive_radius(a, sigma)
    first, last = alive_window(a, m, sigma)
    np.testing.assert_array_equal(first, m - r)
    np.testing.assert_array_equal(last, m + r)
    # at the edge the formula gives alpha_min, to float64 rounding; a hair inside alive, outside dead
    for edge in (first, last):
        np.testing.assert_allclose(opacity_at(a, m, sigma, edge), ALPHA_MIN, rtol=1e-9)
    wide = r > 1e-6 * np.maximum(np.abs(m), 1)  # a window wider than the float64 spacing of m
    inside, outside = m + r * (1 - 1e-6), m + r * (1 + 1e-6)
    assert alive_at(a, m, sigma, inside)[wide].all() and not alive_at(a, m, sigma, outside)[wide].any()
    assert alive_between(a, m, sigma, inside, inside + 1)[wide].all()
    assert not alive_between(a, m, sigma, outside, outside + 1)[wide].any()
    # an interval ending exactly at an edge is alive exactly when the edge itself is
    assert np.array_equal(alive_between(a, m, sigma, last, last + 1), alive_at(a, m, sigma, last))
    assert np.array_equal(alive_between(a, m, sigma, first - 1, first), alive_at(a, m, sigma, first))


def test_alive_between_is_alive_at_the_best_time():
    a, m, sigma = random_windows(2000, seed=2)
    grid = np.linspace(0.0, 1.0, 2001)
    dense = np.stack([opacity_at(a, m, sigma, t) for t in grid])  # [T,N]
    peak = peak_opacity(a, m, sigma, 0.0, 1.0)
    assert (peak >= dense.max(0) * (1 - 1e-12)).all()
    on_grid = (m >= 0) & (m <= 1)
    np.testing.assert_allclose(peak[~on_grid], dense.max(0)[~on_grid], rtol=1e-12)  # at an end of the clip
    for t in (0.0, 0.5, 1.0, grid[777]):
        assert np.array_equal(alive_between(a, m, sigma, t, t), alive_at(a, m, sigma, t))
    for dtype in (torch.float32, torch.float64):
        at, mt, st = (torch.from_numpy(x).to(dtype) for x in (a, m, sigma))
        for t in (0.0, 0.5, 1.0):
            assert torch.equal(alive_between(at, mt, st, t, t), alive_at(at, mt, st, t))
        both = alive_between(at, mt, st, 0.2, 0.6)
        per_time = torch.stack([alive_at(at, mt, st, t) for t in np.linspace(0.2, 0.6, 401).tolist()]).any(0)
        assert bool((both | ~per_time).all())  # alive at a sampled time: alive in the interval


@pytest.mark.parametrize("frames", [1, 2, 7, 90])
def test_the_peak_at_frame_times_is_the_largest_over_them(frames):
    """peak_opacity_at against every frame's opacity (numpy float64, torch float32 and float64), on
    windows over many decades: narrow ones between frames peak at none of them."""
    a, m, sigma = random_windows(3000, seed=frames)
    times = np.sort(np.random.default_rng(frames).uniform(0, 1, frames)) if frames == 7 else \
        np.arange(frames) / max(frames - 1, 1)
    every = np.stack([opacity_at(a, m, sigma, t) for t in times]).max(0)
    np.testing.assert_array_equal(peak_opacity_at(a, m, sigma, times), every)
    for dtype in (torch.float32, torch.float64):
        at, mt, st, tt = (torch.from_numpy(x).to(dtype) for x in (a, m, sigma, times))
        want = torch.stack([opacity_at(at, mt, st, t) for t in tt]).amax(0)
        assert torch.equal(peak_opacity_at(at, mt, st, tt), want)
    if frames > 1:  # a window between two frames, alive inside the clip but at no frame
        between = peak_opacity_at(np.array([1.0]), np.array([times[0] / 2 + times[1] / 2]), np.array([1e-3]), times)
        assert between[0] < ALPHA_MIN <= peak_opacity(1.0, times[0] / 2 + times[1] / 2, 1e-3, 0.0, 1.0)


def test_float32_alive_lies_in_the_slack_window():
    a, m, sigma = (torch.from_numpy(x).float() for x in random_windows(5000, seed=3))
    first, last = alive_window(a, m, sigma, slack=1e-3)
    strict_first, strict_last = alive_window(a, m, sigma)
    assert bool((first <= strict_first).all() and (last >= strict_last).all())
    for t in np.linspace(-0.5, 1.5, 81).tolist():
        alive = alive_at(a, m, sigma, t)
        assert bool(((first <= t) & (t <= last))[alive].all())


def test_numpy_window_matches_torch():
    a, m, sigma = random_windows(1000, seed=4)
    first, last = alive_window(a, m, sigma, slack=1e-3)
    tf, tl = alive_window(*(torch.from_numpy(x) for x in (a, m, sigma)), slack=1e-3)
    np.testing.assert_allclose(tf.numpy(), first, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(tl.numpy(), last, rtol=1e-13, atol=1e-15)
    assert np.array_equal(np.isneginf(alive_radius(a, sigma)), a < ALPHA_MIN)


def test_the_warp_kernel_keeps_the_same_formula():
    """The projection kernel's o_i(t) (its own Warp copy) against this module in float32."""
    from tomgs.render.frame import rasterize

    g = torch.Generator().manual_seed(5)
    n = 3000
    a, m, sigma = (torch.from_numpy(x).float() for x in random_windows(n, seed=5))
    means = torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 4.0])
    inputs = dict(means=means, quats=torch.randn(n, 4, generator=g), scales=torch.full((n, 3), 0.05),
                  opacities=a, colors=torch.rand(n, 3, generator=g), t_means=m, t_scales=sigma)
    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])
    for t in (0.0, 0.4, 1.0):
        _, _, meta = rasterize(**inputs, viewmat=torch.eye(4), K=K, width=32, height=32, t=t)
        # the kernel forms t - m from t in float64 (hi + lo): compare with float64 of its float32 inputs
        exact = opacity_at(*(x.double() for x in (a, m, sigma)), t)
        kernel = meta["opacities_t"].double()
        z2 = ((t - m.double()) / sigma.double()) ** 2
        close = z2 < 20
        assert bool(((kernel - exact).abs() <= 1e-6 * (1 + z2) * exact + 1e-30)[close].all())
        clear = (exact / ALPHA_MIN - 1).abs() > 1e-3  # away from the edge, where float32 roundings differ
        assert torch.equal((kernel >= ALPHA_MIN)[clear], alive_at(a, m, sigma, t)[clear])
        assert int(meta["n_alive"]) == pytest.approx(int(alive_at(a, m, sigma, t).sum()), abs=int((~clear).sum()))


def test_frames_and_clip_time():
    assert frames_to_clip_time(2.0, 41) == 2.0 / 40
    assert clip_time_to_frames(frames_to_clip_time(3.0, 11), 11) == pytest.approx(3.0)
    assert frames_to_clip_time(2.0, 1) == 2.0 and clip_time_to_frames(0.5, 1) == 0.5  # one frame: clip units
    sigma = np.array([0.025, 0.1])
    np.testing.assert_allclose(clip_time_to_frames(sigma, 41), [1.0, 4.0])
    assert torch.equal(frames_to_clip_time(torch.tensor([4.0]), 5), torch.tensor([1.0]))


def test_frozen_at_renders_that_moment_with_only_the_alive_gaussians():
    """A frozen cloud (alive Gaussians, opacity baked) rendered at t is the full cloud rendered at t,
    and it drops exactly the Gaussians dead at t."""
    import tomgs
    from tests.scenes import random_scene
    from tomgs.temporal import frozen_at

    for seed in range(3):
        scene = {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in random_scene(700 + seed, n=300).items()}
        scene["t_scales"][:40] = 1e-3  # many dead at t
        names = ("means", "quats", "scales", "opacities", "colors", "t_means", "t_scales")
        gaussians = {k: scene[k] for k in names}
        view = dict(viewmat=scene["viewmat"], K=scene["K"], width=scene["width"], height=scene["height"],
                    background=scene["background"])
        t = scene["t"]
        frozen = frozen_at(gaussians, t)
        alive = alive_at(gaussians["opacities"].double(), gaussians["t_means"].double(),
                         gaussians["t_scales"].double(), t)
        assert len(frozen["means"]) == int(alive.sum()) < 300
        assert set(frozen) == set(names)
        want = opacity_at(*(gaussians[k].double() for k in ("opacities", "t_means", "t_scales")), t)[alive]
        torch.testing.assert_close(frozen["opacities"].double(), want, rtol=1e-6, atol=0)
        full, full_alpha, _ = tomgs.rasterize(**gaussians, **view, t=t)
        still, still_alpha, _ = tomgs.rasterize(**frozen, **view, t=t)
        torch.testing.assert_close(still, full, rtol=0, atol=2e-6)
        torch.testing.assert_close(still_alpha, full_alpha, rtol=0, atol=2e-6)
    empty = frozen_at({k: v[:0] for k, v in gaussians.items()}, 0.5)
    assert all(len(v) == 0 for v in empty.values())
