"""The densifier's statistics of a step in one pass (tomgs.train.densify.Densifier.observe).

Per rendered Gaussian that the frame reached, the norm of its projected mean's gradient, in NDC
units (the scale the 3DGS threshold is set in), is added to its running sum and its view count to
one more. One launch for what took seven torch operations over every Gaussian (scale, norm, zero
fill, select, add, cast, add) each step while the cloud grows: the first minute of a GPU fit.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def observe_view_gradients(
    grad: wp.array(dtype=wp.vec2),  # [M] dL/d(projected mean), pixels
    rows: wp.array(dtype=wp.int64),  # [M] the rendered rows' Gaussians, or empty: rendered row = Gaussian
    visible: wp.array(dtype=wp.bool),  # [N] the Gaussians the frame reached
    ndc_scale: wp.vec2,  # (width / 2, height / 2): pixels -> NDC units
    grad_sum: wp.array(dtype=float),  # [N] in place
    seen: wp.array(dtype=float),  # [N] in place
):
    k = wp.tid()
    g = k
    if rows.shape[0] > 0:
        g = int(rows[k])
    if visible[g]:
        # atomics: a row listed twice (rendered twice) adds both of its gradients
        wp.atomic_add(grad_sum, g, wp.length(wp.cw_mul(grad[k], ndc_scale)))
        wp.atomic_add(seen, g, 1.0)
