"""tomgs.model owns the activations (both ways) and gives its Gaussians' temporal opacity."""

from __future__ import annotations

import math

import numpy as np
import torch

from tomgs import temporal
from tomgs.model import (GaussianModel, PlanarGaussianModel, activated_opacities, activated_scales,
                         activated_t_scales, stored_opacities, stored_scales, stored_t_scales)


def test_stored_inverts_activated_for_tensors_arrays_and_numbers():
    x = torch.linspace(-6, 6, 101, dtype=torch.float64)
    torch.testing.assert_close(stored_scales(activated_scales(x)), x)
    torch.testing.assert_close(stored_t_scales(activated_t_scales(x)), x)
    torch.testing.assert_close(stored_opacities(activated_opacities(x)), x)
    a = np.array([0.01, 0.5, 0.99])
    assert isinstance(stored_opacities(a), np.ndarray) and isinstance(stored_scales(a), np.ndarray)
    np.testing.assert_allclose(activated_opacities(torch.from_numpy(stored_opacities(a))).numpy(), a, rtol=1e-15)
    assert stored_opacities(0.01) == math.log(0.01 / 0.99) and stored_t_scales(1e3) == math.log(1e3)


def test_from_points_takes_one_or_per_point_temporal_sigmas():
    points, colors, t = torch.rand(5, 3), torch.rand(5, 3), torch.linspace(0, 1, 5)
    sizes = torch.full((5,), 0.1)
    one = GaussianModel.from_points(points, colors, t, 0.25, max_sh_degree=0, sizes=sizes)
    assert one.log_t_scales.tolist() == [np.float32(math.log(0.25))] * 5
    sigma = torch.tensor([0.1, 0.2, 0.3, 0.4, 1.0])
    each = GaussianModel.from_points(points, colors, t, sigma, max_sh_degree=0, sizes=sizes)
    assert torch.equal(each.log_t_scales.detach(), torch.log(sigma))
    torch.testing.assert_close(each.t_scales, sigma)
    planar = PlanarGaussianModel.from_points(points, colors, t, sigma, max_sh_degree=0, sizes=sizes)
    torch.testing.assert_close(planar.t_scales, sigma)


def test_model_temporal_opacity_is_the_one_formula():
    g = torch.Generator().manual_seed(0)
    n = 500
    r = lambda *shape: torch.randn(*shape, generator=g)  # noqa: E731
    model = GaussianModel(r(n, 3), r(n, 4), r(n, 3), r(n) * 3, r(n, 1, 3), torch.zeros(n, 0, 3),
                          torch.rand(n, generator=g) * 2 - 0.5, r(n) - 2)
    a, m, s = model.opacities, model.t_means, model.t_scales
    for t in (0.0, 0.3, 1.0):
        assert torch.equal(model.opacity_at(t), temporal.opacity_at(a, m, s, t))
        assert torch.equal(model.alive_at(t), temporal.alive_at(a, m, s, t))
    assert torch.equal(model.peak_opacity(0.0, 1.0), temporal.peak_opacity(a, m, s, 0.0, 1.0))
    assert 0 < int(model.alive_at(0.3).sum()) < n
