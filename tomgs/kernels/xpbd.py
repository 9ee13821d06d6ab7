"""XPBD soft body on tetrahedra: edge-length and tet-volume constraints, a ground plane.

One substep (Macklin et al. 2019, "Small Steps in Physics Simulation": many substeps, one
iteration each, multipliers reset per substep):
    predict -> touch_ground -> solve_edges (per colour) -> solve_tets (per colour) -> collide_ground
    -> update_velocity

Floor contact inside the solve: touch_ground lifts predicted positions out of the floor and marks
them; the constraints then move a marked vertex only tangentially (floor_gradient) and meet
themselves with the free vertices, recording what they asked of it along the normal (`lift`);
collide_ground lets it lift off by the mean of those asks when they pull it up, bounds friction by
the whole push, and clears any penetration left. Solving the constraints with the floor's vertices
free and projecting afterwards (the first version) let every substep push the contact layer into the
floor and undo it, so on fine meshes (12+ cells a side) an impact flattened and inverted the tets
at the contact.

Constraints are solved Gauss-Seidel over a graph colouring (no two constraints of a colour share a
vertex; the caller launches one colour at a time with `start` = the colour's first constraint).
Why colouring rather than Jacobi with atomics and averaging: each thread owns its vertices, so
there are no atomics and no races, a run repeats bit for bit on the GPU, and the compliance means
what XPBD says it means (averaging softens a constraint by its vertices' valence).

Damping of the material (Macklin et al. 2016, XPBD eq. 26, with the damping coefficient set to
viscosity x stiffness): gamma = viscosity / h resists the constraint's rate of change, a
Kelvin-Voigt solid with relaxation time `viscosity` seconds. It damps wobble and leaves rigid motion
(falling, spinning) alone; `predict` adds plain velocity damping (air drag) on top.

Both constraints are written in strain form (C = l/l0 - 1, C = V/V0 - 1) so that their compliance
does not depend on the element size; the caller folds element volume and 1/h^2 into `alpha`.
All positions are in the caller's units (tomgs.edit.physics works in units of the body's extent).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def tet_volume(x0: wp.vec3, x1: wp.vec3, x2: wp.vec3, x3: wp.vec3) -> float:
    # signed: positive for the contract's vertex order
    return wp.dot(x1 - x0, wp.cross(x2 - x0, x3 - x0)) / 6.0


@wp.kernel
def rest_measures(
    x: wp.array(dtype=wp.vec3),  # [V] rest pose
    edges: wp.array(dtype=wp.vec2i),  # [E]
    tets: wp.array(dtype=wp.vec4i),  # [T]
    rest_length: wp.array(dtype=float),  # [E] out
    rest_volume: wp.array(dtype=float),  # [T] out
):
    # measured by the same float32 code the solver uses, so the rest pose satisfies every
    # constraint exactly and a body left alone stays exactly still
    k = wp.tid()
    if k < edges.shape[0]:
        rest_length[k] = wp.length(x[edges[k][0]] - x[edges[k][1]])
    if k < tets.shape[0]:
        q = tets[k]
        rest_volume[k] = tet_volume(x[q[0]], x[q[1]], x[q[2]], x[q[3]])


@wp.kernel
def predict(
    x: wp.array(dtype=wp.vec3),  # [V] in: end of last substep, out: predicted
    v: wp.array(dtype=wp.vec3),  # [V] in: velocity, out: velocity after gravity and damping
    x_prev: wp.array(dtype=wp.vec3),  # [V] out: x at the start of the substep
    contact: wp.array(dtype=int),  # [V] out: cleared
    pushed: wp.array(dtype=float),  # [V] out: cleared
    lift: wp.array(dtype=wp.vec2),  # [V] out: cleared
    gravity: wp.vec3,
    h: float,
    decay: float,  # exp(-damping h): velocity damping, exact for any h
):
    i = wp.tid()
    vi = (v[i] + gravity * h) * decay
    v[i] = vi
    x_prev[i] = x[i]
    x[i] = x[i] + vi * h
    contact[i] = 0
    pushed[i] = 0.0
    lift[i] = wp.vec2(0.0, 0.0)


@wp.func
def floor_gradient(g: wp.vec3, resting: int, normal: wp.vec3) -> wp.vec3:
    # a vertex the floor holds keeps its height while the constraints are solved: only the tangential
    # part of its gradient moves it, so a constraint is met by the vertices that are free to move
    # (rather than pushing the held vertex into the floor, to be undone by collide_ground)
    if resting != 0:
        return g - normal * wp.dot(g, normal)
    return g


@wp.kernel
def solve_edges(
    x: wp.array(dtype=wp.vec3),  # [V]
    w: wp.array(dtype=float),  # [V] inverse mass
    edges: wp.array(dtype=wp.vec2i),  # [E] sorted by colour
    rest_length: wp.array(dtype=float),  # [E]
    alpha: wp.array(dtype=float),  # [E] compliance / (edge volume h^2)
    lam: wp.array(dtype=float),  # [E] Lagrange multipliers, zeroed per substep
    x_prev: wp.array(dtype=wp.vec3),  # [V] positions at the start of the substep
    contact: wp.array(dtype=int),  # [V] 1 where the floor holds the vertex this substep
    lift: wp.array(dtype=wp.vec2),  # [V] in/out: normal moves the floor held back, and their count
    normal: wp.vec3,  # the floor's, unit, up
    gamma: float,  # viscosity / h
    start: int,  # first edge of this colour
):
    e = start + wp.tid()
    i = edges[e][0]
    j = edges[e][1]
    d = x[i] - x[j]
    length = wp.length(d)
    l0 = rest_length[e]
    if length <= 1.0e-9 * l0:
        return  # coincident vertices: no direction to push along
    n = d / length
    c = length / l0 - 1.0
    gi = floor_gradient(n / l0, contact[i], normal)
    gj = floor_gradient(-n / l0, contact[j], normal)
    denom = (1.0 + gamma) * (w[i] * wp.dot(gi, gi) + w[j] * wp.dot(gj, gj)) + alpha[e]
    if denom <= 1.0e-12:
        return  # both ends immovable (or held by the floor along the edge)
    rate = wp.dot(gi, x[i] - x_prev[i]) + wp.dot(gj, x[j] - x_prev[j])  # grad C . dx
    dlam = (-c - alpha[e] * lam[e] - gamma * rate) / denom
    lam[e] = lam[e] + dlam
    x[i] = x[i] + gi * (w[i] * dlam)
    x[j] = x[j] + gj * (w[j] * dlam)
    if contact[i] != 0:
        lift[i] = lift[i] + wp.vec2(wp.dot(n, normal) * (w[i] * dlam / l0), 1.0)
    if contact[j] != 0:
        lift[j] = lift[j] + wp.vec2(-wp.dot(n, normal) * (w[j] * dlam / l0), 1.0)


@wp.kernel
def solve_tets(
    x: wp.array(dtype=wp.vec3),  # [V]
    w: wp.array(dtype=float),  # [V] inverse mass
    tets: wp.array(dtype=wp.vec4i),  # [T] sorted by colour
    rest_volume: wp.array(dtype=float),  # [T] > 0
    alpha: wp.array(dtype=float),  # [T] compliance / (V0 h^2)
    lam: wp.array(dtype=float),  # [T] zeroed per substep
    x_prev: wp.array(dtype=wp.vec3),  # [V]
    contact: wp.array(dtype=int),  # [V]
    lift: wp.array(dtype=wp.vec2),  # [V] in/out
    normal: wp.vec3,
    gamma: float,  # viscosity / h
    start: int,
):
    t = start + wp.tid()
    a = tets[t][0]
    b = tets[t][1]
    c = tets[t][2]
    d = tets[t][3]
    x0 = x[a]
    x1 = x[b]
    x2 = x[c]
    x3 = x[d]
    v0 = rest_volume[t]
    # dV/dx_k; the gradient points towards growing volume on either side of V = 0, so an
    # inverted tet is pushed back through zero to positive volume, never held inverted
    g1 = wp.cross(x2 - x0, x3 - x0) / (6.0 * v0)
    g2 = wp.cross(x3 - x0, x1 - x0) / (6.0 * v0)
    g3 = wp.cross(x1 - x0, x2 - x0) / (6.0 * v0)
    g0 = -(g1 + g2 + g3)
    cval = tet_volume(x0, x1, x2, x3) / v0 - 1.0
    f0 = floor_gradient(g0, contact[a], normal)
    f1 = floor_gradient(g1, contact[b], normal)
    f2 = floor_gradient(g2, contact[c], normal)
    f3 = floor_gradient(g3, contact[d], normal)
    stiff = w[a] * wp.dot(f0, f0) + w[b] * wp.dot(f1, f1) + w[c] * wp.dot(f2, f2) + w[d] * wp.dot(f3, f3)
    full = w[a] * wp.dot(g0, g0) + w[b] * wp.dot(g1, g1) + w[c] * wp.dot(g2, g2) + w[d] * wp.dot(g3, g3)
    if stiff < 0.01 * full:
        # flattened against the floor: only a normal move can restore it, so move it freely
        # (collide_ground lifts what goes under)
        f0 = g0
        f1 = g1
        f2 = g2
        f3 = g3
        stiff = full
    if stiff <= 1.0e-12:
        return  # collapsed to a point or line, or held by the floor: no gradient to follow
    rate = (wp.dot(f0, x0 - x_prev[a]) + wp.dot(f1, x1 - x_prev[b]) + wp.dot(f2, x2 - x_prev[c])
            + wp.dot(f3, x3 - x_prev[d]))
    dlam = (-cval - alpha[t] * lam[t] - gamma * rate) / ((1.0 + gamma) * stiff + alpha[t])
    lam[t] = lam[t] + dlam
    x[a] = x0 + f0 * (w[a] * dlam)
    x[b] = x1 + f1 * (w[b] * dlam)
    x[c] = x2 + f2 * (w[c] * dlam)
    x[d] = x3 + f3 * (w[d] * dlam)
    if contact[a] != 0:
        lift[a] = lift[a] + wp.vec2(wp.dot(g0, normal) * (w[a] * dlam), 1.0)
    if contact[b] != 0:
        lift[b] = lift[b] + wp.vec2(wp.dot(g1, normal) * (w[b] * dlam), 1.0)
    if contact[c] != 0:
        lift[c] = lift[c] + wp.vec2(wp.dot(g2, normal) * (w[c] * dlam), 1.0)
    if contact[d] != 0:
        lift[d] = lift[d] + wp.vec2(wp.dot(g3, normal) * (w[d] * dlam), 1.0)


@wp.kernel
def touch_ground(
    x: wp.array(dtype=wp.vec3),  # [V]
    contact: wp.array(dtype=int),  # [V] out: 1 where the floor pushed
    pushed: wp.array(dtype=float),  # [V] out: how far it pushed
    point: wp.vec3,  # a point on the floor
    normal: wp.vec3,  # unit, pointing into the free half-space
):
    # before the constraints: lift the predicted positions out of the floor and mark them, so that
    # the constraints leave them there (floor_gradient) and push the rest of the body instead;
    # friction waits for collide_ground, which sees the whole substep's slide
    i = wp.tid()
    depth = -wp.dot(x[i] - point, normal)
    if depth <= 0.0:
        return
    x[i] = x[i] + normal * depth
    contact[i] = 1
    pushed[i] = depth


@wp.kernel
def collide_ground(
    x: wp.array(dtype=wp.vec3),  # [V]
    x_prev: wp.array(dtype=wp.vec3),  # [V]
    contact: wp.array(dtype=int),  # [V] in/out: 1 where the floor pushed
    pushed: wp.array(dtype=float),  # [V] how far touch_ground pushed this substep (0 without it)
    lift: wp.array(dtype=wp.vec2),  # [V] the normal moves the constraints asked of held vertices, count
    point: wp.vec3,  # a point on the floor
    normal: wp.vec3,  # unit, pointing into the free half-space
    friction: float,
):
    i = wp.tid()
    xi = x[i]
    net = lift[i][0]  # > 0: the constraints pull the vertex off the floor, < 0: they press it on
    if net > 0.0:
        # lift-off by their mean move (each was solved with the vertex held, so their sum overshoots)
        xi = xi + normal * (net / lift[i][1])
    depth = wp.max(-wp.dot(xi - point, normal), 0.0)
    # the substep's whole normal push (touch_ground's, the constraints' net push into the floor and
    # what is left now): Coulomb friction is bounded by it
    total = depth + pushed[i] + wp.max(-net, 0.0)
    if total <= 0.0:
        x[i] = xi
        return
    xi = xi + normal * depth
    # Coulomb friction on the substep's sliding displacement (Macklin et al. 2014): static while
    # the slide is within friction x push, otherwise shortened by that much
    dx = xi - x_prev[i]
    slide = dx - normal * wp.dot(dx, normal)
    s = wp.length(slide)
    limit = friction * total
    if s <= limit:
        xi = xi - slide
    else:
        xi = xi - slide * (limit / s)
    x[i] = xi
    contact[i] = 1


@wp.kernel
def update_velocity(
    x: wp.array(dtype=wp.vec3),  # [V]
    x_prev: wp.array(dtype=wp.vec3),  # [V]
    v: wp.array(dtype=wp.vec3),  # [V] in: velocity before the solve, out: new velocity
    contact: wp.array(dtype=int),  # [V]
    normal: wp.vec3,
    inv_h: float,
    restitution: float,
    rest_speed: float,  # approach speeds below this do not bounce (no jitter at rest)
):
    i = wp.tid()
    vi = (x[i] - x_prev[i]) * inv_h
    if contact[i] != 0:
        approach = wp.dot(v[i], normal)
        if approach < 0.0:
            target = float(0.0)
            if -approach > rest_speed:
                target = -restitution * approach
            vi = vi + normal * (target - wp.dot(vi, normal))
    v[i] = vi


@wp.kernel
def record_frame(
    x: wp.array(dtype=wp.vec3),  # [V]
    tets: wp.array(dtype=wp.vec4i),  # [T]
    rest_volume: wp.array(dtype=float),  # [T]
    frame: int,
    frames: wp.array2d(dtype=wp.vec3),  # [F, V] out: row `frame` = x
    min_ratio: wp.array(dtype=float),  # [F] out: min over tets of V / V0 (start at +inf)
    inverted: wp.array(dtype=int),  # [F] out: tets with V <= 0 or a non-finite vertex
):
    # one thread per tet, plus the vertex copy on threads below V
    t = wp.tid()
    if t < x.shape[0]:
        frames[frame, t] = x[t]
    if t >= tets.shape[0]:
        return
    q = tets[t]
    r = tet_volume(x[q[0]], x[q[1]], x[q[2]], x[q[3]]) / rest_volume[t]
    if not (r > 0.0) or not wp.isfinite(r):
        wp.atomic_add(inverted, frame, 1)
    if wp.isfinite(r):
        wp.atomic_min(min_ratio, frame, r)
