"""Writes of per-Gaussian gradients for kernels that take `rows` (tomgs.render.rasterize(rows=)):
thread j handles Gaussian rows[j] and writes its gradient into the full [N] array, added atomically,
so that a Gaussian listed twice (rendered twice, as gathered inputs with a repeated row would be)
gets the sum; without rows thread i stores into row i, as it always did."""

import warp as wp


@wp.func
def put(a: wp.array(dtype=float), i: int, value: float, add: int):
    if add != 0:
        wp.atomic_add(a, i, value)
    else:
        a[i] = value


@wp.func
def put(a: wp.array(dtype=wp.vec3), i: int, value: wp.vec3, add: int):  # noqa: F811 (a Warp overload)
    if add != 0:
        wp.atomic_add(a, i, value)
    else:
        a[i] = value


@wp.func
def put(a: wp.array(dtype=wp.vec4), i: int, value: wp.vec4, add: int):  # noqa: F811
    if add != 0:
        wp.atomic_add(a, i, value)
    else:
        a[i] = value


@wp.func
def put(a: wp.array2d(dtype=wp.vec3), i: int, k: int, value: wp.vec3, add: int):  # noqa: F811
    if add != 0:
        wp.atomic_add(a, i, k, value)
    else:
        a[i, k] = value
