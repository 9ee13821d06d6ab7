"""Bundle adjustment: robust (Huber) reprojection error minimised by Levenberg-Marquardt.

Poses are world-to-camera (R, t) with x_cam = R X + t, updated as R <- exp(dw) R, t <- t + dt;
the focal length (fx = fy) is updated in log space when asked. Each iteration eliminates the
points with the Schur complement: for every point p with damped block V_p,
    S = H_cc - sum_p M_p V_p^-1 M_p^T = H_cc - Z^T Z,   Z_p = (M_p chol(V_p^-1))^T,
so the reduced camera system is one dense BLAS product, independent of track length.
Everything is float64: numpy for the per-observation algebra (the Jacobians are a few lines, no
autograd needed), torch for the reduced dense solve.
Observations are in pixels with +0.5 centres, like K.
"""

from __future__ import annotations

import numpy as np


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues: axis-angle [N,3] -> rotation [N,3,3]."""
    th = np.linalg.norm(w, axis=1)[:, None, None]
    small = th < 1e-8
    a = np.where(small, 1.0, np.sin(th) / np.where(small, 1.0, th))
    b = np.where(small, 0.5, (1 - np.cos(th)) / np.where(small, 1.0, th * th))
    return np.eye(3) + a * skew(w) + b * (skew(w) @ skew(w))


def skew(v: np.ndarray) -> np.ndarray:
    """[N,3] -> [N,3,3] cross-product matrices."""
    z = np.zeros(len(v))
    return np.stack([z, -v[:, 2], v[:, 1], v[:, 2], z, -v[:, 0], -v[:, 1], v[:, 0], z], 1).reshape(-1, 3, 3)


def reprojection_errors(R, t, X, K, cam_idx, pt_idx, obs) -> np.ndarray:
    """Pixel error per observation [N]; points behind a camera get inf.

    R [C,3,3], t [C,3] world-to-camera; X [P,3]; K [3,3]; cam_idx, pt_idx [N]; obs [N,2].
    """
    Xc = np.einsum("nij,nj->ni", R[cam_idx], X[pt_idx]) + t[cam_idx]
    z = Xc[:, 2]
    uv = (K[:2, :2] @ (Xc[:, :2] / np.where(z > 1e-9, z, 1.0)[:, None]).T).T + K[:2, 2]
    err = np.linalg.norm(uv - obs, axis=1)
    err[z <= 1e-9] = np.inf
    return err


def _huber_cost(err: np.ndarray, delta: float) -> float:
    e = np.where(np.isfinite(err), err, 1e6)
    return float(np.where(e <= delta, 0.5 * e * e, delta * (e - 0.5 * delta)).sum())


def _reduced_solve(H: np.ndarray, Z: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve (H - Z^T Z) x = b. Done in torch on one thread: for these sizes (a few hundred
    unknowns) handing BLAS work to threads costs more than it saves on a busy 2-core machine."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        Zt = torch.from_numpy(np.ascontiguousarray(Z))
        S = torch.from_numpy(H) - Zt.T @ Zt
        return torch.linalg.solve(S, torch.from_numpy(b)).numpy()
    finally:
        torch.set_num_threads(threads)


def bundle_adjust(R0: np.ndarray, t0: np.ndarray, X0: np.ndarray, K: np.ndarray,
                  cam_idx: np.ndarray, pt_idx: np.ndarray, obs: np.ndarray,
                  free_cams: np.ndarray, opt_focal: bool = False, fix_translation: bool = False,
                  iters: int = 20, delta: float = 1.0, focal_bounds=(0.0, np.inf)):
    """Refine poses of free cameras, all points, and optionally the focal length.

    R0 [C,3,3], t0 [C,3]: world-to-camera; X0 [P,3]; K [3,3]; cam_idx, pt_idx int [N]; obs [N,2]
    pixels; free_cams bool [C]. fix_translation keeps t (rotation-only cameras). The focal stays
    inside focal_bounds (a tiny focal is a degenerate way to shrink every error).
    Returns (R [C,3,3], t [C,3], X [P,3], K [3,3]).
    """
    R, t, X, K = R0.copy(), t0.copy(), X0.copy(), K.copy()
    N, P = len(obs), len(X0)
    if N == 0:
        return R, t, X, K
    cb = 3 if fix_translation else 6
    fc = np.flatnonzero(free_cams)
    slot = np.full(len(R0), -1)
    slot[fc] = np.arange(len(fc))
    nC = len(fc) * cb
    fcol, trash = nC, nC + 1  # focal column, then a bin for the columns of fixed cameras
    D = nC + 1 + cb
    s = slot[cam_idx]
    cols = np.where(s[:, None] >= 0, s[:, None] * cb + np.arange(cb), trash + np.arange(cb))
    cols = np.concatenate([cols, np.full((N, 1), fcol)], 1)  # [N, cb + 1]
    keep = np.r_[np.arange(nC), [fcol] if opt_focal else []].astype(int)
    hidx = (cols[:, :, None] * D + cols[:, None, :]).ravel()
    zcol = np.repeat(cols[:, :, None], 3, 2)  # [N, cb+1, 3]
    zidx = ((3 * pt_idx[:, None, None] + np.arange(3)[None, None, :]) * D + zcol).ravel()
    c = K[:2, 2]

    def residuals(R, t, X, f):
        Xc = np.einsum("nij,nj->ni", R[cam_idx], X[pt_idx]) + t[cam_idx]
        return Xc, f * Xc[:, :2] / np.maximum(Xc[:, 2:3], 1e-6) + c - obs

    f = K[0, 0]
    cost = _huber_cost(np.linalg.norm(residuals(R, t, X, f)[1], axis=1), delta)
    lam = 1e-3
    for _ in range(iters):
        Xc, r = residuals(R, t, X, f)
        z = np.maximum(Xc[:, 2], 1e-6)
        n = np.linalg.norm(r, axis=1)
        sw = np.sqrt(np.where(n <= delta, 1.0, delta / np.maximum(n, 1e-12)))[:, None]  # IRLS
        du = np.zeros((N, 2, 3))
        du[:, 0, 0] = du[:, 1, 1] = f / z
        du[:, 0, 2] = -f * Xc[:, 0] / z ** 2
        du[:, 1, 2] = -f * Xc[:, 1] / z ** 2
        Jw = -du @ skew(Xc - t[cam_idx])
        A = np.concatenate([Jw] + ([] if fix_translation else [du]) + [(r + obs - c)[:, :, None]], 2)
        A *= sw[:, :, None]
        B = (du @ R[cam_idx]) * sw[:, :, None]
        rw = r * sw
        H = np.bincount(hidx, (A.transpose(0, 2, 1) @ A).ravel(), D * D).reshape(D, D)
        g = np.bincount(cols.ravel(), np.einsum("nki,nk->ni", A, rw).ravel(), D)
        V = np.stack([np.bincount(pt_idx, (B[:, :, i] * B[:, :, j]).sum(1), P)
                      for i in range(3) for j in range(3)], 1).reshape(P, 3, 3)
        gp = np.stack([np.bincount(pt_idx, (B[:, :, i] * rw).sum(1), P) for i in range(3)], 1)
        W = A.transpose(0, 2, 1) @ B  # [N, cb+1, 3]
        while True:
            Hd = H + lam * np.diag(np.diag(H)) + 1e-9 * np.eye(D)
            Vd = V + lam * V * np.eye(3) + 1e-9 * np.eye(3)
            Vinv = np.linalg.inv(Vd)
            L = np.linalg.cholesky(0.5 * (Vinv + Vinv.transpose(0, 2, 1)))
            Z = np.bincount(zidx, (W @ L[pt_idx]).ravel(), 3 * P * D).reshape(3 * P, D)
            Vg = np.einsum("pij,pj->pi", Vinv, gp)
            rhs = g - np.bincount(cols.ravel(), np.einsum("nij,nj->ni", W, Vg[pt_idx]).ravel(), D)
            dc = np.zeros(D)
            if len(keep):
                dc[keep] = _reduced_solve(Hd[np.ix_(keep, keep)], Z[:, keep], -rhs[keep])
            wdc = np.einsum("nij,ni->nj", W, dc[cols])
            back = np.stack([np.bincount(pt_idx, wdc[:, i], P) for i in range(3)], 1)
            dX = -np.einsum("pij,pj->pi", Vinv, gp + back)
            dcam = dc[:nC].reshape(-1, cb)
            R1, t1 = R.copy(), t.copy()
            R1[fc] = so3_exp(dcam[:, :3]) @ R[fc]
            if not fix_translation:
                t1[fc] = t[fc] + dcam[:, 3:]
            f1 = float(np.clip(f * np.exp(dc[fcol]), *focal_bounds)) if opt_focal else f
            X1 = X + dX
            new = _huber_cost(np.linalg.norm(residuals(R1, t1, X1, f1)[1], axis=1), delta)
            if new < cost:
                R, t, X, f = R1, t1, X1, f1
                improved = (cost - new) / max(cost, 1e-12)
                cost, lam = new, max(lam / 3, 1e-7)
                break
            lam *= 10
            if lam > 1e8:
                improved = 0.0
                break
        if improved < 1e-5:
            break
    K[0, 0] = K[1, 1] = f
    return R, t, X, K
