"""Spherical-harmonics colour, degree 0..3 (the 3DGS basis and constants).

Evaluated in torch: it is a handful of fused elementwise ops per Gaussian, autograd differentiates
it, and the renderer, the reference and the model all share this one definition.
"""

from __future__ import annotations

import math

import torch

_C0 = 0.28209479177387814
_C1 = 0.4886025119029199
_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_degree_of(num_coeffs: int) -> int:
    """Degree d of an SH block with (d + 1)^2 coefficients; raises for other counts."""
    degree = int(round(math.sqrt(num_coeffs))) - 1
    if degree < 0 or degree > 3 or (degree + 1) ** 2 != num_coeffs:
        raise ValueError(f"SH coefficients per channel must be 1, 4, 9 or 16, got {num_coeffs}")
    return degree


def eval_sh(sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Raw SH value (no +0.5 offset) of `sh` [N,K,3] along unit directions `dirs` [N,3] -> [N,3]."""
    degree = sh_degree_of(sh.shape[-2])
    out = _C0 * sh[:, 0]
    if degree == 0:
        return out
    x, y, z = dirs[:, 0:1], dirs[:, 1:2], dirs[:, 2:3]
    out = out - _C1 * y * sh[:, 1] + _C1 * z * sh[:, 2] - _C1 * x * sh[:, 3]
    if degree == 1:
        return out
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    out = (
        out
        + _C2[0] * xy * sh[:, 4]
        + _C2[1] * yz * sh[:, 5]
        + _C2[2] * (2.0 * zz - xx - yy) * sh[:, 6]
        + _C2[3] * xz * sh[:, 7]
        + _C2[4] * (xx - yy) * sh[:, 8]
    )
    if degree == 2:
        return out
    return (
        out
        + _C3[0] * y * (3.0 * xx - yy) * sh[:, 9]
        + _C3[1] * xy * z * sh[:, 10]
        + _C3[2] * y * (4.0 * zz - xx - yy) * sh[:, 11]
        + _C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh[:, 12]
        + _C3[4] * x * (4.0 * zz - xx - yy) * sh[:, 13]
        + _C3[5] * z * (xx - yy) * sh[:, 14]
        + _C3[6] * x * (xx - 3.0 * yy) * sh[:, 15]
    )


def sh_to_colors(sh: torch.Tensor, means: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
    """RGB [N,3] seen from the camera of `viewmat` [4,4] (world->camera) for SH `sh` [N,K,3].

    Follows 3DGS: value + 0.5, clamped at 0 from below. Degree 0 needs no view direction.
    """
    if sh.shape[-2] == 1:
        return torch.clamp_min(_C0 * sh[:, 0] + 0.5, 0.0)
    rot, trans = viewmat[:3, :3], viewmat[:3, 3]
    cam_center = -rot.T @ trans
    dirs = torch.nn.functional.normalize(means - cam_center, dim=-1)
    return torch.clamp_min(eval_sh(sh, dirs) + 0.5, 0.0)
