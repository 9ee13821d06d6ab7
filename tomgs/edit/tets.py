"""Gaussians <-> tetrahedra, exact both ways.

Gaussian i (mean mu, rotation R, scales S) becomes the regular tetrahedron x_k = mu + c R S v_k,
k = 0..3, with v_k the rows of `DIRECTIONS` and c = `TET_SIZE`. Because sum v_k = 0 and
sum v_k v_k^T = 4 I, the tet gives the Gaussian back: mu = mean x_k and
Sigma = 1/(4 c^2) sum (x_k - mu)(x_k - mu)^T = R S^2 R^T. Any motion of the 4 vertices is an affine
map F = D_s D_m^-1 (edge matrices now and at rest), under which the Gaussian becomes
(x_0' + F (mu - x_0), F Sigma F^T): `deform`.

Orientation: with the vertices in the order of `DIRECTIONS` the edge matrix has det < 0 for a
right-handed R, so a positively oriented tet lists them as (0, 1, 3, 2): tomgs.io.tets.POSITIVE_ORDER, the
order a `gaussian` tets file's rows keep.

Flat Gaussians (one scale ~0) give a degenerate tet, which no solver can move. `gaussians_to_tets`
can thicken the thin axis to `thicken` times the middle scale; `deform` then still maps the
Gaussian's own (flat) covariance, so the result stays exact. Everything is float64 numpy; rotations,
covariances and edge matrices come from tomgs.geometry.
"""

from __future__ import annotations

import numpy as np

from tomgs.geometry import covariances, edge_matrices, quat_to_rotmat, rotmat_to_quat

TET_SIZE = 1.0  # c: the tet's vertices sit at one standard deviation along each regular direction
DIRECTIONS = np.array([[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]])  # v_k [4,3]
THICKEN = 0.1  # physics tets: thin axis >= THICKEN x middle scale (keeps det D_m > 0)
MIN_VARIANCE = 1e-24  # eigenvalues are floored here (scale 1e-12) so that log(scale) stays finite


def _f64(x) -> np.ndarray:
    if hasattr(x, "detach"):  # torch tensor
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def covariance_to_gaussian(sigma) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric PSD [N,3,3] -> (quats [N,4] w >= 0, scales [N,3] ascending) by eigh; R right-handed."""
    sigma = _f64(sigma)
    sigma = 0.5 * (sigma + np.swapaxes(sigma, -1, -2))
    evals, evecs = np.linalg.eigh(sigma)
    flip = np.linalg.det(evecs) < 0
    evecs[flip, :, 2] *= -1  # a reflection is not a rotation: flip one axis (the Gaussian is symmetric)
    return rotmat_to_quat(evecs), np.sqrt(np.maximum(evals, MIN_VARIANCE))


def gaussians_to_tets(means, quats, scales, thicken: float = 0.0) -> np.ndarray:
    """Tet vertices [N,4,3]: x_k = mu + c R S v_k for means [N,3], quats [N,4], scales [N,3].

    `thicken` > 0 raises each Gaussian's smallest scale to at least `thicken` x its middle scale
    (a tet a solver can move; pair it with `deform`, which keeps the true covariance)."""
    scales = _f64(scales).copy()
    if thicken > 0:
        order = np.sort(scales, axis=-1)
        thin = np.argmin(scales, axis=-1)
        rows = np.arange(len(scales))
        scales[rows, thin] = np.maximum(scales[rows, thin], thicken * order[:, 1])
    M = TET_SIZE * quat_to_rotmat(_f64(quats)) * scales[..., None, :]  # [N,3,3] = c R S
    return _f64(means)[:, None, :] + DIRECTIONS @ np.swapaxes(M, -1, -2)


def tets_to_gaussians(vertices) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tet vertices [N,4,3] -> (means [N,3], quats [N,4], scales [N,3]), the inverse of
    `gaussians_to_tets` (without thickening) up to the order and signs of the axes."""
    x = _f64(vertices)
    mu = x.mean(axis=1)
    d = x - mu[:, None, :]
    sigma = np.swapaxes(d, -1, -2) @ d / (4.0 * TET_SIZE**2)
    quats, scales = covariance_to_gaussian(sigma)
    return mu, quats, scales


def deform(rest_vertices, vertices, means, quats, scales) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gaussians carried by their tets from `rest_vertices` [N,4,3] to `vertices` [N,4,3]:
    F = D_s D_m^-1, mean x_0' + F (mu - x_0), covariance F Sigma F^T (exact for any affine motion,
    flat Gaussians included). Returns (means [N,3], quats [N,4], scales [N,3]) in float64."""
    rest, now = _f64(rest_vertices), _f64(vertices)
    F = np.swapaxes(np.linalg.solve(np.swapaxes(edge_matrices(rest), -1, -2),
                                    np.swapaxes(edge_matrices(now), -1, -2)), -1, -2)  # D_s D_m^-1
    new_means = now[:, 0] + np.einsum("nij,nj->ni", F, _f64(means) - rest[:, 0])
    sigma = F @ covariances(_f64(quats), _f64(scales)) @ np.swapaxes(F, -1, -2)
    new_quats, new_scales = covariance_to_gaussian(sigma)
    return new_means, new_quats, new_scales
