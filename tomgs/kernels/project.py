"""Stage 1: project Gaussians to the image, one thread per Gaussian, and its backward.

A warp takes as long as its slowest lane: with ~15% of a fitted clip alive at a frame, nearly every
warp of a pass over all Gaussians holds a few alive ones, and one pass cost what projecting every
Gaussian costs. So `project_forward` settles what a dead Gaussian needs (o_i(t), depth, zeros, the
contract checks) for all of them and runs the long path only in warps holding at least `inline_lanes`
alive ones (lanes.INLINE_LANES; on a CPU, where every thread runs alone, each runs its own); the
others' alive Gaussians go to work lists (tomgs/kernels/lanes.py) that `project_listed` runs in full
warps. The backward splits the visible ones the same way (`project_backward`, `project_backward_listed`).

Forward writes, per Gaussian i: means2d (px), conic (inverse 2D covariance, upper triangle),
depth (camera z), radii (px per axis; 0 = culled), temporal opacity o_i(t), and tiles touched.
Culled: depth outside (near, far), anything non-finite, o_i(t) < 1/255, or off screen.
Out of contract (opacity outside [0, 1], a negative scale or temporal scale, a camera that is not
finite or has fx, fy <= 0): flagged in `flags` for the caller to refuse, never silently drawn.

Time: t arrives as two float32s, t_hi + t_lo (t_hi = t rounded), and t - m is formed as
(t_hi - m) + t_lo, exact to float32 rounding of the difference, so temporal scales far below
float32's resolution of t itself (6e-8 near t = 0.5) are honoured. A frame replayed from a CUDA
graph (tomgs.render.captured) cannot change scalar arguments: its (t_hi, t_lo) are read from `times` [2]
in device memory instead, written per frame by `set_frame` (`times` empty: the scalars hold t).
"""

import warp as wp

from tomgs import constants
from tomgs.kernels.binning import opacity_extent, tiles_of
from tomgs.kernels.lanes import DENSE_REGISTERS, lanes_count, list_row, work_item
from tomgs.kernels.rows import put

wp.set_module_options({"enable_backward": False})

ALPHA_MIN = wp.constant(constants.ALPHA_MIN)
EPS2D = wp.constant(constants.EPS2D)
FOV_CLAMP = wp.constant(constants.FOV_CLAMP)
QUAT_EPS = wp.constant(constants.QUAT_EPS)
MAX_RADIUS = wp.constant(float(2**30))  # keeps radii inside int32; tiles are clamped to the image anyway

mat23 = wp.types.matrix(shape=(2, 3), dtype=wp.float32)

# slots of the int64 `flags` array shared by project_forward and frame_stats (tomgs.render reads it)
FLAG_TOTAL = wp.constant(0)  # the frame's Gaussian-tile intersection count
FLAG_OPACITIES = wp.constant(1)  # an opacity outside [0, 1] (NaN included)
FLAG_SCALES = wp.constant(2)  # a negative scale
FLAG_T_SCALES = wp.constant(3)  # a negative temporal scale
FLAG_K = wp.constant(4)  # K not finite, or fx <= 0 or fy <= 0
FLAG_VIEWMAT = wp.constant(5)  # viewmat not finite
FLAG_BACKGROUND = wp.constant(6)  # background not finite
FLAG_VISIBLE = wp.constant(7)  # count: Gaussians holding tiles (tiles_touched != 0)
FLAG_ALIVE = wp.constant(8)  # count: Gaussians with o_i(t) >= 1/255
FLAG_ROWS = wp.constant(9)  # a row outside [0, N) in the rows rendered
NUM_FLAGS = 10
CONTRACT_FLAGS = (1, 2, 3, 4, 5, 6, 9)  # the slots that refuse the frame


# What the projection kernels share, bundled: each kernel takes the Gaussians, the view and its outputs (or
# gradients) as three arguments rather than some thirty, and a frame builds each once for its four launches.


@wp.struct
class Cloud:
    """The Gaussians a frame reads (`rasterize`'s inputs) and which of them it projects: output j is
    Gaussian rows[j] with has_rows, else Gaussian j."""

    means: wp.array(dtype=wp.vec3)  # [N] world
    quats: wp.array(dtype=wp.vec4)  # [N] w x y z, any norm
    scales: wp.array(dtype=wp.vec3)  # [N]
    opacities: wp.array(dtype=float)  # [N] base opacity
    t_means: wp.array(dtype=float)  # [N]
    t_scales: wp.array(dtype=float)  # [N] sigma
    n: int  # N, the Gaussians the inputs hold
    rows: wp.array(dtype=wp.int32)  # [M] with has_rows: the Gaussians projected (the outputs are [M])
    has_rows: int
    # [1] with rows: only rows[:row_count[0]] are the frame's, the rest padding, culled (a replayed frame's,
    # tomgs.render.captured); or empty
    row_count: wp.array(dtype=wp.int32)


@wp.struct
class View:
    """A frame's camera, image and time, as the projection kernels read them."""

    viewmats: wp.array(dtype=wp.mat44)  # [1] world -> camera
    Ks: wp.array(dtype=wp.mat33)  # [1]
    width: int
    height: int
    tiles_x: int
    tiles_y: int
    t_hi: float  # t = t_hi + t_lo
    t_lo: float
    times: wp.array(dtype=float)  # [2] (t_hi, t_lo) in device memory, read in place of the two above; or empty
    near: float
    far: float


@wp.struct
class Projected:
    """Stage 1's outputs, per output j [M]."""

    means2d: wp.array(dtype=wp.vec2)
    conics: wp.array(dtype=wp.vec3)
    depths: wp.array(dtype=float)
    radii: wp.array(dtype=wp.vec2i)  # (0, 0) when culled
    opacities_t: wp.array(dtype=float)  # o_i(t)
    tiles_touched: wp.array(dtype=wp.int32)


@wp.struct
class Gradients:
    """The projection backward's gradients: in, per output [M]; out, per Gaussian [N] (with rows added at
    rows[j] into arrays the caller zeroed, kernels/rows.py), and the camera's partials per output [M]."""

    v_means2d: wp.array(dtype=wp.vec2)  # [M] incoming
    v_conics: wp.array(dtype=wp.vec3)
    v_opacities_t: wp.array(dtype=float)
    camera_grads: int  # 1: write per-output viewmat and K partials
    v_means: wp.array(dtype=wp.vec3)  # out [N]
    v_quats: wp.array(dtype=wp.vec4)
    v_scales: wp.array(dtype=wp.vec3)
    v_opacities: wp.array(dtype=float)
    v_t_means: wp.array(dtype=float)
    v_t_scales: wp.array(dtype=float)
    v_viewmat_parts: wp.array(dtype=wp.mat44)  # out [M] when camera_grads, summed by the caller
    v_K_parts: wp.array(dtype=wp.vec4)  # out [M] (fx, fy, cx, cy) when camera_grads


@wp.func
def quat_max_abs(q: wp.vec4) -> float:
    return wp.max(wp.max(wp.abs(q[0]), wp.abs(q[1])), wp.max(wp.abs(q[2]), wp.abs(q[3])))


@wp.func
def unit_quat(q: wp.vec4) -> wp.vec4:
    # q / max(|q|, QUAT_EPS) without squaring q: |q|^2 overflows float32 from |q| ~ 1.8e19 (that
    # quaternion rendered as the identity) and loses precision below |q| ~ 1e-19
    m = quat_max_abs(q)
    if m >= 1.0e-18 and m <= 1.0e18:  # |q|^2 is safe: the plain formula, as always
        return q / wp.max(wp.length(q), QUAT_EPS)
    if m > 0.0:
        qs = q / m
        ls = wp.length(qs)  # in [1, 2]
        if m * ls >= QUAT_EPS:
            return qs / ls
    return q / QUAT_EPS


@wp.func
def rotation_from_unit_quat(q: wp.vec4) -> wp.mat33:
    # q = (w, x, y, z); rows of the rotation matrix
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    return wp.mat33(
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y),
    )


@wp.func
def temporal_z(t_hi: float, t_lo: float, t_mean: float, t_scale: float) -> float:
    # (t - m) / sigma with t = t_hi + t_lo: t_hi - m is exact when m is near t (Sterbenz)
    return ((t_hi - t_mean) + t_lo) / t_scale


@wp.func
def frame_time(t_hi: float, t_lo: float, times: wp.array(dtype=float)) -> wp.vec2:
    # (t_hi, t_lo) from `times` [2] when it holds them (a replayed frame), else the scalars
    if times.shape[0] == 2:
        return wp.vec2(times[0], times[1])
    return wp.vec2(t_hi, t_lo)


@wp.func
def fov_limits(K: wp.mat33, width: int, height: int) -> wp.vec2:
    return wp.vec2(FOV_CLAMP * 0.5 * float(width) / K[0, 0], FOV_CLAMP * 0.5 * float(height) / K[1, 1])


@wp.func
def ewa_jacobian(p: wp.vec3, K: wp.mat33, lim: wp.vec2) -> mat23:
    # d(pixel)/d(camera point), evaluated at x/z, y/z clamped to the widened field of view
    u = wp.clamp(p[0] / p[2], -lim[0], lim[0])
    v = wp.clamp(p[1] / p[2], -lim[1], lim[1])
    return mat23(K[0, 0] / p[2], 0.0, -K[0, 0] * u / p[2], 0.0, K[1, 1] / p[2], -K[1, 1] * v / p[2])


@wp.func
def conic_of(A: mat23) -> wp.vec3:
    # inverse of A A^T + eps I; its determinant as a sum of squared 2x2 minors (Cauchy-Binet)
    # plus the dilation terms, all non-negative, so thin or huge Gaussians lose no precision
    a0 = A[0, 0] * A[0, 0] + A[0, 1] * A[0, 1] + A[0, 2] * A[0, 2]
    c0 = A[1, 0] * A[1, 0] + A[1, 1] * A[1, 1] + A[1, 2] * A[1, 2]
    b = A[0, 0] * A[1, 0] + A[0, 1] * A[1, 1] + A[0, 2] * A[1, 2]
    m01 = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
    m02 = A[0, 0] * A[1, 2] - A[0, 2] * A[1, 0]
    m12 = A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]
    det = m01 * m01 + m02 * m02 + m12 * m12 + EPS2D * (a0 + c0) + EPS2D * EPS2D
    return wp.vec3((c0 + EPS2D) / det, -b / det, (a0 + EPS2D) / det)


@wp.func
def conic_vjp(A: mat23, vc: wp.vec3) -> mat23:
    # gradient of conic_of(A) given dL/d(conic) = vc, through the same stable pieces: the squared row
    # norms a0, c0, the row product b and the minors m = A0 x A1 (Cauchy-Binet); every term is a plain
    # product, so nothing cancels for thin Gaussians
    A0 = wp.vec3(A[0, 0], A[0, 1], A[0, 2])
    A1 = wp.vec3(A[1, 0], A[1, 1], A[1, 2])
    a = wp.dot(A0, A0) + EPS2D
    c = wp.dot(A1, A1) + EPS2D
    b = wp.dot(A0, A1)
    m = wp.cross(A0, A1)
    det = wp.dot(m, m) + EPS2D * (a + c) - EPS2D * EPS2D
    inv = 1.0 / det
    v_det = -(vc[0] * c - vc[1] * b + vc[2] * a) * inv * inv  # conic = (c, -b, a) / det
    v_a = vc[2] * inv + EPS2D * v_det
    v_c = vc[0] * inv + EPS2D * v_det
    v_b = -vc[1] * inv
    v_m = 2.0 * v_det * m
    v_A0 = 2.0 * v_a * A0 + v_b * A1 + wp.cross(A1, v_m)
    v_A1 = 2.0 * v_c * A1 + v_b * A0 + wp.cross(v_m, A0)
    return mat23(v_A0[0], v_A0[1], v_A0[2], v_A1[0], v_A1[1], v_A1[2])


@wp.func
def world_to_camera(viewmat: wp.mat44, x: wp.vec3) -> wp.vec3:
    return wp.vec3(
        viewmat[0, 0] * x[0] + viewmat[0, 1] * x[1] + viewmat[0, 2] * x[2] + viewmat[0, 3],
        viewmat[1, 0] * x[0] + viewmat[1, 1] * x[1] + viewmat[1, 2] * x[2] + viewmat[1, 3],
        viewmat[2, 0] * x[0] + viewmat[2, 1] * x[1] + viewmat[2, 2] * x[2] + viewmat[2, 3],
    )


@wp.func
def view_rotation(viewmat: wp.mat44) -> wp.mat33:
    return wp.mat33(
        viewmat[0, 0], viewmat[0, 1], viewmat[0, 2],
        viewmat[1, 0], viewmat[1, 1], viewmat[1, 2],
        viewmat[2, 0], viewmat[2, 1], viewmat[2, 2],
    )


@wp.func
def scaled_rotation(q: wp.vec4, s: wp.vec3) -> wp.mat33:
    # M = R diag(s), so that the 3D covariance is M M^T
    R = rotation_from_unit_quat(unit_quat(q))
    return wp.mat33(
        R[0, 0] * s[0], R[0, 1] * s[1], R[0, 2] * s[2],
        R[1, 0] * s[0], R[1, 1] * s[1], R[1, 2] * s[2],
        R[2, 0] * s[0], R[2, 1] * s[1], R[2, 2] * s[2],
    )


@wp.func
def footprint(j: int, p: wp.vec3, opac: float, q: wp.vec4, s: wp.vec3, viewmat: wp.mat44, K: wp.mat33, view: View,
              out: Projected):
    """The long path of output j (camera point p, alive at opacity opac, inside the depth range): its
    screen-space footprint written where it is visible; off screen or non-finite it stays culled."""
    width = view.width
    height = view.height
    J = ewa_jacobian(p, K, fov_limits(K, width, height))
    A = J * view_rotation(viewmat) * scaled_rotation(q, s)
    conic = conic_of(A)
    a = A[0, 0] * A[0, 0] + A[0, 1] * A[0, 1] + A[0, 2] * A[0, 2] + EPS2D
    c = A[1, 0] * A[1, 0] + A[1, 1] * A[1, 1] + A[1, 2] * A[1, 2] + EPS2D
    center = wp.vec2(K[0, 0] * p[0] / p[2] + K[0, 2], K[1, 1] * p[1] / p[2] + K[1, 2])

    # opacity-aware extent: beyond it the Gaussian's alpha is below 1/255 everywhere
    extend = opacity_extent(opac)
    rx = wp.min(wp.ceil(extend * wp.sqrt(a)), MAX_RADIUS)
    ry = wp.min(wp.ceil(extend * wp.sqrt(c)), MAX_RADIUS)
    finite = wp.isfinite(center) and wp.isfinite(conic) and wp.isfinite(rx) and wp.isfinite(ry)
    on_screen = not (center[0] + rx <= 0.0 or center[0] - rx >= float(width) or center[1] + ry <= 0.0
                     or center[1] - ry >= float(height))
    if finite and (rx > 0.0 or ry > 0.0) and on_screen:
        radius = wp.vec2i(int(rx), int(ry))
        out.means2d[j] = center
        out.conics[j] = conic
        out.radii[j] = radius
        out.tiles_touched[j] = tiles_of(center, conic, radius, opac, view.tiles_x, view.tiles_y)


@wp.kernel(cuda_max_registers=DENSE_REGISTERS, grid_stride=False)  # one thread per row: no loop to carry
def project_forward(
    cloud: Cloud,
    view: View,
    out: Projected,  # out [M]
    flags: wp.array(dtype=wp.int64),  # [NUM_FLAGS] zeroed by the caller; set to 1 on a contract violation
    inline_lanes: int,  # a warp holding this many alive lanes runs their long path (INLINE_LANES; 1 on a CPU)
    capacity: int,  # slots of each work list (work_capacity)
    work: wp.array(dtype=wp.int32),  # out [WORK_LISTS x capacity]: outputs left to project_listed
    work_counts: wp.array(dtype=wp.int32),  # [lanes.work_counters(1)] zeroed by the caller: each list's count
):
    # Every Gaussian: what a dead one needs (contract checks, o_i(t), depth, zeros). The long path
    # runs here for the alive ones (and in depth range) of a warp holding at least inline_lanes of
    # them; a warp holding fewer lists them for project_listed, which runs them in full warps (a warp
    # takes as long as its slowest lane: with ~15% alive, nearly every warp holds a few)
    j = wp.tid()
    i = j
    out.radii[j] = wp.vec2i(0, 0)
    out.tiles_touched[j] = 0
    out.means2d[j] = wp.vec2(0.0, 0.0)
    out.conics[j] = wp.vec3(0.0, 0.0, 0.0)
    valid = True
    if cloud.has_rows != 0:
        if cloud.row_count.shape[0] > 0 and j >= cloud.row_count[0]:
            valid = False  # padding: projected as a culled Gaussian, never read
        else:
            i = cloud.rows[j]
            if i < 0 or i >= cloud.n:
                flags[FLAG_ROWS] = wp.int64(1)
                valid = False
    keep = False
    opac = float(0.0)
    p = wp.vec3(0.0)
    viewmat = view.viewmats[0]
    if valid:
        base = cloud.opacities[i]
        s = cloud.scales[i]
        t_scale = cloud.t_scales[i]
        if not (base >= 0.0 and base <= 1.0):
            flags[FLAG_OPACITIES] = wp.int64(1)
        if s[0] < 0.0 or s[1] < 0.0 or s[2] < 0.0:
            flags[FLAG_SCALES] = wp.int64(1)
        if t_scale < 0.0:
            flags[FLAG_T_SCALES] = wp.int64(1)
        t = frame_time(view.t_hi, view.t_lo, view.times)
        z = temporal_z(t[0], t[1], cloud.t_means[i], t_scale)
        opac = base * wp.exp(-0.5 * z * z)
        p = world_to_camera(viewmat, cloud.means[i])
        # alive (also rejects NaN) and inside the depth range
        keep = opac >= ALPHA_MIN and opac <= 1.0e30 and p[2] > view.near and p[2] < view.far
    out.opacities_t[j] = opac
    out.depths[j] = p[2]
    inline = lanes_count(keep) >= inline_lanes  # the same for the warp's lanes
    list_row(keep and not inline, j, capacity, work, work_counts)  # every lane reaches it: no return above
    if keep and inline:
        footprint(j, p, opac, cloud.quats[i], cloud.scales[i], viewmat, view.Ks[0], view, out)


@wp.kernel
def project_listed(
    cloud: Cloud,
    view: View,
    out: Projected,  # [M]: reads opacities_t from project_forward, writes the long path's outputs where visible
    capacity: int,  # project_forward's work lists: the outputs it left
    work: wp.array(dtype=wp.int32),
    work_counts: wp.array(dtype=wp.int32),
):
    # launched over the work lists' slots, run where one lists a row
    j = work_item(wp.tid(), capacity, work, work_counts)
    if j < 0:
        return
    i = j
    if cloud.has_rows != 0:
        i = cloud.rows[j]
    viewmat = view.viewmats[0]
    footprint(j, world_to_camera(viewmat, cloud.means[i]), out.opacities_t[j], cloud.quats[i], cloud.scales[i],
              viewmat, view.Ks[0], view, out)


@wp.func
def rotation_vjp(q: wp.vec4, g: wp.mat33) -> wp.vec4:
    # gradient of rotation_from_unit_quat at unit q, given dL/dR = g
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    vw = 2.0 * (-z * g[0, 1] + y * g[0, 2] + z * g[1, 0] - x * g[1, 2] - y * g[2, 0] + x * g[2, 1])
    vx = 2.0 * (y * g[0, 1] + z * g[0, 2] + y * g[1, 0] - 2.0 * x * g[1, 1] - w * g[1, 2]
                + z * g[2, 0] + w * g[2, 1] - 2.0 * x * g[2, 2])
    vy = 2.0 * (-2.0 * y * g[0, 0] + x * g[0, 1] + w * g[0, 2] + x * g[1, 0] + z * g[1, 2]
                - w * g[2, 0] + z * g[2, 1] - 2.0 * y * g[2, 2])
    vz = 2.0 * (-2.0 * z * g[0, 0] - w * g[0, 1] + x * g[0, 2] + w * g[1, 0] - 2.0 * z * g[1, 1]
                + y * g[1, 2] + x * g[2, 0] + y * g[2, 1])
    return wp.vec4(vw, vx, vy, vz)


@wp.func
def gradients(
    j: int,  # the output
    i: int,  # its Gaussian
    cloud: Cloud,
    view: View,
    t_hi: float,  # the frame's time (frame_time)
    t_lo: float,
    grads: Gradients,
):
    """The long path of the backward for visible output j (Gaussian i): its gradients (added at i
    with rows) and camera partials."""
    # temporal window: o = a g, g = exp(-z^2 / 2), z = (t - m) / sigma
    sigma = cloud.t_scales[i]
    z = temporal_z(t_hi, t_lo, cloud.t_means[i], sigma)
    g = wp.exp(-0.5 * z * z)
    v_o = grads.v_opacities_t[j]
    o = cloud.opacities[i] * g
    put(grads.v_opacities, i, v_o * g, cloud.has_rows)
    put(grads.v_t_means, i, v_o * o * z / sigma, cloud.has_rows)
    put(grads.v_t_scales, i, v_o * o * z * z / sigma, cloud.has_rows)

    viewmat = view.viewmats[0]
    W = view_rotation(viewmat)
    K = view.Ks[0]
    fx = K[0, 0]
    fy = K[1, 1]
    mu = cloud.means[i]
    p = world_to_camera(viewmat, mu)
    lim = fov_limits(K, view.width, view.height)
    J = ewa_jacobian(p, K, lim)
    q = cloud.quats[i]
    qn = unit_quat(q)
    R = rotation_from_unit_quat(qn)
    s = cloud.scales[i]
    M = wp.mat33(
        R[0, 0] * s[0], R[0, 1] * s[1], R[0, 2] * s[2],
        R[1, 0] * s[0], R[1, 1] * s[1], R[1, 2] * s[2],
        R[2, 0] * s[0], R[2, 1] * s[1], R[2, 2] * s[2],
    )
    B = W * M
    A = J * B

    # differentiate the forward's own formulas (conic_of), never dL/dSigma2d = -Q V Q: for a needle
    # that matrix needs an absolute accuracy far below float32's on its entries (error ~ eps cond)
    v_A = conic_vjp(A, grads.v_conics[j])
    v_J = v_A * wp.transpose(B)
    v_B = wp.transpose(J) * v_A
    v_M = wp.transpose(W) * v_B
    v_W = v_B * wp.transpose(M)

    v_R = wp.mat33(
        v_M[0, 0] * s[0], v_M[0, 1] * s[1], v_M[0, 2] * s[2],
        v_M[1, 0] * s[0], v_M[1, 1] * s[1], v_M[1, 2] * s[2],
        v_M[2, 0] * s[0], v_M[2, 1] * s[1], v_M[2, 2] * s[2],
    )
    put(grads.v_scales, i, wp.vec3(
        v_M[0, 0] * R[0, 0] + v_M[1, 0] * R[1, 0] + v_M[2, 0] * R[2, 0],
        v_M[0, 1] * R[0, 1] + v_M[1, 1] * R[1, 1] + v_M[2, 1] * R[2, 1],
        v_M[0, 2] * R[0, 2] + v_M[1, 2] * R[1, 2] + v_M[2, 2] * R[2, 2],
    ), cloud.has_rows)
    v_qn = rotation_vjp(qn, v_R)
    q_max = quat_max_abs(q)
    q_len = wp.length(q / q_max)  # |q| = q_max q_len, never formed: it may overflow
    if q_max > 0.0 and q_max * q_len >= QUAT_EPS:
        put(grads.v_quats, i, (v_qn - qn * wp.dot(qn, v_qn)) / q_len / q_max, cloud.has_rows)
    else:
        put(grads.v_quats, i, v_qn / QUAT_EPS, cloud.has_rows)

    # Jacobian entries J00 = fx/z, J02 = -fx u/z, J11 = fy/z, J12 = -fy v/z with u, v clamped
    px = p[0]
    py = p[1]
    pz = p[2]
    u = wp.clamp(px / pz, -lim[0], lim[0])
    v = wp.clamp(py / pz, -lim[1], lim[1])
    v_p = wp.vec3(0.0)
    v_fx = v_J[0, 0] / pz - v_J[0, 2] * u / pz
    v_fy = v_J[1, 1] / pz - v_J[1, 2] * v / pz
    v_p[2] = (-fx * v_J[0, 0] - fy * v_J[1, 1] + fx * u * v_J[0, 2] + fy * v * v_J[1, 2]) / (pz * pz)
    v_u = -fx * v_J[0, 2] / pz
    v_v = -fy * v_J[1, 2] / pz
    if wp.abs(px / pz) <= lim[0]:
        v_p[0] += v_u / pz
        v_p[2] -= v_u * px / (pz * pz)
    else:
        v_fx -= v_u * u / fx  # u = +-lim, and lim scales with 1 / fx
    if wp.abs(py / pz) <= lim[1]:
        v_p[1] += v_v / pz
        v_p[2] -= v_v * py / (pz * pz)
    else:
        v_fy -= v_v * v / fy

    # pixel centre (fx x/z + cx, fy y/z + cy)
    vm2 = grads.v_means2d[j]
    v_p[0] += fx * vm2[0] / pz
    v_p[1] += fy * vm2[1] / pz
    v_p[2] -= (fx * px * vm2[0] + fy * py * vm2[1]) / (pz * pz)
    v_fx += vm2[0] * px / pz
    v_fy += vm2[1] * py / pz

    put(grads.v_means, i, wp.transpose(W) * v_p, cloud.has_rows)
    if grads.camera_grads != 0:
        v_W += wp.outer(v_p, mu)
        grads.v_viewmat_parts[j] = wp.mat44(
            v_W[0, 0], v_W[0, 1], v_W[0, 2], v_p[0],
            v_W[1, 0], v_W[1, 1], v_W[1, 2], v_p[1],
            v_W[2, 0], v_W[2, 1], v_W[2, 2], v_p[2],
            0.0, 0.0, 0.0, 0.0,
        )
        grads.v_K_parts[j] = wp.vec4(v_fx, v_fy, vm2[0], vm2[1])


@wp.kernel(cuda_max_registers=DENSE_REGISTERS)
def project_backward(
    cloud: Cloud,  # the forward's
    view: View,
    radii: wp.array(dtype=wp.vec2i),  # [M] from the forward; (0, 0) = culled, no gradient
    grads: Gradients,
    inline_lanes: int,  # as project_forward's
    capacity: int,  # slots of each work list (work_capacity)
    work: wp.array(dtype=wp.int32),  # out [WORK_LISTS x capacity]: visible outputs left to project_backward_listed
    work_counts: wp.array(dtype=wp.int32),  # [lanes.work_counters(1)] zeroed by the caller
):
    # as project_forward: the visible outputs of a warp holding at least inline_lanes of them run the
    # long path here, the others are listed for project_backward_listed; every other row gets zeros
    # (without rows: the listed ones too, which project_backward_listed overwrites after)
    j = wp.tid()
    i = j
    if cloud.has_rows != 0:
        i = cloud.rows[j]
    r = radii[j]
    visible = r[0] != 0 or r[1] != 0  # a culled or bad row: no gradient
    inline = lanes_count(visible) >= inline_lanes
    list_row(visible and not inline, j, capacity, work, work_counts)  # every lane reaches it
    if visible and inline:
        t = frame_time(view.t_hi, view.t_lo, view.times)
        gradients(j, i, cloud, view, t[0], t[1], grads)
    else:
        if cloud.has_rows == 0:
            grads.v_means[i] = wp.vec3(0.0)
            grads.v_quats[i] = wp.vec4(0.0)
            grads.v_scales[i] = wp.vec3(0.0)
            grads.v_opacities[i] = 0.0
            grads.v_t_means[i] = 0.0
            grads.v_t_scales[i] = 0.0
        if grads.camera_grads != 0:
            grads.v_viewmat_parts[j] = wp.mat44(0.0)
            grads.v_K_parts[j] = wp.vec4(0.0)


@wp.kernel
def project_backward_listed(
    cloud: Cloud,  # as project_backward
    view: View,
    grads: Gradients,
    capacity: int,  # project_backward's work lists: the visible outputs it left
    work: wp.array(dtype=wp.int32),
    work_counts: wp.array(dtype=wp.int32),
):
    # launched over the work lists' slots, run where one lists a row
    j = work_item(wp.tid(), capacity, work, work_counts)
    if j < 0:
        return
    i = j
    if cloud.has_rows != 0:
        i = cloud.rows[j]
    t = frame_time(view.t_hi, view.t_lo, view.times)
    gradients(j, i, cloud, view, t[0], t[1], grads)


@wp.func
def check_camera(
    viewmats: wp.array(dtype=wp.mat44),  # [1]
    Ks: wp.array(dtype=wp.mat33),  # [1]
    background: wp.array(dtype=wp.vec3),  # [1], read when has_background
    has_background: int,
    flags: wp.array(dtype=wp.int64),  # [NUM_FLAGS]: the camera's and background's flags written here
):
    V = viewmats[0]
    for r in range(4):
        for c in range(4):
            if not wp.isfinite(V[r, c]):
                flags[FLAG_VIEWMAT] = wp.int64(1)
    K = Ks[0]
    for r in range(3):
        for c in range(3):
            if not wp.isfinite(K[r, c]):
                flags[FLAG_K] = wp.int64(1)
    if not (K[0, 0] > 0.0 and K[1, 1] > 0.0):
        flags[FLAG_K] = wp.int64(1)
    if has_background != 0 and not wp.isfinite(background[0]):
        flags[FLAG_BACKGROUND] = wp.int64(1)


# rows each thread of frame_stats counts, a launch apart: a sixteenth of the blocks one would need
# with a row a thread, and so of the atomics they add to the same two counters (which serialise)
STATS_ROWS = 16


@wp.kernel
def frame_stats(
    tiles_touched: wp.array(dtype=wp.int32),  # [N]
    opacities_t: wp.array(dtype=float),  # [N]
    ends: wp.array(dtype=wp.int64),  # [N] inclusive scan of tiles touched
    n: int,
    threads: int,  # the launch's size: whole blocks, about N / STATS_ROWS, at least one block
    viewmats: wp.array(dtype=wp.mat44),  # [1]
    Ks: wp.array(dtype=wp.mat33),  # [1]
    background: wp.array(dtype=wp.vec3),  # [1], read when has_background
    has_background: int,
    flags: wp.array(dtype=wp.int64),  # [NUM_FLAGS] zeroed before projection; counts added, the rest set here
):
    # gathers what the host reads back in one transfer: the intersection count, the camera's flags
    # and the visible and alive counts. Every thread reaches the block sums, one per block adds them
    # (no return before).
    i = wp.tid()
    visible = int(0)
    alive = int(0)
    for row in range(i, n, threads):  # consecutive threads, consecutive rows: coalesced
        if tiles_touched[row] != 0:
            visible += 1
        if opacities_t[row] >= ALPHA_MIN:
            alive += 1
    block_visible = wp.tile_extract(wp.tile_sum(wp.tile(visible)), 0)
    block_alive = wp.tile_extract(wp.tile_sum(wp.tile(alive)), 0)
    if i % wp.block_dim() == 0:
        if block_visible != 0:
            wp.atomic_add(flags, FLAG_VISIBLE, wp.int64(block_visible))
        if block_alive != 0:
            wp.atomic_add(flags, FLAG_ALIVE, wp.int64(block_alive))
    if i == 0:
        if n > 0:
            flags[FLAG_TOTAL] = ends[n - 1]
        check_camera(viewmats, Ks, background, has_background, flags)


@wp.kernel
def set_frame(
    viewmat: wp.array(dtype=wp.mat44),  # [1] a frame's world -> camera
    K: wp.array(dtype=wp.mat33),  # [1]
    t_hi: float,  # its t = t_hi + t_lo
    t_lo: float,
    viewmats: wp.array(dtype=wp.mat44),  # out [1]: where a replayed frame reads its camera
    Ks: wp.array(dtype=wp.mat33),  # out [1]
    times: wp.array(dtype=float),  # out [2]: and its time (`frame_time`)
    count: int,  # the rows of the frame, for a frame that renders rows
    row_count: wp.array(dtype=wp.int32),  # out [1]: where it reads their count (project_forward); or empty
):
    # one thread: a replayed frame's camera, time and row count in one launch (tomgs.render.captured)
    viewmats[0] = viewmat[0]
    Ks[0] = K[0]
    times[0] = t_hi
    times[1] = t_lo
    if row_count.shape[0] > 0:
        row_count[0] = count
