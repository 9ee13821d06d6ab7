"""SSIM with its gradient in four separable passes (the 3DGS formula, 11x11 Gaussian window).

Images are flat float32 arrays of [B,H,W,3] (channels last, as the rasterizer writes them); every
thread owns one (image, row, column, channel) value. Zero padding: taps outside the image add
nothing, exactly like conv2d(padding=5).

Forward, per pixel q of a channel: the five moments mu1 = G*x, mu2 = G*y, e11 = G*x^2, e22 = G*y^2,
e12 = G*xy (G: the window), then

    S = (2 mu1 mu2 + C1)(2 s12 + C2) / ((mu1^2 + mu2^2 + C1)(s11 + s22 + C2)),
    s11 = e11 - mu1^2, s22 = e22 - mu2^2, s12 = e12 - mu1 mu2.

The forward also keeps the partials of S in the moments that involve x: dS/dmu1 (through the
sigmas too), dS/de11 and dS/de12. The backward of a loss L with upstream g = dL/dS is then, for the
pixel p,

    dL/dx(p) = G*(g dS/dmu1)(p) + 2 x(p) G*(g dS/de11)(p) + y(p) G*(g dS/de12)(p)

(the window is symmetric, so the transposed blur is the blur). Only x gets a gradient: the
reference is a constant of the training loss. Two 1D passes each way, no atomics.

The training loss L = (1 - w) mean|x - y| + w (1 - mean S) comes from the same passes: `loss_sums`
adds |x - y|, S and (x - y)^2 over every value (block sums, one atomic per block) and `combine_loss`
forms L, and the PSNR a training step hands its frame sampler, on the device; L's gradient is the
SSIM backward with a uniform upstream g = -w dL / n, and grad_cols adds the L1 term
(1 - w) dL / n sign(x - y) as it writes dL/dx. dL (the loss's upstream) stays on the
device: the uniform arrays are a single value seen through a zero stride.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

RADIUS = 5  # 11 taps


@wp.func
def _tap(window: wp.array(dtype=float), k: int) -> float:
    return window[k + RADIUS]


@wp.kernel
def moments_rows(
    x: wp.array(dtype=float),  # [B*H*W*3]
    y: wp.array(dtype=float),  # [B*H*W*3]
    window: wp.array(dtype=float),  # [11]
    width: int,
    moments: wp.array2d(dtype=float),  # [5, B*H*W*3] out: the five moments blurred along rows
):
    i = wp.tid()
    col = (i // 3) % width
    m0 = float(0.0)
    m1 = float(0.0)
    m2 = float(0.0)
    m3 = float(0.0)
    m4 = float(0.0)
    for k in range(-RADIUS, RADIUS + 1):
        c = col + k
        if c >= 0 and c < width:
            j = i + 3 * k
            w = _tap(window, k)
            a = x[j]
            b = y[j]
            m0 += w * a
            m1 += w * b
            m2 += w * a * a
            m3 += w * b * b
            m4 += w * a * b
    moments[0, i] = m0
    moments[1, i] = m1
    moments[2, i] = m2
    moments[3, i] = m3
    moments[4, i] = m4


@wp.kernel
def ssim_cols(
    moments: wp.array2d(dtype=float),  # [5, B*H*W*3] from moments_rows
    window: wp.array(dtype=float),  # [11]
    width: int,
    height: int,
    c1: float,
    c2: float,
    ssim: wp.array(dtype=float),  # [B*H*W*3] out
    partials: wp.array2d(dtype=float),  # [3, B*H*W*3] out: dS/dmu1, dS/de11, dS/de12
):
    i = wp.tid()
    row = (i // (3 * width)) % height
    stride = 3 * width
    mu1 = float(0.0)
    mu2 = float(0.0)
    e11 = float(0.0)
    e22 = float(0.0)
    e12 = float(0.0)
    for k in range(-RADIUS, RADIUS + 1):
        r = row + k
        if r >= 0 and r < height:
            j = i + stride * k
            w = _tap(window, k)
            mu1 += w * moments[0, j]
            mu2 += w * moments[1, j]
            e11 += w * moments[2, j]
            e22 += w * moments[3, j]
            e12 += w * moments[4, j]
    a1 = 2.0 * mu1 * mu2 + c1
    a2 = 2.0 * (e12 - mu1 * mu2) + c2
    b1 = mu1 * mu1 + mu2 * mu2 + c1
    b2 = (e11 - mu1 * mu1) + (e22 - mu2 * mu2) + c2
    s = (a1 * a2) / (b1 * b2)
    d_a1 = a2 / (b1 * b2)
    d_a2 = a1 / (b1 * b2)
    d_b1 = -s / b1
    d_b2 = -s / b2
    ssim[i] = s
    partials[0, i] = 2.0 * mu2 * (d_a1 - d_a2) + 2.0 * mu1 * (d_b1 - d_b2)
    partials[1, i] = d_b2
    partials[2, i] = 2.0 * d_a2


@wp.kernel
def loss_sums(
    x: wp.array(dtype=float),  # [B*H*W*3]
    y: wp.array(dtype=float),  # [B*H*W*3]
    ssim: wp.array(dtype=float),  # [B*H*W*3] from ssim_cols
    n: int,  # values; launched over n rounded up to whole blocks
    sums: wp.array(dtype=float),  # [3] zeroed: (sum |x - y|, sum S, sum (x - y)^2) added
):
    # every thread reaches the block sums (no return before them); one per block adds them
    i = wp.tid()
    l1 = float(0.0)
    s = float(0.0)
    sq = float(0.0)
    if i < n:
        d = x[i] - y[i]
        l1 = wp.abs(d)
        s = ssim[i]
        sq = d * d
    block_l1 = wp.tile_extract(wp.tile_sum(wp.tile(l1)), 0)
    block_s = wp.tile_extract(wp.tile_sum(wp.tile(s)), 0)
    block_sq = wp.tile_extract(wp.tile_sum(wp.tile(sq)), 0)
    if i % wp.block_dim() == 0:
        wp.atomic_add(sums, 0, block_l1)
        wp.atomic_add(sums, 1, block_s)
        wp.atomic_add(sums, 2, block_sq)


@wp.kernel
def combine_loss(
    sums: wp.array(dtype=float),  # [3] from loss_sums
    n: int,
    ssim_weight: float,
    loss: wp.array(dtype=float),  # [1] out
    psnr: wp.array(dtype=float),  # [1] out: of x against y over all n values
):
    loss[0] = (1.0 - ssim_weight) * sums[0] / float(n) + ssim_weight * (1.0 - sums[1] / float(n))
    psnr[0] = -10.0 * wp.log10(sums[2] / float(n))  # inf where x == y, as tomgs.metrics.psnr


@wp.kernel
def grad_rows(
    v_ssim: wp.array(dtype=float),  # [B*H*W*3] dL/dS
    partials: wp.array2d(dtype=float),  # [3, B*H*W*3] from ssim_cols
    window: wp.array(dtype=float),  # [11]
    width: int,
    blurred: wp.array2d(dtype=float),  # [3, B*H*W*3] out: g * partials blurred along rows
):
    i = wp.tid()
    col = (i // 3) % width
    s0 = float(0.0)
    s1 = float(0.0)
    s2 = float(0.0)
    for k in range(-RADIUS, RADIUS + 1):
        c = col + k
        if c >= 0 and c < width:
            j = i + 3 * k
            wg = _tap(window, k) * v_ssim[j]
            s0 += wg * partials[0, j]
            s1 += wg * partials[1, j]
            s2 += wg * partials[2, j]
    blurred[0, i] = s0
    blurred[1, i] = s1
    blurred[2, i] = s2


@wp.kernel
def grad_cols(
    blurred: wp.array2d(dtype=float),  # [3, B*H*W*3] from grad_rows
    x: wp.array(dtype=float),  # [B*H*W*3]
    y: wp.array(dtype=float),  # [B*H*W*3]
    window: wp.array(dtype=float),  # [11]
    width: int,
    height: int,
    v_l1: wp.array(dtype=float),  # [B*H*W*3] dL/d|x - y| (a training loss's), or empty: none
    v_x: wp.array(dtype=float),  # [B*H*W*3] out: dL/dx
):
    i = wp.tid()
    row = (i // (3 * width)) % height
    stride = 3 * width
    s0 = float(0.0)
    s1 = float(0.0)
    s2 = float(0.0)
    for k in range(-RADIUS, RADIUS + 1):
        r = row + k
        if r >= 0 and r < height:
            j = i + stride * k
            w = _tap(window, k)
            s0 += w * blurred[0, j]
            s1 += w * blurred[1, j]
            s2 += w * blurred[2, j]
    v = s0 + 2.0 * x[i] * s1 + y[i] * s2
    if v_l1.shape[0] > 0:
        d = x[i] - y[i]
        if d > 0.0:  # |d|' as torch takes it: 0 where d = 0
            v += v_l1[i]
        elif d < 0.0:
            v -= v_l1[i]
    v_x[i] = v
