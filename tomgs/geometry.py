"""Rotations, covariances and tetrahedra, for torch tensors and numpy arrays alike.

Quaternions are w x y z of any norm: a quaternion is divided by max(|q|, QUAT_EPS), so a zero one is
the identity (the renderer's rule: tomgs/kernels/project.py keeps its Warp copy). Every function
computes in the dtype it is given and returns a tensor for a tensor and a numpy array otherwise;
batch dimensions ([...]) pass through.
"""

from __future__ import annotations

import sys

import numpy as np

from tomgs.constants import QUAT_EPS


def _is_torch(x) -> bool:
    torch = sys.modules.get("torch")  # no tensor exists before torch is imported
    return torch is not None and isinstance(x, torch.Tensor)


def _swap(x):
    """x with its last two axes swapped (a batch of transposes)."""
    return x.transpose(-1, -2) if _is_torch(x) else np.swapaxes(x, -1, -2)


def quat_to_rotmat(quats):
    """Rotation matrices [...,3,3] of quaternions [...,4] (w x y z; any norm, zero -> identity)."""
    if _is_torch(quats):
        import torch

        q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(QUAT_EPS)
        w, x, y, z = q.unbind(-1)
        stack = torch.stack
    else:
        q = np.asarray(quats)
        q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), QUAT_EPS)
        w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
        stack = np.stack
    return stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(tuple(q.shape[:-1]) + (3, 3))


def rotmat_to_quat(R):
    """Rotation matrices [...,3,3] (det +1) -> unit quaternions [...,4] w x y z with w >= 0."""
    if _is_torch(R):
        import torch

        stack, where, sqrt, argmax = torch.stack, torch.where, torch.sqrt, torch.argmax
        take, floor = torch.take_along_dim, torch.clamp_min

        def unit(q):
            return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)

        def rows(best):  # [...] -> [...,1,4] index along the candidates
            return best[..., None, None].expand(*best.shape, 1, 4)
    else:
        R = np.asarray(R)
        stack, where, sqrt, argmax = np.stack, np.where, np.sqrt, np.argmax
        take, floor = np.take_along_axis, np.maximum

        def unit(q):
            return q / np.linalg.norm(q, axis=-1, keepdims=True)

        def rows(best):
            return best[..., None, None].repeat(4, -1)
    # Shepperd: build from the largest of the four squared components, so no division by ~0
    diag = stack([R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2], R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]], -1)
    t = stack([1 + diag[..., 0], 1 + 2 * diag[..., 1] - diag[..., 0], 1 + 2 * diag[..., 2] - diag[..., 0],
               1 + 2 * diag[..., 3] - diag[..., 0]], -1)  # 4 w^2, 4 x^2, 4 y^2, 4 z^2
    best = argmax(t, -1)
    s = sqrt(floor(take(t, best[..., None], -1)[..., 0], 1e-300))
    a, b, c = R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]
    d, e, f = R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1]
    candidates = stack([
        stack([s, a / s, b / s, c / s], -1),
        stack([a / s, s, d / s, e / s], -1),
        stack([b / s, d / s, s, f / s], -1),
        stack([c / s, e / s, f / s, s], -1),
    ], -2) / 2
    q = unit(take(candidates, rows(best), -2)[..., 0, :])
    return where(q[..., :1] < 0, -q, q)


def covariances(quats, scales):
    """Sigma = R S^2 R^T [...,3,3] of quaternions [...,4] and scales [...,3]."""
    M = quat_to_rotmat(quats) * scales[..., None, :]
    return M @ _swap(M)


def edge_matrices(vertices):
    """D [...,3,3] with columns x_1 - x_0, x_2 - x_0, x_3 - x_0 of tets [...,4,3]."""
    return _swap(vertices[..., 1:, :] - vertices[..., :1, :])


def signed_volumes(vertices, tets=None):
    """Signed volumes det(x_1 - x_0, x_2 - x_0, x_3 - x_0) / 6 (positive = correctly oriented) of
    tets [...,4,3], or, with `tets` [T,4] (indices), of those tets over vertices [...,V,3] -> [...,T]."""
    if tets is not None:
        vertices = vertices[..., tets, :]
    D = edge_matrices(vertices)
    return (D.det() if _is_torch(D) else np.linalg.det(D)) / 6.0


__all__ = ["quat_to_rotmat", "rotmat_to_quat", "covariances", "edge_matrices", "signed_volumes"]
