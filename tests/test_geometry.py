"""tomgs.geometry: quaternions <-> rotation matrices, covariances and tet volumes, torch and numpy."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tomgs.geometry import covariances, edge_matrices, quat_to_rotmat, rotmat_to_quat, signed_volumes


def random_quats(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, 4))


def by_hand(w: float, x: float, y: float, z: float) -> np.ndarray:
    """Rotation of a unit quaternion, from the textbook (w x y z)."""
    return np.array([[w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z]])


def test_quat_to_rotmat_numpy_torch_and_by_hand_agree():
    q = random_quats(500)
    R = quat_to_rotmat(q)
    assert R.shape == (500, 3, 3) and R.dtype == np.float64
    want = np.stack([by_hand(*(row / np.linalg.norm(row))) for row in q])
    np.testing.assert_allclose(R, want, atol=1e-14)
    np.testing.assert_allclose(quat_to_rotmat(torch.from_numpy(q)).numpy(), R, atol=1e-15)
    R32 = quat_to_rotmat(torch.from_numpy(q).float())
    assert R32.dtype == torch.float32
    np.testing.assert_allclose(R32.numpy(), R, atol=1e-6)
    # proper rotations, whatever the quaternion's norm; q and -q the same rotation
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    np.testing.assert_allclose(quat_to_rotmat(1e-6 * q), R, atol=1e-14)
    np.testing.assert_allclose(quat_to_rotmat(1e6 * q), R, atol=1e-14)
    np.testing.assert_array_equal(quat_to_rotmat(-q), R)


def test_zero_quaternion_is_the_identity_and_batches_pass_through():
    for q in (np.zeros(4), torch.zeros(4), torch.zeros(4, dtype=torch.float64)):
        R = quat_to_rotmat(q)
        assert tuple(R.shape) == (3, 3) and np.array_equal(np.asarray(R), np.eye(3))
    q = random_quats(24, seed=1).reshape(2, 3, 4, 4)
    R = quat_to_rotmat(q)
    assert R.shape == (2, 3, 4, 3, 3)
    np.testing.assert_array_equal(R.reshape(-1, 3, 3), quat_to_rotmat(q.reshape(-1, 4)))
    assert tuple(quat_to_rotmat(torch.from_numpy(q)).shape) == (2, 3, 4, 3, 3)


def test_rotmat_to_quat_round_trip_including_half_turns():
    q = random_quats(500, seed=2)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    # half turns (w = 0) and quarter turns about the axes: every branch of Shepperd's method
    special = [[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [1, 0, 0, 0], [math.sqrt(0.5), math.sqrt(0.5), 0, 0],
               [0, math.sqrt(0.5), math.sqrt(0.5), 0], [0, 0, math.sqrt(0.5), -math.sqrt(0.5)]]
    q = np.concatenate([q, np.array(special, dtype=np.float64)])
    R = quat_to_rotmat(q)
    back = rotmat_to_quat(R)
    assert (back[:, 0] >= 0).all()
    np.testing.assert_allclose(np.linalg.norm(back, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(quat_to_rotmat(back), R, atol=1e-14)
    np.testing.assert_allclose(np.abs((back * q).sum(1)), 1.0, atol=1e-12)  # the same rotation: back = +-q
    back_t = rotmat_to_quat(torch.from_numpy(R))
    assert isinstance(back_t, torch.Tensor) and back_t.dtype == torch.float64
    np.testing.assert_allclose(back_t.numpy(), back, atol=1e-15)
    assert rotmat_to_quat(np.eye(3)).tolist() == [1.0, 0.0, 0.0, 0.0]


def test_covariances_are_r_s2_rt():
    q, s = random_quats(200, seed=3), np.exp(np.random.default_rng(3).normal(size=(200, 3)))
    sigma = covariances(q, s)
    R = quat_to_rotmat(q)
    np.testing.assert_allclose(sigma, R @ (s[:, :, None] ** 2 * np.swapaxes(R, -1, -2)), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np.sort(np.linalg.eigvalsh(sigma), 1), np.sort(s**2, 1), rtol=1e-10)
    np.testing.assert_allclose(covariances(torch.from_numpy(q), torch.from_numpy(s)).numpy(), sigma, rtol=1e-12,
                               atol=1e-14)


def test_signed_volumes():
    unit = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    assert signed_volumes(unit[None]).tolist() == [pytest.approx(1 / 6)]
    assert signed_volumes(unit[None][:, [0, 2, 1, 3]]).tolist() == [pytest.approx(-1 / 6)]  # a swap flips it
    assert edge_matrices(unit[None])[0].tolist() == np.eye(3).tolist()
    rng = np.random.default_rng(4)
    x = rng.normal(size=(100, 4, 3))
    vol = signed_volumes(x)
    want = np.einsum("ij,ij->i", x[:, 1] - x[:, 0], np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0])) / 6
    np.testing.assert_allclose(vol, want, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(signed_volumes(torch.from_numpy(x)).numpy(), vol, rtol=1e-12, atol=1e-15)
    # indexed: tets [T,4] over vertices [V,3], or a sequence [F,V,3] -> [F,T]
    vertices = rng.normal(size=(3, 20, 3))
    tets = rng.integers(0, 20, size=(30, 4))
    got = signed_volumes(vertices, tets)
    assert got.shape == (3, 30)
    np.testing.assert_allclose(got[1], signed_volumes(vertices[1][tets]), rtol=1e-12, atol=1e-15)
    got_t = signed_volumes(torch.from_numpy(vertices), torch.from_numpy(tets))
    np.testing.assert_allclose(got_t.numpy(), got, rtol=1e-12, atol=1e-15)
    # an affine map scales every volume by its determinant
    F = rng.normal(size=(3, 3))
    np.testing.assert_allclose(signed_volumes(x @ F.T), vol * np.linalg.det(F), rtol=1e-9, atol=1e-12)
