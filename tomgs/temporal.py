"""Temporal opacity: the one formula (docs/design.md "The representation"), and its alive window.

Gaussian i with base opacity a, temporal mean m and temporal scale sigma has, at clip time t,

    o(t) = a exp(-z^2 / 2),   z = (t - m) / sigma

and is alive at t when o(t) >= alpha_min (ALPHA_MIN = 1/255, what the renderer culls by): within
r = sigma sqrt(2 ln(a / alpha_min)) of m, never when a < alpha_min.

Every function takes torch tensors or numpy arrays (Python numbers too) and computes in their dtype,
so a caller picks its precision by what it passes (the renderer float32, selections float64); the
result is a tensor when any argument is one, else numpy. The Warp kernels (tomgs/kernels/project.py)
keep a copy of the formula, as kernels cannot call torch; tests hold them to this one.

Durations in frames and in clip time convert here too: frame k of n sits at t = k / (n - 1)
(tomgs.cameras.frame_times), so one frame lasts 1 / (n - 1) of the clip (a single frame: 1).
"""

from __future__ import annotations

import sys

import numpy as np

from tomgs.constants import ALPHA_MIN


def _xp(*values):
    """torch when any value is a tensor (torch is imported by then), else numpy."""
    torch = sys.modules.get("torch")
    if torch is not None and any(isinstance(v, torch.Tensor) for v in values):
        return torch
    return np


def _clamp(xp, x, lo=None, hi=None):
    return xp.clamp(x, lo, hi) if xp is not np else np.clip(x, lo, hi)


def opacity_at(opacities, t_means, t_scales, t):
    """o(t) [N] = a exp(-z^2 / 2), z = (t - m) / sigma, for opacities a, t_means m, t_scales sigma
    [N] and a clip time t (a number, a 0-d array or [N])."""
    xp = _xp(opacities, t_means, t_scales, t)
    z = (t - t_means) / t_scales
    return opacities * xp.exp(-0.5 * z * z)


def alive_at(opacities, t_means, t_scales, t, alpha_min: float = ALPHA_MIN):
    """bool [N]: o(t) >= alpha_min (false where o(t) is NaN)."""
    return opacity_at(opacities, t_means, t_scales, t) >= alpha_min


def peak_opacity(opacities, t_means, t_scales, t0, t1):
    """[N]: the largest o(t) for t in [t0, t1] (t0 <= t1): o at the temporal mean clamped into it."""
    xp = _xp(opacities, t_means, t_scales)
    return opacity_at(opacities, t_means, t_scales, _clamp(xp, t_means, t0, t1))


def peak_opacity_at(opacities, t_means, t_scales, times):
    """[N]: the largest o(t) over the clip times `times` ([T], ascending, as the Gaussians' type: a
    tensor on their device or an array): o at the time on either side of the temporal mean, since o
    falls away from it. A Gaussian that peaks between frames may be alive at none of them."""
    xp = _xp(opacities, t_means, t_scales, times)
    last = len(times) - 1
    after = _clamp(xp, xp.searchsorted(times, t_means), 0, last)
    before = _clamp(xp, after - 1, 0, last)
    return xp.maximum(opacity_at(opacities, t_means, t_scales, times[before]),
                      opacity_at(opacities, t_means, t_scales, times[after]))


def alive_between(opacities, t_means, t_scales, t0, t1, alpha_min: float = ALPHA_MIN):
    """bool [N]: alive (o(t) >= alpha_min) for some t in [t0, t1] (t0 <= t1); alive_between(t, t)
    is alive_at(t) exactly, as both evaluate the one formula at the same time."""
    return peak_opacity(opacities, t_means, t_scales, t0, t1) >= alpha_min


def alive_radius(opacities, t_scales, alpha_min: float = ALPHA_MIN, slack: float = 0.0):
    """r [N] = sigma sqrt(2 ln(a / alpha_min)): alive within r of the temporal mean; -inf where
    a < alpha_min (alive at no time). `slack` > 0 widens it to sigma (sqrt(...) (1 + slack) + slack),
    for a caller that must never miss a Gaussian the float32 renderer finds alive (gathering)."""
    xp = _xp(opacities, t_scales)
    reach = xp.sqrt(2.0 * xp.log(_clamp(xp, opacities / alpha_min, 1.0))) * (1.0 + slack) + slack
    return xp.where(opacities >= alpha_min, reach * t_scales, -float("inf"))


def alive_window(opacities, t_means, t_scales, alpha_min: float = ALPHA_MIN, slack: float = 0.0):
    """(first [N], last [N]) = m -+ r (`alive_radius`): the clip times between which o(t) >= alpha_min;
    first > last when alive at no time."""
    r = alive_radius(opacities, t_scales, alpha_min, slack)
    return t_means - r, t_means + r


def frozen_at(gaussians: dict, t: float, alpha_min: float = ALPHA_MIN) -> dict:
    """One moment of a clip as a static cloud: the Gaussians of `gaussians` (the rasterizer's inputs,
    `GaussianModel.render_inputs()`: means [N,3], quats [N,4], scales [N,3], opacities [N], colors
    [N,K,3], t_means [N], t_scales [N]) alive at clip time t, with their opacity at t baked into
    `opacities` (computed in float64, then in the inputs' dtype). Same keys, rows of the alive ones,
    detached; `t_means` = t and `t_scales` = 1 so that rendering the result at t draws each with
    exactly its baked opacity, and a static tool that ignores the temporal fields sees that moment."""
    opacities = gaussians["opacities"].detach()
    at_t = opacity_at(opacities.double(), gaussians["t_means"].detach().double(),
                      gaussians["t_scales"].detach().double(), float(t))
    rows = (at_t >= alpha_min).nonzero()[:, 0]  # one index for every key: far cheaper than a mask per key
    frozen = {name: value.detach().index_select(0, rows) for name, value in gaussians.items()}
    frozen["opacities"] = at_t.index_select(0, rows).to(opacities.dtype)
    frozen["t_means"] = frozen["t_means"].new_full(frozen["t_means"].shape, float(t))
    frozen["t_scales"] = frozen["t_scales"].new_ones(frozen["t_scales"].shape)
    return frozen


def frames_to_clip_time(frames, num_frames: int):
    """A duration of `frames` frames of an n-frame clip in clip time: frames / (n - 1)."""
    return frames / max(num_frames - 1, 1)


def clip_time_to_frames(duration, num_frames: int):
    """A clip-time duration in frames of an n-frame clip: duration (n - 1) (clip units for n = 1)."""
    return duration * max(num_frames - 1, 1)


__all__ = ["opacity_at", "alive_at", "peak_opacity", "alive_between", "alive_radius", "alive_window",
           "frozen_at", "frames_to_clip_time", "clip_time_to_frames"]
