"""Fuzz `rasterize` with random and extreme scenes against the float64 reference (seeded, CPU).

Every scene mixes ordinary Gaussians with needles, discs, tiny and huge ones, quaternions of any
norm, opacities at the ends of [0, 1], temporal windows from 1e-9 to 1e3 around a float64 time,
depths from the near plane to 1e9, Gaussians behind the camera or off screen, non-finite rows,
RGB or SH colours, odd image sizes, affine cameras and clip planes. In contract, the image, alpha,
radii and every gradient must match the float64 reference (`assert_matches_within_float32`: to
IMAGE_TOL / GRAD_TOL, or to 3x the float32 reference's own error where float32 cannot do better).
Out of contract (one violation planted in some scenes), a RenderError must name the input.
No other exception may escape. TOMGS_FUZZ_SEED picks another family of scenes.
"""

from __future__ import annotations

import math
import os

import pytest
import torch

import tomgs
from scenes import INPUT_NAMES, look_at
from tests.render.test_raster import assert_matches_within_float32

FUZZ_SEED = int(os.environ.get("TOMGS_FUZZ_SEED", "0"))
CHUNKS = 8  # pytest cases, so a failure names its chunk and the run shows progress
SCENES_PER_CHUNK = 120
BAD_EVERY = 5  # one scene in five carries one out-of-contract input


class Draw:
    """Seeded float64 draws."""

    def __init__(self, seed: int):
        self.g = torch.Generator().manual_seed(seed)

    def u(self, lo: float = 0.0, hi: float = 1.0, *shape) -> torch.Tensor | float:
        x = lo + (hi - lo) * torch.rand(*(shape or (1,)), generator=self.g, dtype=torch.float64)
        return x if shape else float(x)

    def n(self, *shape) -> torch.Tensor:
        return torch.randn(*shape, generator=self.g, dtype=torch.float64)

    def log(self, lo: float, hi: float, *shape):
        """10 ** U(lo, hi)."""
        return 10.0 ** self.u(lo, hi, *shape) if shape else 10.0 ** self.u(lo, hi)

    def pick(self, options: list):
        return options[int(torch.randint(len(options), (1,), generator=self.g))]

    def chance(self, p: float) -> bool:
        return self.u() < p


def random_direction(d: Draw) -> torch.Tensor:
    v = d.n(3)
    return v / v.norm().clamp_min(1e-12)


def fuzz_scene(seed: int) -> dict:
    """One random scene (float64 tensors; `rasterize` sees their float32 values) with near/far/t."""
    d = Draw(seed)
    width = d.pick([1, 3, 16, 17, 24, 33, 40])
    height = d.pick([1, 7, 16, 20, 31])
    eye = d.n(3) * d.pick([0.0, 0.5, 3.0])
    view = look_at(eye, eye + random_direction(d) * 3.0)
    if d.chance(0.15):  # an affine camera: world units scaled per axis (EWA holds for any linear map)
        view[:3] = torch.diag(d.log(-0.5, 0.5, 3)) @ view[:3]
    c2w = torch.linalg.inv(view)
    focal = max(width, height) * d.log(-0.5, 0.5)
    K = torch.tensor([[focal, 0.0, width / 2 + d.u(-3, 3)], [0.0, focal * d.u(0.8, 1.25), height / 2 + d.u(-3, 3)],
                      [0.0, 0.0, 1.0]], dtype=torch.float64)
    near = d.pick([0.01, 0.01, 1e-3, 0.3])
    far = d.pick([1e10, 1e10, math.inf, 30.0])
    t = d.u()  # a float64: not rounded to float32
    n = d.pick([0, 1, 2, 5, 30, 60, 60])

    # positions in camera space, by kind
    cam = torch.stack([d.n(n) * 0.5, d.n(n) * 0.4, d.u(0.5, 8.0, n)], -1)
    for i in range(n):
        kind = d.pick(["plain"] * 6 + ["near", "behind", "side", "far", "centre", "cluster"])
        if kind == "near":  # 1% .. 100% beyond the near plane: closer is a coin flip in float32 (the
            # depth is a sum of world coordinates ~10 that cancels to ~near), for any float32 renderer
            cam[i, 2] = near * (1 + d.log(-2, 0))
            cam[i, :2] *= cam[i, 2]
        elif kind == "behind":
            cam[i, 2] = -d.u(0.0, 3.0)
        elif kind == "side":
            cam[i, 0] += d.pick([-1.0, 1.0]) * d.u(2.0, 8.0) * cam[i, 2]
        elif kind == "far":
            cam[i] *= d.log(3, 9)
        elif kind == "centre":
            cam[i] = 0.0
        elif kind == "cluster":
            cam[i] = torch.tensor([0.0, 0.0, 2.5], dtype=torch.float64) + 0.05 * d.n(3)
    means = cam @ c2w[:3, :3].T + c2w[:3, 3]

    # shapes, by kind
    scales = torch.exp(d.n(n, 3) * 0.7 - 2.5)
    for i in range(n):
        kind = d.pick(["plain"] * 4 + ["needle", "needle", "disc", "tiny", "huge", "zero"])
        if kind == "needle":
            scales[i] = torch.tensor([d.log(0, 4), d.log(-5, -2), d.log(-5, -2)], dtype=torch.float64)
            scales[i] = scales[i][torch.randperm(3, generator=d.g)]
        elif kind == "disc":
            scales[i] = torch.tensor([d.log(-1, 1), d.log(-1, 1), d.log(-8, -3)], dtype=torch.float64)
        elif kind == "tiny":  # never exactly isotropic: the quaternion gradient would be 0 + rounding noise
            scales[i] = d.log(-9, -5, 3)
        elif kind == "huge":
            scales[i] = d.log(2, 4, 3)
        elif kind == "zero":
            scales[i, int(d.u(0, 3))] = 0.0
    quats = d.n(n, 4)
    quats = quats / quats.norm(dim=-1, keepdim=True) * d.log(-0.5, 0.5, n, 1)
    for i in range(n):
        kind = d.pick(["plain"] * 6 + ["big", "small", "below_eps", "zero"])
        if kind == "big":
            quats[i] *= d.log(10, 25)
        elif kind == "small":
            quats[i] *= d.log(-11, -5)
        elif kind == "below_eps":
            quats[i] *= d.log(-25, -13)
        elif kind == "zero":
            quats[i] = 0.0

    opacities = d.u(0.0, 1.0, n)
    t_scales = d.log(-2.5, 0.5, n)
    t_means = d.u(0.0, 1.0, n)
    for i in range(n):
        kind = d.pick(["plain"] * 4 + ["zero", "one", "threshold", "short", "short", "long", "dead"])
        if kind == "zero":
            opacities[i] = 0.0
        elif kind == "one":
            opacities[i] = 1.0
        elif kind == "threshold":
            opacities[i] = (1 / 255) * (1 + d.log(-3, -1))
        elif kind == "short":  # a window below float32's resolution of t, centred near it
            t_scales[i] = d.log(-9, -5)
            t_means[i] = float(torch.tensor(t, dtype=torch.float32)) + d.u(-2.5, 2.5) * t_scales[i]
        elif kind == "long":
            t_scales[i] = d.log(1, 3)
        elif kind == "dead":
            t_means[i] = t + d.pick([-1.0, 1.0]) * 1e4 * t_scales[i]
    if d.chance(0.3):
        colors = d.n(n, d.pick([1, 4, 9, 16]), 3) * 0.5
    else:
        colors = d.u(0.0, 1.0, n, 3)

    # non-finite rows are culled, never drawn, and get finite (zero) gradients
    for i in range(n):
        if d.chance(0.03):
            which = d.pick(["means", "scales", "quats", "t_means", "t_scales_zero"])
            value = d.pick([math.nan, math.inf, -math.inf])
            if which == "means":
                means[i, int(d.u(0, 3))] = value
            elif which == "scales":
                scales[i, int(d.u(0, 3))] = abs(value) if value == value else value
            elif which == "quats":
                quats[i, int(d.u(0, 4))] = value
            elif which == "t_means":
                t_means[i] = value
            else:
                t_scales[i], t_means[i] = 0.0, float(torch.tensor(t, dtype=torch.float32))
    background = d.u(0.0, 1.0, 3) if d.chance(0.6) else None
    return dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, t_means=t_means,
                t_scales=t_scales, viewmat=view, K=K, background=background, width=width, height=height, t=t,
                near=near, far=far)


# (input, how to break it): a RenderError must name the input
VIOLATIONS = [
    ("opacities", lambda s, d: s["opacities"].__setitem__(int(d.u(0, len(s["opacities"]))),
                                                          d.pick([1.0 + d.log(-6, 1), -d.log(-6, 0), math.inf,
                                                                  -math.inf, math.nan]))),
    ("scales", lambda s, d: s["scales"].__setitem__((int(d.u(0, len(s["scales"]))), int(d.u(0, 3))),
                                                    -d.log(-8, 2))),
    ("t_scales", lambda s, d: s["t_scales"].__setitem__(int(d.u(0, len(s["t_scales"]))), -d.log(-8, 2))),
    ("K", lambda s, d: s["K"].__setitem__(d.pick([(0, 0), (1, 1)]), d.pick([0.0, -1.0, -1e-30, math.nan]))),
    ("K", lambda s, d: s["K"].__setitem__(d.pick([(0, 2), (1, 2), (2, 2)]), d.pick([math.nan, math.inf]))),
    ("viewmat", lambda s, d: s["viewmat"].__setitem__((int(d.u(0, 3)), int(d.u(0, 4))),
                                                      d.pick([math.nan, math.inf, -math.inf]))),
    ("background", lambda s, d: s.__setitem__("background", torch.tensor([0.5, d.pick([math.nan, math.inf]), 0.1],
                                                                         dtype=torch.float64))),
    ("width", lambda s, d: s.__setitem__("width", d.pick([math.nan, math.inf, 12.5, 0, -4]))),
    ("height", lambda s, d: s.__setitem__("height", d.pick([math.nan, -math.inf, 0.5]))),
    ("t", lambda s, d: s.__setitem__("t", d.pick([math.nan, math.inf, -math.inf, 1e39, -1e300]))),
    ("near", lambda s, d: s.__setitem__("near", d.pick([math.nan, 0.0, -1.0, math.inf]))),
]


def _rasterize(scene: dict):
    tensors = {k: (None if scene[k] is None else scene[k].float()) for k in INPUT_NAMES}
    return tomgs.rasterize(**tensors, width=scene["width"], height=scene["height"], t=scene["t"],
                           near=scene["near"], far=scene["far"])


@pytest.mark.parametrize("chunk", range(CHUNKS))
def test_fuzz_against_the_float64_reference(chunk):
    checked = refused = 0
    for k in range(SCENES_PER_CHUNK):
        seed = FUZZ_SEED * 100_000 + chunk * SCENES_PER_CHUNK + k
        scene = fuzz_scene(seed)
        d = Draw(seed + 77_777)
        if seed % BAD_EVERY == BAD_EVERY - 1:
            candidates = [v for v in VIOLATIONS if scene["means"].shape[0] > 0 or
                          v[0] not in ("opacities", "scales", "t_scales")]
            name, plant = d.pick(candidates)
            plant(scene, d)
            with pytest.raises(tomgs.RenderError, match=name):
                _rasterize(scene)
            refused += 1
            continue
        try:
            args = {k: v for k, v in scene.items() if k not in ("near", "far", "t")}
            if scene["background"] is None:  # the helper differentiates every input: use a zero background
                args["background"] = torch.zeros(3, dtype=torch.float64)
            assert_matches_within_float32(args, "cpu", t=scene["t"], near=scene["near"], far=scene["far"],
                                          thin_slack=True)
        except AssertionError as error:
            raise AssertionError(f"fuzz scene seed {seed}: {error}") from error
        checked += 1
    assert checked + refused == SCENES_PER_CHUNK
