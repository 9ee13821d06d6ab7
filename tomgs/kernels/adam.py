"""Adam on the rows of one parameter that a step saw: the Gaussians in view at the frame's time.

At a frame of a TOM-GS clip most Gaussians are dead or out of view (15% alive, 12% in view on
DAVIS camel after a fit), so their gradient is exactly zero. Dense Adam still rewrites every row and
keeps moving those Gaussians on stale momentum; here a row that was not seen keeps its value and
its moments (the sparse Adam of Taming 3DGS, Mallick et al. 2024). One thread per element of the
parameter viewed as [N, D]; the update is torch.optim.Adam's, with the bias corrections of the
optimiser's step count.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def adam_seen_rows(
    param: wp.array2d(dtype=float),  # [N, D] updated in place
    grad: wp.array2d(dtype=float),  # [N, D]
    exp_avg: wp.array2d(dtype=float),  # [N, D] first moment, in place
    exp_avg_sq: wp.array2d(dtype=float),  # [N, D] second moment, in place
    seen: wp.array(dtype=wp.uint8),  # [N] 1 where the row's Gaussian was in view
    lr: float,
    beta1: float,
    beta2: float,
    eps: float,
    bias1: float,  # 1 - beta1^step
    bias2_sqrt: float,  # sqrt(1 - beta2^step)
):
    i = wp.tid()
    d = param.shape[1]
    row = i // d
    if seen[row] == wp.uint8(0):
        return
    col = i - row * d
    g = grad[row, col]
    m = beta1 * exp_avg[row, col] + (1.0 - beta1) * g
    v = beta2 * exp_avg_sq[row, col] + (1.0 - beta2) * g * g
    exp_avg[row, col] = m
    exp_avg_sq[row, col] = v
    param[row, col] = param[row, col] - (lr / bias1) * m / (wp.sqrt(v) / bias2_sqrt + eps)
