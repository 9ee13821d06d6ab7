"""Adam on the rows of the parameters that a step saw: the Gaussians in view at the frame's time.

At a frame of a TOM-GS clip most Gaussians are dead or out of view (15% alive, 12% in view on
DAVIS camel after a fit), so their gradient is exactly zero. Dense Adam still rewrites every row and
keeps moving those Gaussians on stale momentum; here a row that was not seen keeps its value and
its moments (the sparse Adam of Taming 3DGS, Mallick et al. 2024). The update is torch.optim.Adam's,
with the bias corrections of each parameter's step count.

One launch updates up to SLOTS parameters (a training step's eight: means, quats, scales, opacity,
two SH blocks, temporal mean and scale), each viewed as [N, D]: one thread per row, which returns at
once where the row was not seen and else updates the row's elements of every parameter. A launch
per parameter cost the GPU machine's host more than the update itself (eight launches and ~40 torch
calls per step); a thread per element of all of them (~16 N threads) took twice the GPU time on a
fitted scene (docs/notes/training.md). `adam_seen_rows_read` is the same update with
its learning rates and bias corrections read from device memory: a training step replayed from a CUDA
graph (tomgs.train.captured_step), whose kernels keep the scalars they were captured with.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

SLOTS = 8
vec_slots = wp.types.vector(length=SLOTS, dtype=float)


@wp.func
def adam_row(
    param: wp.array2d(dtype=float),  # [N, D] updated in place (an unused slot: [0, 1])
    grad: wp.array2d(dtype=float),  # [N, D]
    exp_avg: wp.array2d(dtype=float),  # [N, D] first moment, in place
    exp_avg_sq: wp.array2d(dtype=float),  # [N, D] second moment, in place
    row: int,
    lr: float,
    beta1: float,
    beta2: float,
    eps: float,
    bias1: float,  # 1 - beta1^step
    bias2_sqrt: float,  # sqrt(1 - beta2^step)
):
    if row < param.shape[0]:
        step = lr / bias1
        for col in range(param.shape[1]):
            g = grad[row, col]
            m = beta1 * exp_avg[row, col] + (1.0 - beta1) * g
            v = beta2 * exp_avg_sq[row, col] + (1.0 - beta2) * g * g
            exp_avg[row, col] = m
            exp_avg_sq[row, col] = v
            param[row, col] = param[row, col] - step * m / (wp.sqrt(v) / bias2_sqrt + eps)


@wp.func
def adam_slots(
    p0: wp.array2d(dtype=float), g0: wp.array2d(dtype=float), m0: wp.array2d(dtype=float), v0: wp.array2d(dtype=float),
    p1: wp.array2d(dtype=float), g1: wp.array2d(dtype=float), m1: wp.array2d(dtype=float), v1: wp.array2d(dtype=float),
    p2: wp.array2d(dtype=float), g2: wp.array2d(dtype=float), m2: wp.array2d(dtype=float), v2: wp.array2d(dtype=float),
    p3: wp.array2d(dtype=float), g3: wp.array2d(dtype=float), m3: wp.array2d(dtype=float), v3: wp.array2d(dtype=float),
    p4: wp.array2d(dtype=float), g4: wp.array2d(dtype=float), m4: wp.array2d(dtype=float), v4: wp.array2d(dtype=float),
    p5: wp.array2d(dtype=float), g5: wp.array2d(dtype=float), m5: wp.array2d(dtype=float), v5: wp.array2d(dtype=float),
    p6: wp.array2d(dtype=float), g6: wp.array2d(dtype=float), m6: wp.array2d(dtype=float), v6: wp.array2d(dtype=float),
    p7: wp.array2d(dtype=float), g7: wp.array2d(dtype=float), m7: wp.array2d(dtype=float), v7: wp.array2d(dtype=float),
    row: int,
    lr: vec_slots,
    bias1: vec_slots,
    bias2_sqrt: vec_slots,
    beta1: float,
    beta2: float,
    eps: float,
):
    # row `row` of every slot's parameter, each with its own learning rate and bias corrections
    adam_row(p0, g0, m0, v0, row, lr[0], beta1, beta2, eps, bias1[0], bias2_sqrt[0])
    adam_row(p1, g1, m1, v1, row, lr[1], beta1, beta2, eps, bias1[1], bias2_sqrt[1])
    adam_row(p2, g2, m2, v2, row, lr[2], beta1, beta2, eps, bias1[2], bias2_sqrt[2])
    adam_row(p3, g3, m3, v3, row, lr[3], beta1, beta2, eps, bias1[3], bias2_sqrt[3])
    adam_row(p4, g4, m4, v4, row, lr[4], beta1, beta2, eps, bias1[4], bias2_sqrt[4])
    adam_row(p5, g5, m5, v5, row, lr[5], beta1, beta2, eps, bias1[5], bias2_sqrt[5])
    adam_row(p6, g6, m6, v6, row, lr[6], beta1, beta2, eps, bias1[6], bias2_sqrt[6])
    adam_row(p7, g7, m7, v7, row, lr[7], beta1, beta2, eps, bias1[7], bias2_sqrt[7])


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
    lr: vec_slots,
    bias1: vec_slots,
    bias2_sqrt: vec_slots,
    beta1: float,
    beta2: float,
    eps: float,
):
    row = wp.tid()
    if not seen[row]:
        return
    adam_slots(p0, g0, m0, v0, p1, g1, m1, v1, p2, g2, m2, v2, p3, g3, m3, v3, p4, g4, m4, v4, p5, g5, m5, v5,
               p6, g6, m6, v6, p7, g7, m7, v7, row, lr, bias1, bias2_sqrt, beta1, beta2, eps)


@wp.kernel
def adam_seen_rows_read(
    p0: wp.array2d(dtype=float), g0: wp.array2d(dtype=float), m0: wp.array2d(dtype=float), v0: wp.array2d(dtype=float),
    p1: wp.array2d(dtype=float), g1: wp.array2d(dtype=float), m1: wp.array2d(dtype=float), v1: wp.array2d(dtype=float),
    p2: wp.array2d(dtype=float), g2: wp.array2d(dtype=float), m2: wp.array2d(dtype=float), v2: wp.array2d(dtype=float),
    p3: wp.array2d(dtype=float), g3: wp.array2d(dtype=float), m3: wp.array2d(dtype=float), v3: wp.array2d(dtype=float),
    p4: wp.array2d(dtype=float), g4: wp.array2d(dtype=float), m4: wp.array2d(dtype=float), v4: wp.array2d(dtype=float),
    p5: wp.array2d(dtype=float), g5: wp.array2d(dtype=float), m5: wp.array2d(dtype=float), v5: wp.array2d(dtype=float),
    p6: wp.array2d(dtype=float), g6: wp.array2d(dtype=float), m6: wp.array2d(dtype=float), v6: wp.array2d(dtype=float),
    p7: wp.array2d(dtype=float), g7: wp.array2d(dtype=float), m7: wp.array2d(dtype=float), v7: wp.array2d(dtype=float),
    seen: wp.array(dtype=wp.bool),  # [N]
    rates: wp.array(dtype=vec_slots),  # [3]: lr, bias1, bias2_sqrt, read where a replayed graph finds this step's
    beta1: float,
    beta2: float,
    eps: float,
):
    # adam_seen_rows with the rates in device memory (a step captured in a CUDA graph cannot change its scalars)
    row = wp.tid()
    if not seen[row]:
        return
    adam_slots(p0, g0, m0, v0, p1, g1, m1, v1, p2, g2, m2, v2, p3, g3, m3, v3, p4, g4, m4, v4, p5, g5, m5, v5,
               p6, g6, m6, v6, p7, g7, m7, v7, row, rates[0], rates[1], rates[2], beta1, beta2, eps)
