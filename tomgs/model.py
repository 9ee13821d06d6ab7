"""GaussianModel: the stored parameters of a TOM-GS scene and the one place that activates them.

Stored (unconstrained, what the optimiser sees), per Gaussian:
    means [N,3]  quats [N,4] (w x y z, raw)  log_scales [N,3]  opacity_logits [N]
    sh_dc [N,1,3]  sh_rest [N,K-1,3] (K = (max_degree + 1)^2)  t_means [N]  log_t_scales [N]
Activated (what the renderer takes): scales = exp(log_scales), opacities = sigmoid(logits),
t_scales = exp(log_t_scales), SH truncated to the active degree. Optimising log(sigma) keeps
the temporal window's gradient bounded (docs/design.md: d o / d log sigma = o z^2 <= 2a/e).

The activations and their inverses (`activated_*`, `stored_*`) live here and nowhere else: code
that holds raw parameters (densification, edits writing geometry back) goes through them; the
temporal opacity of a model is tomgs.temporal's formula on its activated values.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from tomgs import temporal
from tomgs.constants import ALPHA_MIN, SH_C0, sh_degree_of

PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest", "t_means", "log_t_scales")
RENDER_INPUTS = ("means", "quats", "scales", "opacities", "colors", "t_means", "t_scales")  # `render_inputs` keys


# -- the activations, both ways: stored (unconstrained) <-> what the renderer takes -------------------

def activated_scales(log_scales: torch.Tensor) -> torch.Tensor:
    return torch.exp(log_scales)


def activated_opacities(opacity_logits: torch.Tensor) -> torch.Tensor:
    return torch.sigmoid(opacity_logits)


def activated_t_scales(log_t_scales: torch.Tensor) -> torch.Tensor:
    return torch.exp(log_t_scales)


def _log(x):
    """log of a tensor, a numpy array or a number, in its own precision."""
    if isinstance(x, torch.Tensor):
        return torch.log(x)
    return np.log(x) if isinstance(x, np.ndarray) else math.log(x)


def stored_scales(scales):
    """log_scales of `scales` (tensor, numpy array or number)."""
    return _log(scales)


def stored_opacities(opacities):
    """opacity_logits of base opacities in (0, 1) (tensor, numpy array or number)."""
    return _log(opacities / (1 - opacities))


def stored_t_scales(t_scales):
    """log_t_scales of temporal sigmas (tensor, numpy array or number)."""
    return _log(t_scales)


def _sh_coefficients(sh_dc: torch.Tensor, sh_rest: torch.Tensor, degree: int) -> torch.Tensor:
    """SH coefficients [N,(d+1)^2,3] of degree `degree` from the stored blocks sh_dc [N,1,3] and sh_rest [N,K-1,3]."""
    if degree == 0:
        return sh_dc  # no copy: most video scenes never leave degree 0
    return torch.cat([sh_dc, sh_rest[:, : (degree + 1) ** 2 - 1]], dim=1)


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    """DC coefficient [N,1,3] whose colour (C0 * dc + 0.5) is `rgb` [N,3]."""
    return ((rgb - 0.5) / SH_C0)[:, None, :]


class GaussianModel(torch.nn.Module):
    """N Gaussians with temporal opacity; `sh_degree` is the active degree (0 .. max_sh_degree)."""

    def __init__(self, means, quats, log_scales, opacity_logits, sh_dc, sh_rest, t_means, log_t_scales,
                 sh_degree: int = 0):
        super().__init__()
        n = means.shape[0]
        shapes = dict(means=(n, 3), quats=(n, 4), log_scales=(n, 3), opacity_logits=(n,), sh_dc=(n, 1, 3),
                      t_means=(n,), log_t_scales=(n,))
        values = dict(means=means, quats=quats, log_scales=log_scales, opacity_logits=opacity_logits, sh_dc=sh_dc,
                      sh_rest=sh_rest, t_means=t_means, log_t_scales=log_t_scales)
        for name, shape in shapes.items():
            if tuple(values[name].shape) != shape:
                raise ValueError(f"{name} must have shape {shape}, got {tuple(values[name].shape)}")
        if sh_rest.dim() != 3 or sh_rest.shape[0] != n or sh_rest.shape[2] != 3:
            raise ValueError(f"sh_rest must have shape (N, K-1, 3), got {tuple(sh_rest.shape)}")
        self.max_sh_degree = sh_degree_of(sh_rest.shape[1] + 1)
        if not 0 <= sh_degree <= self.max_sh_degree:
            raise ValueError(f"sh_degree must be in 0..{self.max_sh_degree}, got {sh_degree}")
        self.sh_degree = sh_degree
        for name, value in values.items():
            setattr(self, name, torch.nn.Parameter(value.detach().float().contiguous()))

    # -- construction -------------------------------------------------------------------------

    @classmethod
    def from_points(cls, points: torch.Tensor, colors: torch.Tensor, t_means: torch.Tensor,
                    t_scale: float | torch.Tensor, max_sh_degree: int = 3, opacity: float = 0.1,
                    sizes: torch.Tensor | None = None) -> "GaussianModel":
        """Isotropic Gaussians at `points` [P,3] with RGB `colors` [P,3] in [0,1], temporal centres
        `t_means` [P] and temporal sigmas `t_scale` (one for all, or [P]); size `sizes` [P], or by
        default the distance to the 3 nearest neighbours (as 3DGS; quadratic in P, so pass sizes for
        large clouds)."""
        points = points.float()
        n = points.shape[0]
        dist = (nearest_neighbour_distance(points, k=3) if sizes is None else sizes.float()).clamp_min(1e-7)
        rest = (max_sh_degree + 1) ** 2 - 1
        if isinstance(t_scale, torch.Tensor):
            log_t_scales = stored_t_scales(t_scale.float()).to(points.device).expand(n).contiguous()
        else:
            log_t_scales = torch.full((n,), stored_t_scales(t_scale), device=points.device)
        return cls(
            means=points,
            quats=torch.tensor([1.0, 0.0, 0.0, 0.0], device=points.device).repeat(n, 1),
            log_scales=stored_scales(dist)[:, None].repeat(1, 3),
            opacity_logits=torch.full((n,), stored_opacities(opacity), device=points.device),
            sh_dc=rgb_to_sh_dc(colors.float().clamp(0, 1)),
            sh_rest=torch.zeros(n, rest, 3, device=points.device),
            t_means=t_means.float(),
            log_t_scales=log_t_scales,
        )

    # -- activations ---------------------------------------------------------------------------

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def scales(self) -> torch.Tensor:
        return activated_scales(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        return activated_opacities(self.opacity_logits)

    @property
    def t_scales(self) -> torch.Tensor:
        return activated_t_scales(self.log_t_scales)

    # -- temporal opacity (tomgs.temporal, float32 as the renderer) ---------------------------------

    def opacity_at(self, t) -> torch.Tensor:
        """o_i(t) [N] at clip time t."""
        return temporal.opacity_at(self.opacities, self.t_means, self.t_scales, t)

    def alive_at(self, t, alpha_min: float = ALPHA_MIN) -> torch.Tensor:
        """bool [N]: o_i(t) >= alpha_min, the Gaussians the renderer draws at t."""
        return temporal.alive_at(self.opacities, self.t_means, self.t_scales, t, alpha_min)

    def peak_opacity(self, t0: float, t1: float) -> torch.Tensor:
        """[N]: the largest o_i(t) for t in [t0, t1]."""
        return temporal.peak_opacity(self.opacities, self.t_means, self.t_scales, t0, t1)

    def sh(self, degree: int | None = None) -> torch.Tensor:
        """SH coefficients [N,(d+1)^2,3] of the active degree (or `degree`)."""
        return _sh_coefficients(self.sh_dc, self.sh_rest, self.sh_degree if degree is None else degree)

    def render_inputs(self) -> dict[str, torch.Tensor]:
        """Keyword arguments of `tomgs.rasterize` for these Gaussians (camera and time excluded); a
        frame of some of them passes their indices as `rows` (tomgs.render.alive), which the kernels read
        in place, so nothing is gathered and autograd needs no scatter."""
        return self.render_inputs_of(self.parameters_by_name())

    def render_inputs_of(self, params: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """`render_inputs` of other stored tensors in this model's layout (`params` by PARAM_NAMES, any
        number of rows), at its active SH degree: a captured training step activates its own copy of
        the parameters (tomgs.train.captured_step)."""
        colors = _sh_coefficients(params["sh_dc"], params["sh_rest"], self.sh_degree)
        return dict(means=params["means"], quats=params["quats"], scales=activated_scales(params["log_scales"]),
                    opacities=activated_opacities(params["opacity_logits"]), colors=colors,
                    t_means=params["t_means"], t_scales=activated_t_scales(params["log_t_scales"]))  # RENDER_INPUTS

    def parameters_by_name(self) -> dict[str, torch.nn.Parameter]:
        return {name: getattr(self, name) for name in PARAM_NAMES}

    def replace(self, tensors: dict[str, torch.Tensor]) -> None:
        """Swap in new per-Gaussian tensors (after densify/prune); the optimiser must be told too."""
        for name in PARAM_NAMES:
            setattr(self, name, torch.nn.Parameter(tensors[name].detach().contiguous()))


def nearest_neighbour_distance(points: torch.Tensor, k: int = 3, chunk: int = 4096) -> torch.Tensor:
    """Root mean squared distance [P] from each point to its k nearest others (brute force, chunked)."""
    n = points.shape[0]
    if n <= 1:
        return torch.ones(n, device=points.device)
    k = min(k, n - 1)
    out = torch.empty(n, device=points.device)
    for start in range(0, n, chunk):
        d2 = torch.cdist(points[start:start + chunk], points).square()
        d2[torch.arange(d2.shape[0]), torch.arange(start, start + d2.shape[0])] = float("inf")
        out[start:start + chunk] = d2.topk(k, dim=1, largest=False).values.mean(1).sqrt()
    return out


PLANE_NORMAL_SCALE = 1e-8  # MiraGe's flat Gaussians: their scale along the plane's normal


def on_plane(means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor):
    """Pin Gaussians to the plane z = 0: means [N,3] get z = 0, quats [N,4] keep only a rotation about
    z (w and z; one in-plane angle theta = 2 atan2(q_z, q_w), stored as a pair so it never wraps), and
    log_scales [N,3] get log(1e-8) along local z, the plane's normal. Differentiable: the pinned
    components get zero gradient."""
    keep = means.new_tensor([1.0, 1.0, 0.0])
    return (means * keep, quats * quats.new_tensor([1.0, 0.0, 0.0, 1.0]),
            log_scales * keep + log_scales.new_tensor([0.0, 0.0, stored_scales(PLANE_NORMAL_SCALE)]))


class PlanarGaussianModel(GaussianModel):
    """A MiraGe-style foreground: flat Gaussians on the plane z = 0 (`on_plane`), so each one has a
    2D position, two in-plane scales and one in-plane angle, plus the usual opacity, colour and
    temporal window. Same stored names and shapes as GaussianModel, so the trainer, the densifier,
    checkpoints and scene files take it unchanged: the activations ignore the pinned components
    (zero gradients, so Adam leaves them alone) and `replace` puts rows that densification added or
    moved back on the plane. Saved, it is an ordinary scene of flat 3D Gaussians."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.replace(self.parameters_by_name())

    @property
    def scales(self) -> torch.Tensor:
        return activated_scales(on_plane(self.means, self.quats, self.log_scales)[2])

    def render_inputs_of(self, params: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        means, quats, log_scales = on_plane(params["means"], params["quats"], params["log_scales"])
        return super().render_inputs_of(dict(params, means=means, quats=quats, log_scales=log_scales))

    def replace(self, tensors: dict[str, torch.Tensor]) -> None:
        means, quats, log_scales = on_plane(tensors["means"], tensors["quats"], tensors["log_scales"])
        super().replace(dict(tensors, means=means, quats=quats, log_scales=log_scales))
