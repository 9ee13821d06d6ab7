"""Spherical-harmonics colour in one pass per Gaussian, and its hand-written backward.

    colors = max(eval_sh(sh, normalize(mean - camera centre)) + 0.5, 0)      (tomgs.render.sh.sh_to_colors)

One thread per Gaussian reads its K x 3 coefficients, its mean and the camera once; the torch
formula it replaces runs ~40 elementwise kernels forward and more backward. The basis and the
direction's rules are tomgs.render.sh's (the oracle; the constants are tomgs.constants'): a mean
component that is not finite counts as 0 (and gets no gradient); the direction is (mean - centre) / max(|mean - centre|,
DIR_EPS), as torch's normalize, so a Gaussian at the camera centre sees direction 0 (its colour is
the DC term) and its mean's gradient is the direction's divided by DIR_EPS. The clamp passes the
gradient where value + 0.5 >= 0 and keeps NaN, as torch.clamp_min. float32; degree 0..3.
"""

import warp as wp

from tomgs import constants
from tomgs.kernels.rows import put

wp.set_module_options({"enable_backward": False})

C0 = wp.constant(constants.SH_C0)
C1 = wp.constant(constants.SH_C1)
C2_0 = wp.constant(constants.SH_C2[0])
C2_1 = wp.constant(constants.SH_C2[1])
C2_2 = wp.constant(constants.SH_C2[2])
C2_3 = wp.constant(constants.SH_C2[3])
C2_4 = wp.constant(constants.SH_C2[4])
C3_0 = wp.constant(constants.SH_C3[0])
C3_1 = wp.constant(constants.SH_C3[1])
C3_2 = wp.constant(constants.SH_C3[2])
C3_3 = wp.constant(constants.SH_C3[3])
C3_4 = wp.constant(constants.SH_C3[4])
C3_5 = wp.constant(constants.SH_C3[5])
C3_6 = wp.constant(constants.SH_C3[6])
DIR_EPS = wp.constant(constants.SH_DIR_EPS)


@wp.func
def finite_or_zero(v: wp.vec3) -> wp.vec3:
    # per component, as tomgs.render.sh.sh_to_colors: a culled Gaussian's NaN must not reach the camera's gradient
    out = v
    for j in range(3):
        if not wp.isfinite(v[j]):
            out[j] = 0.0
    return out


@wp.func
def camera_offset(mean: wp.vec3, V: wp.mat44) -> wp.vec3:
    # mean - centre with centre = -R^T t of the world -> camera matrix V = [R t]
    return wp.vec3(
        mean[0] + (V[0, 0] * V[0, 3] + V[1, 0] * V[1, 3] + V[2, 0] * V[2, 3]),
        mean[1] + (V[0, 1] * V[0, 3] + V[1, 1] * V[1, 3] + V[2, 1] * V[2, 3]),
        mean[2] + (V[0, 2] * V[0, 3] + V[1, 2] * V[1, 3] + V[2, 2] * V[2, 3]),
    )


@wp.func
def norm_of(d: wp.vec3) -> float:
    # |d| through d / max|d_j|: the plain squares overflow float32 from |d| ~ 1.8e19 and vanish below ~1e-19
    m = wp.max(wp.max(wp.abs(d[0]), wp.abs(d[1])), wp.abs(d[2]))
    if m > 0.0 and wp.isfinite(m):
        return m * wp.length(d / m)
    return m  # 0, inf or NaN


@wp.func
def sh_raw(sh: wp.array2d(dtype=wp.vec3), i: int, degree: int, d: wp.vec3) -> wp.vec3:
    # eval_sh(sh[i], d): same terms as tomgs.render.sh.eval_sh
    out = C0 * sh[i, 0]
    if degree > 0:
        x = d[0]
        y = d[1]
        z = d[2]
        out += (-C1 * y) * sh[i, 1] + (C1 * z) * sh[i, 2] + (-C1 * x) * sh[i, 3]
        if degree > 1:
            xx = x * x
            yy = y * y
            zz = z * z
            out += ((C2_0 * x * y) * sh[i, 4] + (C2_1 * y * z) * sh[i, 5]
                    + (C2_2 * (2.0 * zz - xx - yy)) * sh[i, 6] + (C2_3 * x * z) * sh[i, 7]
                    + (C2_4 * (xx - yy)) * sh[i, 8])
            if degree > 2:
                out += ((C3_0 * y * (3.0 * xx - yy)) * sh[i, 9] + (C3_1 * x * y * z) * sh[i, 10]
                        + (C3_2 * y * (4.0 * zz - xx - yy)) * sh[i, 11]
                        + (C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)) * sh[i, 12]
                        + (C3_4 * x * (4.0 * zz - xx - yy)) * sh[i, 13] + (C3_5 * z * (xx - yy)) * sh[i, 14]
                        + (C3_6 * x * (xx - 3.0 * yy)) * sh[i, 15])
    return out


@wp.kernel
def sh_colors_forward(
    sh: wp.array2d(dtype=wp.vec3),  # [N, K] coefficients, K = (degree + 1)^2
    means: wp.array(dtype=wp.vec3),  # [N] world; read when degree > 0
    viewmats: wp.array(dtype=wp.mat44),  # [1] world -> camera
    degree: int,  # 0..3
    colors: wp.array(dtype=wp.vec3),  # out [N], or [M] with rows
    rows: wp.array(dtype=wp.int32),  # [M] with has_rows: the Gaussians evaluated (a row outside [0, N)
    has_rows: int,  #                  gets black; projection flags it)
):
    j = wp.tid()
    i = j
    if has_rows != 0:
        i = rows[j]
        if i < 0 or i >= sh.shape[0]:
            colors[j] = wp.vec3(0.0)
            return
    d = wp.vec3(0.0)
    if degree > 0:
        d = camera_offset(finite_or_zero(means[i]), viewmats[0])
        d = d / wp.max(norm_of(d), DIR_EPS)
    c = sh_raw(sh, i, degree, d) + wp.vec3(0.5)
    for k in range(3):
        if c[k] < 0.0:  # not wp.max: NaN stays NaN, as in torch
            c[k] = 0.0
    colors[j] = c


@wp.kernel
def sh_colors_backward(
    sh: wp.array2d(dtype=wp.vec3),  # [N, K] (forward inputs, as above)
    means: wp.array(dtype=wp.vec3),  # [N]
    viewmats: wp.array(dtype=wp.mat44),  # [1]
    degree: int,
    v_colors: wp.array(dtype=wp.vec3),  # [N] incoming gradient
    camera_grads: int,  # 1: write v_offsets below
    v_sh: wp.array2d(dtype=wp.vec3),  # out [N, K]
    v_means: wp.array(dtype=wp.vec3),  # out [N] when degree > 0
    v_offsets: wp.array(dtype=wp.vec3),  # out [N] when camera_grads: dL/d(mean - centre), summed by the caller
    rows: wp.array(dtype=wp.int32),  # [M] with has_rows: v_colors and v_offsets are [M], and
    has_rows: int,  #                  v_sh and v_means [N], zeroed by the caller, are added at rows
):
    j = wp.tid()
    i = j
    if has_rows != 0:
        i = rows[j]
        if i < 0 or i >= sh.shape[0]:
            if camera_grads != 0:
                v_offsets[j] = wp.vec3(0.0)
            return
    d = wp.vec3(0.0)
    n = 0.0
    mean = wp.vec3(0.0)
    if degree > 0:
        mean = means[i]
        d = camera_offset(finite_or_zero(mean), viewmats[0])
        n = norm_of(d)
        d = d / wp.max(n, DIR_EPS)
    # the clamp's mask from the forward's own value (recomputed: cheaper than storing it)
    c = sh_raw(sh, i, degree, d) + wp.vec3(0.5)
    g = v_colors[j]
    for k in range(3):
        if not (c[k] >= 0.0):
            g[k] = 0.0

    put(v_sh, i, 0, C0 * g, has_rows)
    if degree == 0:
        return
    x = d[0]
    y = d[1]
    z = d[2]
    # v_sh[k] = Y_k g; the direction's gradient is sum_k (sh[k] . g) grad Y_k
    put(v_sh, i, 1, (-C1 * y) * g, has_rows)
    put(v_sh, i, 2, (C1 * z) * g, has_rows)
    put(v_sh, i, 3, (-C1 * x) * g, has_rows)
    v_d = wp.vec3(-C1 * wp.dot(sh[i, 3], g), -C1 * wp.dot(sh[i, 1], g), C1 * wp.dot(sh[i, 2], g))
    if degree > 1:
        xx = x * x
        yy = y * y
        zz = z * z
        put(v_sh, i, 4, (C2_0 * x * y) * g, has_rows)
        put(v_sh, i, 5, (C2_1 * y * z) * g, has_rows)
        put(v_sh, i, 6, (C2_2 * (2.0 * zz - xx - yy)) * g, has_rows)
        put(v_sh, i, 7, (C2_3 * x * z) * g, has_rows)
        put(v_sh, i, 8, (C2_4 * (xx - yy)) * g, has_rows)
        g4 = C2_0 * wp.dot(sh[i, 4], g)
        g5 = C2_1 * wp.dot(sh[i, 5], g)
        g6 = C2_2 * wp.dot(sh[i, 6], g)
        g7 = C2_3 * wp.dot(sh[i, 7], g)
        g8 = C2_4 * wp.dot(sh[i, 8], g)
        v_d += wp.vec3(g4 * y - 2.0 * g6 * x + g7 * z + 2.0 * g8 * x,
                       g4 * x + g5 * z - 2.0 * g6 * y - 2.0 * g8 * y,
                       g5 * y + 4.0 * g6 * z + g7 * x)
        if degree > 2:
            put(v_sh, i, 9, (C3_0 * y * (3.0 * xx - yy)) * g, has_rows)
            put(v_sh, i, 10, (C3_1 * x * y * z) * g, has_rows)
            put(v_sh, i, 11, (C3_2 * y * (4.0 * zz - xx - yy)) * g, has_rows)
            put(v_sh, i, 12, (C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)) * g, has_rows)
            put(v_sh, i, 13, (C3_4 * x * (4.0 * zz - xx - yy)) * g, has_rows)
            put(v_sh, i, 14, (C3_5 * z * (xx - yy)) * g, has_rows)
            put(v_sh, i, 15, (C3_6 * x * (xx - 3.0 * yy)) * g, has_rows)
            g9 = C3_0 * wp.dot(sh[i, 9], g)
            g10 = C3_1 * wp.dot(sh[i, 10], g)
            g11 = C3_2 * wp.dot(sh[i, 11], g)
            g12 = C3_3 * wp.dot(sh[i, 12], g)
            g13 = C3_4 * wp.dot(sh[i, 13], g)
            g14 = C3_5 * wp.dot(sh[i, 14], g)
            g15 = C3_6 * wp.dot(sh[i, 15], g)
            v_d += wp.vec3(
                6.0 * g9 * x * y + g10 * y * z - 2.0 * g11 * x * y - 6.0 * g12 * x * z
                + g13 * (4.0 * zz - 3.0 * xx - yy) + 2.0 * g14 * x * z + 3.0 * g15 * (xx - yy),
                3.0 * g9 * (xx - yy) + g10 * x * z + g11 * (4.0 * zz - xx - 3.0 * yy) - 6.0 * g12 * y * z
                - 2.0 * g13 * x * y - 2.0 * g14 * y * z - 6.0 * g15 * x * y,
                g10 * x * y + 8.0 * g11 * y * z + g12 * (6.0 * zz - 3.0 * xx - 3.0 * yy) + 8.0 * g13 * x * z
                + g14 * (xx - yy),
            )
    # through d / max(|d|, DIR_EPS): the tangent part over |d|, or all of it over DIR_EPS (torch's clamp)
    if n >= DIR_EPS:
        v_d = (v_d - d * wp.dot(d, v_d)) / n
    else:
        v_d = v_d / DIR_EPS
    v_m = v_d
    for k in range(3):
        if not wp.isfinite(mean[k]):
            v_m[k] = 0.0
    put(v_means, i, v_m, has_rows)
    if camera_grads != 0:
        v_offsets[j] = v_d
