"""Spherical-harmonics colour, degree 0..3 (the 3DGS basis and constants).

    eval_sh(sh, dirs)                    the basis, in torch: the one definition, and the oracle
    sh_to_colors(sh, means, viewmat)     RGB seen from a camera, in torch (any dtype; the reference)
    fused_sh_to_colors(sh, means, viewmat)
                                         the same in one Warp kernel forward and one backward, float32
                                         (the renderer: ~40 torch kernels per direction become one)

The basis's constants live in tomgs.constants, where tomgs.kernels.sh reads them too.
"""

from __future__ import annotations

import torch

from tomgs.constants import SH_C0, SH_C1, SH_C2, SH_C3, SH_DIR_EPS, sh_degree_of


def eval_sh(sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Raw SH value (no +0.5 offset) of `sh` [N,K,3] along unit directions `dirs` [N,3] -> [N,3]."""
    degree = sh_degree_of(sh.shape[-2])
    out = SH_C0 * sh[:, 0]
    if degree == 0:
        return out
    x, y, z = dirs[:, 0:1], dirs[:, 1:2], dirs[:, 2:3]
    out = out - SH_C1 * y * sh[:, 1] + SH_C1 * z * sh[:, 2] - SH_C1 * x * sh[:, 3]
    if degree == 1:
        return out
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    out = (
        out
        + SH_C2[0] * xy * sh[:, 4]
        + SH_C2[1] * yz * sh[:, 5]
        + SH_C2[2] * (2.0 * zz - xx - yy) * sh[:, 6]
        + SH_C2[3] * xz * sh[:, 7]
        + SH_C2[4] * (xx - yy) * sh[:, 8]
    )
    if degree == 2:
        return out
    return (
        out
        + SH_C3[0] * y * (3.0 * xx - yy) * sh[:, 9]
        + SH_C3[1] * xy * z * sh[:, 10]
        + SH_C3[2] * y * (4.0 * zz - xx - yy) * sh[:, 11]
        + SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh[:, 12]
        + SH_C3[4] * x * (4.0 * zz - xx - yy) * sh[:, 13]
        + SH_C3[5] * z * (xx - yy) * sh[:, 14]
        + SH_C3[6] * x * (xx - 3.0 * yy) * sh[:, 15]
    )


def sh_to_colors(sh: torch.Tensor, means: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
    """RGB [N,3] seen from the camera of `viewmat` [4,4] (world->camera) for SH `sh` [N,K,3].

    Follows 3DGS: value + 0.5, clamped at 0 from below. Degree 0 needs no view direction. A mean
    component that is not finite counts as 0 (and gets no gradient): such a Gaussian is culled by
    the renderer anyway, and its NaN view direction would reach every gradient of means and viewmat
    through the backward (0 * NaN). A Gaussian at the camera centre sees direction 0 (SH_DIR_EPS).
    """
    if sh.shape[-2] == 1:
        return torch.clamp_min(SH_C0 * sh[:, 0] + 0.5, 0.0)
    means = torch.where(torch.isfinite(means), means, torch.zeros_like(means))
    rot, trans = viewmat[:3, :3], viewmat[:3, 3]
    cam_center = -rot.T @ trans
    dirs = torch.nn.functional.normalize(means - cam_center, dim=-1, eps=SH_DIR_EPS)
    return torch.clamp_min(eval_sh(sh, dirs) + 0.5, 0.0)


def fused_sh_to_colors(sh: torch.Tensor, means: torch.Tensor, viewmat: torch.Tensor,
                       rows: torch.Tensor | None = None) -> torch.Tensor:
    """`sh_to_colors` in float32 by the Warp kernels of tomgs.kernels.sh, on the inputs' device (CPU
    or CUDA): RGB [N,3] float32 for SH `sh` [N,K,3], `means` [N,3], `viewmat` [4,4] of any float dtype;
    with `rows` (int32 [M] on that device) RGB [M,3] of those Gaussians only (a row
    outside [0, N) gets black; the renderer refuses it). Differentiable in sh, means and viewmat (the
    viewmat's gradient is formed only when it is asked for)."""
    if sh.dim() != 3 or sh.shape[2] != 3 or means.shape != (sh.shape[0], 3) or viewmat.shape != (4, 4):
        raise ValueError(f"need sh [N,K,3], means [N,3], viewmat [4,4]; got {tuple(sh.shape)}, "
                         f"{tuple(means.shape)}, {tuple(viewmat.shape)}")
    sh_degree_of(sh.shape[1])
    return _FusedColors.apply(*(x.to(torch.float32).contiguous() for x in (sh, means, viewmat)), rows)


class _FusedColors(torch.autograd.Function):
    # sh [N,K,3], means [N,3], viewmat [4,4]: float32, contiguous; rows None or int32 [M] contiguous
    @staticmethod
    def forward(ctx, sh, means, viewmat, rows):
        import warp as wp  # here, not at the top: importing tomgs.render.sh loads no Warp

        from tomgs.kernels import sh as kernels
        from tomgs.runtime import NO_ARRAY, launch, scope, wrap

        degree = sh_degree_of(sh.shape[1])
        m = sh.shape[0] if rows is None else rows.shape[0]
        colors = torch.empty(m, 3, device=sh.device, dtype=torch.float32)
        with scope(sh.device) as device:
            launch(kernels.sh_colors_forward, m, device=device, args=[
                wrap(sh, wp.vec3), wrap(means, wp.vec3), wrap(viewmat.reshape(1, 4, 4), wp.mat44), degree,
                wrap(colors, wp.vec3), NO_ARRAY if rows is None else wrap(rows), int(rows is not None)])
        ctx.rows = rows
        ctx.save_for_backward(sh, means, viewmat)
        return colors

    @staticmethod
    def backward(ctx, v_colors):
        import warp as wp

        from tomgs.kernels import sh as kernels
        from tomgs.runtime import NO_ARRAY, indexable, launch, scope, wrap

        sh, means, viewmat = ctx.saved_tensors
        rows = ctx.rows
        degree = sh_degree_of(sh.shape[1])
        m = sh.shape[0] if rows is None else rows.shape[0]
        camera_grads = degree > 0 and ctx.needs_input_grad[2]
        # with rows only theirs are written: the rest stays zero
        fresh = torch.empty_like if rows is None else torch.zeros_like
        v_sh = fresh(sh)
        v_means = fresh(means) if degree > 0 else None
        v_offsets = means.new_empty(m, 3) if camera_grads else None
        v_colors = indexable(v_colors, sh[:, 0], m, 3)  # named: a descriptor does not keep its tensor alive
        with scope(sh.device) as device:
            launch(kernels.sh_colors_backward, m, device=device, args=[
                wrap(sh, wp.vec3), wrap(means, wp.vec3), wrap(viewmat.reshape(1, 4, 4), wp.mat44), degree,
                wrap(v_colors, wp.vec3), int(camera_grads), wrap(v_sh, wp.vec3),
                wrap(means if v_means is None else v_means, wp.vec3),  # unwritten stand-ins
                wrap(means if v_offsets is None else v_offsets, wp.vec3),
                NO_ARRAY if rows is None else wrap(rows), int(rows is not None)])
        v_viewmat = None
        if camera_grads:
            # centre c = -R^T t and every offset is mean - c: with s = sum of dL/d(offset) [3],
            # dL/dR = t s^T and dL/dt = R s
            s = v_offsets.sum(0, dtype=torch.float64).to(viewmat.dtype)
            v_viewmat = torch.zeros_like(viewmat)
            v_viewmat[:3, :3] = torch.outer(viewmat[:3, 3], s)
            v_viewmat[:3, 3] = viewmat[:3, :3] @ s
        return v_sh, v_means, v_viewmat, None
