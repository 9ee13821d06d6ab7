"""Adam on the rows of the parameters that a step saw: the Gaussians in view at the frame's time.

At a frame of a TOM-GS clip most Gaussians are dead or out of view (15% alive, 12% in view on
DAVIS camel after a fit), so their gradient is exactly zero. Dense Adam still rewrites every row and
keeps moving those Gaussians on stale momentum; here a row that was not seen keeps its value and
its moments (the sparse Adam of Taming 3DGS, Mallick et al. 2024). The update is torch.optim.Adam's,
with the bias corrections of each parameter's step count.

One launch updates up to SLOTS parameters (a training step's eight: means, quats, scales, opacity,
two SH blocks, temporal mean and scale): one thread per element of their concatenation, each
parameter viewed as [N, D]. A launch per parameter cost the GPU machine's host more than the
update itself (eight launches and ~40 torch calls per step).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

SLOTS = 8
vec_slots = wp.types.vector(length=SLOTS, dtype=float)
vec_slots_i = wp.types.vector(length=SLOTS, dtype=wp.int32)


@wp.func
def adam_element(
    param: wp.array2d(dtype=float),  # [N, D] updated in place
    grad: wp.array2d(dtype=float),  # [N, D]
    exp_avg: wp.array2d(dtype=float),  # [N, D] first moment, in place
    exp_avg_sq: wp.array2d(dtype=float),  # [N, D] second moment, in place
    seen: wp.array(dtype=wp.bool),  # [N] True where the row's Gaussian was in view
    element: int,  # index into the parameter's N x D elements
    lr: float,
    beta1: float,
    beta2: float,
    eps: float,
    bias1: float,  # 1 - beta1^step
    bias2_sqrt: float,  # sqrt(1 - beta2^step)
):
    d = param.shape[1]
    row = element // d
    if seen[row]:
        col = element - row * d
        g = grad[row, col]
        m = beta1 * exp_avg[row, col] + (1.0 - beta1) * g
        v = beta2 * exp_avg_sq[row, col] + (1.0 - beta2) * g * g
        exp_avg[row, col] = m
        exp_avg_sq[row, col] = v
        param[row, col] = param[row, col] - (lr / bias1) * m / (wp.sqrt(v) / bias2_sqrt + eps)


@wp.kernel
def adam_seen_rows(
    p0: wp.array2d(dtype=float), g0: wp.array2d(dtype=float), m0: wp.array2d(dtype=float), v0: wp.array2d(dtype=float),
    p1: wp.array2d(dtype=float), g1: wp.array2d(dtype=float), m1: wp.array2d(dtype=float), v1: wp.array2d(dtype=float),
    p2: wp.array2d(dtype=float), g2: wp.array2d(dtype=float), m2: wp.array2d(dtype=float), v2: wp.array2d(dtype=float),
    p3: wp.array2d(dtype=float), g3: wp.array2d(dtype=float), m3: wp.array2d(dtype=float), v3: wp.array2d(dtype=float),
    p4: wp.array2d(dtype=float), g4: wp.array2d(dtype=float), m4: wp.array2d(dtype=float), v4: wp.array2d(dtype=float),
    p5: wp.array2d(dtype=float), g5: wp.array2d(dtype=float), m5: wp.array2d(dtype=float), v5: wp.array2d(dtype=float),
    p6: wp.array2d(dtype=float), g6: wp.array2d(dtype=float), m6: wp.array2d(dtype=float), v6: wp.array2d(dtype=float),
    p7: wp.array2d(dtype=float), g7: wp.array2d(dtype=float), m7: wp.array2d(dtype=float), v7: wp.array2d(dtype=float),
    seen: wp.array(dtype=wp.bool),  # [N]
    ends: vec_slots_i,  # cumulative element counts of the slots (an unused slot ends where the last did)
    lr: vec_slots,
    bias1: vec_slots,
    bias2_sqrt: vec_slots,
    beta1: float,
    beta2: float,
    eps: float,
):
    e = wp.tid()
    # parameter (slot) of element e, and e's index inside it
    if e < ends[0]:
        adam_element(p0, g0, m0, v0, seen, e, lr[0], beta1, beta2, eps, bias1[0], bias2_sqrt[0])
    elif e < ends[1]:
        adam_element(p1, g1, m1, v1, seen, e - ends[0], lr[1], beta1, beta2, eps, bias1[1], bias2_sqrt[1])
    elif e < ends[2]:
        adam_element(p2, g2, m2, v2, seen, e - ends[1], lr[2], beta1, beta2, eps, bias1[2], bias2_sqrt[2])
    elif e < ends[3]:
        adam_element(p3, g3, m3, v3, seen, e - ends[2], lr[3], beta1, beta2, eps, bias1[3], bias2_sqrt[3])
    elif e < ends[4]:
        adam_element(p4, g4, m4, v4, seen, e - ends[3], lr[4], beta1, beta2, eps, bias1[4], bias2_sqrt[4])
    elif e < ends[5]:
        adam_element(p5, g5, m5, v5, seen, e - ends[4], lr[5], beta1, beta2, eps, bias1[5], bias2_sqrt[5])
    elif e < ends[6]:
        adam_element(p6, g6, m6, v6, seen, e - ends[5], lr[6], beta1, beta2, eps, bias1[6], bias2_sqrt[6])
    elif e < ends[7]:
        adam_element(p7, g7, m7, v7, seen, e - ends[6], lr[7], beta1, beta2, eps, bias1[7], bias2_sqrt[7])
