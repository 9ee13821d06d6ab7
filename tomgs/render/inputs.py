"""The contract of `rasterize`: validated, normalised inputs shared by the renderer and the reference."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from tomgs.constants import sh_degree_of
from tomgs.errors import RenderError
from tomgs.render.sh import fused_sh_to_colors, sh_to_colors


@dataclass
class RasterInputs:
    means: torch.Tensor  # [N,3]
    quats: torch.Tensor  # [N,4] w x y z, any norm
    scales: torch.Tensor  # [N,3] > 0
    opacities: torch.Tensor  # [N] base opacity in (0, 1)
    colors: torch.Tensor  # [N,3] RGB after SH evaluation; [M,3] of `rows` when given
    t_means: torch.Tensor  # [N]
    t_scales: torch.Tensor  # [N] sigma > 0
    viewmat: torch.Tensor  # [4,4] world -> camera, OpenCV axes
    K: torch.Tensor  # [3,3] pixels
    background: torch.Tensor | None  # [3]
    width: int
    height: int
    t: float
    near: float
    far: float
    rows: torch.Tensor | None = None  # int32 [M]: the Gaussians rendered (None: all N)


def check_rows(rows, device: torch.device) -> torch.Tensor | None:
    """`rows` as int32 [M] contiguous on `device`, or None; RenderError for what is not an integer
    index vector there (values are checked in projection, with the other per-Gaussian checks)."""
    if rows is None:
        return None
    if not isinstance(rows, torch.Tensor) or rows.dim() != 1 or rows.is_floating_point() or rows.is_complex() \
            or rows.dtype == torch.bool:
        raise RenderError(f"rows must be an integer tensor of shape (M,), got "
                          f"{rows.dtype if isinstance(rows, torch.Tensor) else type(rows).__name__} "
                          f"{tuple(rows.shape) if isinstance(rows, torch.Tensor) else ''}".rstrip())
    if rows.device != device:
        raise RenderError(f"rows must be on the Gaussians' device {device}, got {rows.device}")
    return (rows if rows.dtype == torch.int32 else rows.to(torch.int32)).contiguous()


def _shape_error(name: str, tensor: torch.Tensor, expected: str) -> RenderError:
    return RenderError(f"{name} must have shape {expected}, got {tuple(tensor.shape)}")


def prepare_inputs(
    means, quats, scales, opacities, colors, t_means, t_scales, viewmat, K, width, height, t,
    background, near, far, dtype: torch.dtype | None, *, fused_sh: bool = False, rows=None,
) -> RasterInputs:
    """Check shapes, devices and scalars; evaluate SH into RGB; cast to `dtype` (None keeps means').

    SH is evaluated by tomgs.render.sh.sh_to_colors in the inputs' dtype (the reference: the torch oracle),
    or with `fused_sh` by its Warp kernel in float32 (the renderer), which alone takes `rows` (the
    Gaussians rendered: colours are then [M,3])."""
    tensors = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
                   t_means=t_means, t_scales=t_scales, viewmat=viewmat, K=K)
    for name, value in tensors.items():
        if not isinstance(value, torch.Tensor):
            raise RenderError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    n = means.shape[0] if means.dim() == 2 else -1
    expected = dict(means=(n, 3), quats=(n, 4), scales=(n, 3), opacities=(n,), t_means=(n,),
                    t_scales=(n,), viewmat=(4, 4), K=(3, 3))
    for name, shape in expected.items():
        if tuple(tensors[name].shape) != shape:
            raise _shape_error(name, tensors[name], str(tuple("N" if s == n else s for s in shape)))
    if not ((colors.dim() == 2 and colors.shape == (n, 3)) or (colors.dim() == 3 and colors.shape[0] == n
                                                                  and colors.shape[2] == 3)):
        raise _shape_error("colors", colors, "(N, 3) for RGB or (N, K, 3) for SH")
    devices = {v.device for v in tensors.values()}
    if background is not None:
        if not isinstance(background, torch.Tensor) or tuple(background.shape) != (3,):
            raise RenderError("background must be a tensor of shape (3,) or None")
        devices.add(background.device)
    if len(devices) != 1:
        raise RenderError(f"all tensors must be on one device, got {sorted(map(str, devices))}")
    for name, value in tensors.items():
        if not value.is_floating_point():
            raise RenderError(f"{name} must be a floating-point tensor, got {value.dtype}")
    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise RenderError(f"width and height must be positive integers, got {width}x{height}")
    if not (0.0 < near < far):
        raise RenderError(f"need 0 < near < far, got near={near}, far={far}")
    rows = check_rows(rows, means.device)
    if rows is not None and not fused_sh:
        raise RenderError("rows are rendered by the Warp renderer only")
    if colors.dim() == 3:
        sh_degree_of(colors.shape[1])  # raises on a bad coefficient count
        # both count a non-finite mean component as 0 (that Gaussian is culled; its NaN view direction
        # would reach every gradient of means and viewmat through the SH backward)
        colors = fused_sh_to_colors(colors, means, viewmat, rows) if fused_sh else sh_to_colors(colors, means, viewmat)
    elif rows is not None:  # clamped: a row outside [0, N) is refused by projection, never read
        colors = colors.index_select(0, rows.clamp(0, n - 1)) if n > 0 else colors.new_zeros(len(rows), 3)
    dtype = dtype or means.dtype
    # no .to() call where the dtype already matches: each is a dispatched op (host time on a GPU machine)
    cast = {k: v if v.dtype == dtype else v.to(dtype) for k, v in dict(tensors, colors=colors).items()}
    return RasterInputs(
        **cast,
        background=background if background is None or background.dtype == dtype else background.to(dtype),
        width=int(width), height=int(height), t=float(t), near=float(near), far=float(far), rows=rows,
    )
