"""The alive index's bound on a Gaussian under training (tomgs/render/alive.py says why and how): the clip
times its temporal window can reach before the index looks at it again, and whether that reaches a
frame outside the buckets listing it.

One thread per Gaussian, in float64: the row's temporal parameters and their Adam moments -> how far
Adam can move each (tomgs.render.alive.adam_reach), the widest window that allows (the model's activations,
tomgs.temporal's alive window with the index's slack). A copy of those formulas, as kernels cannot
call torch; tests hold it to tomgs.render.alive.reach_reference. A training step's check is one launch
instead of some forty torch calls.
"""

import warp as wp

from tomgs.constants import ALPHA_MIN

wp.set_module_options({"enable_backward": False})

INF = wp.constant(wp.float64(float("inf")))


@wp.func
def adam_move(p: float, m: float, v: float, has_moments: int, scale: wp.float64, q: wp.float64,
              root_c: wp.float64, spikes: int, dense: int, headroom: wp.float64) -> wp.float64:
    # tomgs.render.alive.adam_reach: r = |m| / sqrt(v); s spikes r <- q r + sqrt(c); dense Adam then coasts
    # q r / (1 - q); scale = F lr (1 + 1e-3) (0: the parameter does not move, whatever r is)
    if scale == wp.float64(0.0):
        return headroom + wp.float64(1.0e-5) * (wp.float64(1.0) + wp.abs(wp.float64(p)))
    r = wp.float64(0.0)
    if has_moments != 0 and m != 0.0:
        r = wp.float64(wp.abs(m)) / wp.sqrt(wp.float64(v))  # inf where v underflowed: listed everywhere
    moved = wp.float64(0.0)
    for _ in range(spikes):
        r = q * r + root_c
        moved = moved + r
    if dense != 0:
        moved = moved + q / (wp.float64(1.0) - q) * r
    return scale * moved + wp.float64(1.0e-5) * (wp.float64(1.0) + wp.abs(wp.float64(p))) + headroom


@wp.struct
class Bound:
    """What bounds each Gaussian's reach under training: its temporal parameters, their Adam moments and
    Adam's constants (tomgs.render.alive's TrainingIndex fills it), one argument for the two kernels."""

    t_means: wp.array(dtype=float)  # [N] the model's stored parameters
    log_t_scales: wp.array(dtype=float)
    opacity_logits: wp.array(dtype=float)
    m_t: wp.array(dtype=float)  # Adam's moments of each (stand-ins without)
    v_t: wp.array(dtype=float)
    m_s: wp.array(dtype=float)
    v_s: wp.array(dtype=float)
    m_o: wp.array(dtype=float)
    v_o: wp.array(dtype=float)
    has_moments: wp.vec3i  # t_means, log_t_scales, opacity_logits
    scale: wp.vec3d  # F lr (1 + 1e-3) of each
    headroom: wp.vec3d  # headroom x lr of each
    q: wp.float64
    root_c: wp.float64
    spikes: int
    dense: int
    slack: wp.float64


@wp.func
def reach_window(i: int, b: Bound) -> wp.vec2d:
    mu = b.t_means[i]
    d_t = adam_move(mu, b.m_t[i], b.v_t[i], b.has_moments[0], b.scale[0], b.q, b.root_c, b.spikes, b.dense,
                    b.headroom[0])
    d_s = adam_move(b.log_t_scales[i], b.m_s[i], b.v_s[i], b.has_moments[1], b.scale[1], b.q, b.root_c, b.spikes,
                    b.dense, b.headroom[1])
    d_o = adam_move(b.opacity_logits[i], b.m_o[i], b.v_o[i], b.has_moments[2], b.scale[2], b.q, b.root_c, b.spikes,
                    b.dense, b.headroom[2])
    a = wp.float64(1.0) / (wp.float64(1.0) + wp.exp(-(wp.float64(b.opacity_logits[i]) + d_o)))
    sigma = wp.exp(wp.float64(b.log_t_scales[i]) + d_s)
    alpha_min = wp.float64(ALPHA_MIN)
    if not (a >= alpha_min):  # alive at no time (NaN too)
        return wp.vec2d(INF, -INF)
    reach = wp.sqrt(wp.float64(2.0) * wp.log(wp.max(a / alpha_min, wp.float64(1.0))))
    r = (reach * (wp.float64(1.0) + b.slack) + b.slack) * sigma
    return wp.vec2d(wp.float64(mu) - d_t - r, wp.float64(mu) + d_t + r)


@wp.kernel
def reach_windows(
    bound: Bound,
    first: wp.array(dtype=wp.float64),  # out [N]
    last: wp.array(dtype=wp.float64),  # out [N]
):
    i = wp.tid()
    w = reach_window(i, bound)
    first[i] = w[0]
    last[i] = w[1]


@wp.func
def frames_from(times: wp.array(dtype=wp.float64), x: wp.float64) -> int:
    # the first frame at or after x (times ascending)
    lo = int(0)
    hi = times.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if times[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    return lo


@wp.func
def frames_to(times: wp.array(dtype=wp.float64), x: wp.float64) -> int:
    # one past the last frame at or before x
    lo = int(0)
    hi = times.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if times[mid] <= x:
            lo = mid + 1
        else:
            hi = mid
    return lo


@wp.kernel
def reach_escapes(
    rows: wp.array(dtype=wp.int32),  # [M] the Gaussians a step rendered
    moved: wp.array(dtype=wp.bool),  # [M] those it gave a gradient (in view): only these are checked
    bound: Bound,
    times: wp.array(dtype=wp.float64),  # [T] the index's frame times, ascending
    size: int,  # frames per bucket
    b_first: wp.array(dtype=wp.int32),  # [N] first bucket listing each Gaussian
    b_last: wp.array(dtype=wp.int32),  # [N] last one (< b_first: none)
    escaped: wp.array(dtype=wp.bool),  # out [M]: reaches a frame no bucket of it holds
    count: wp.array(dtype=wp.int32),  # [1] += the escaped
):
    j = wp.tid()
    if not moved[j]:  # zero gradient: it coasts (dense Adam) or stays (SeenAdam), inside by consistency
        escaped[j] = False
        return
    i = int(rows[j])
    w = reach_window(i, bound)
    out = False
    if not (wp.isnan(w[0]) or wp.isnan(w[1])):  # a NaN window: culled by projection, alive nowhere
        start = frames_from(times, w[0])
        stop = frames_to(times, w[1])
        if stop > start:
            out = start // size < b_first[i] or (stop - 1) // size > b_last[i]
    escaped[j] = out
    if out:
        wp.atomic_add(count, 0, 1)
