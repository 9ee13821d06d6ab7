"""Bundle adjustment: robust (Huber) reprojection error minimised by Levenberg-Marquardt.

Poses are world-to-camera (R, t) with x_cam = R X + t, updated as R <- exp(dw) R, t <- t + dt;
the focal length (fx = fy) is updated in log space when asked. Each iteration eliminates the
points with the Schur complement: for every point p with damped block V_p,
    S = H_cc - sum_p M_p V_p^-1 M_p^T = H_cc - Z^T Z,   Z_p = (M_p chol(V_p^-1))^T,
so the reduced camera system is one dense product, independent of track length.
Everything is float64 torch on `device` (the per-observation algebra is a few scatter-adds; the
reduced product Z^T Z is what grows with the keyframes, and is what a GPU takes over); numpy at
the boundary. `refine_poses` is the pose-only version for many frames at once (points fixed),
used to register the frames between keyframes.
Observations are in pixels with +0.5 centres, like K.
"""

from __future__ import annotations

import numpy as np
import torch


def pick_device(device=None) -> torch.device:
    """The device for the heavy algebra: `device` if given, else CUDA when torch sees it."""
    if device is not None:
        return torch.device(device)
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def skew(v: torch.Tensor) -> torch.Tensor:
    """[N,3] -> [N,3,3] cross-product matrices."""
    z = torch.zeros_like(v[:, 0])
    return torch.stack([z, -v[:, 2], v[:, 1], v[:, 2], z, -v[:, 0], -v[:, 1], v[:, 0], z], 1).reshape(-1, 3, 3)


def so3_exp(w: torch.Tensor) -> torch.Tensor:
    """Rodrigues: axis-angle [N,3] -> rotation [N,3,3]."""
    th = torch.linalg.norm(w, dim=1)[:, None, None]
    small = th < 1e-8
    safe = torch.where(small, torch.ones_like(th), th)
    a = torch.where(small, torch.ones_like(th), torch.sin(safe) / safe)
    b = torch.where(small, torch.full_like(th, 0.5), (1 - torch.cos(safe)) / (safe * safe))
    S = skew(w)
    return torch.eye(3, dtype=w.dtype, device=w.device) + a * S + b * (S @ S)


def reprojection_errors(R, t, X, K, cam_idx, pt_idx, obs) -> np.ndarray:
    """Pixel error per observation [N]; points behind a camera get inf.

    R [C,3,3], t [C,3] world-to-camera; X [P,3]; K [3,3]; cam_idx, pt_idx [N]; obs [N,2].
    Computed ERROR_RUN observations at a time: a whole clip's (~1,500 a frame) made ~200 bytes of
    temporaries each.
    """
    err = np.empty(len(obs))
    for a in range(0, len(obs), ERROR_RUN):
        ci, pi = cam_idx[a:a + ERROR_RUN], pt_idx[a:a + ERROR_RUN]
        Xc = np.einsum("nij,nj->ni", R[ci], X[pi]) + t[ci]
        z = Xc[:, 2]
        uv = (K[:2, :2] @ (Xc[:, :2] / np.where(z > 1e-9, z, 1.0)[:, None]).T).T + K[:2, 2]
        e = np.linalg.norm(uv - obs[a:a + ERROR_RUN], axis=1)
        e[z <= 1e-9] = np.inf
        err[a:a + ERROR_RUN] = e
    return err


ERROR_RUN = 1 << 16


def _huber(n: torch.Tensor, delta: float) -> torch.Tensor:
    """Huber cost per residual norm [N] (non-finite counts as 1e6 px)."""
    e = torch.where(torch.isfinite(n), n, torch.full_like(n, 1e6))
    return torch.where(e <= delta, 0.5 * e * e, delta * (e - 0.5 * delta))


def _project(Rc, tc, Xp, f, c, obs):
    """Camera points [N,3] and residuals [N,2] (pixels) of points Xp [N,3] in cameras (Rc [N,3,3], tc [N,3])."""
    Xc = torch.einsum("nij,nj->ni", Rc, Xp) + tc
    return Xc, f * Xc[:, :2] / Xc[:, 2:3].clamp_min(1e-6) + c - obs


def _jacobians(Xc, tc, r, obs, c, f, delta):
    """Per observation: d(residual)/d(point in camera) du [N,2,3], the rotation block Jw [N,2,3],
    and the IRLS weight sqrt(w) [N,1] of the Huber loss."""
    z = Xc[:, 2].clamp_min(1e-6)
    du = torch.zeros(len(Xc), 2, 3, dtype=Xc.dtype, device=Xc.device)
    du[:, 0, 0] = du[:, 1, 1] = f / z
    du[:, 0, 2] = -f * Xc[:, 0] / z ** 2
    du[:, 1, 2] = -f * Xc[:, 1] / z ** 2
    Jw = -du @ skew(Xc - tc)
    n = torch.linalg.norm(r, dim=1)
    sw = torch.sqrt(torch.where(n <= delta, torch.ones_like(n), delta / n.clamp_min(1e-12)))[:, None]
    return du, Jw, sw


def _reduced_solve(H: torch.Tensor, Z: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Solve (H - Z^T Z) x = b (the tracker runs it on the CPU in one thread: tomgs.runtime.one_cpu_thread)."""
    return torch.linalg.solve(H - Z.T @ Z, b)


BA_RUN = 1 << 15  # observations whose Jacobians are built at once (~2 kB each; a 1800-frame clip's keyframes: 0.5 GB)


def bundle_adjust(R0: np.ndarray, t0: np.ndarray, X0: np.ndarray, K: np.ndarray,
                  cam_idx: np.ndarray, pt_idx: np.ndarray, obs: np.ndarray,
                  free_cams: np.ndarray, opt_focal: bool = False, fix_translation: bool = False,
                  iters: int = 20, delta: float = 1.0, focal_bounds=(0.0, np.inf), device=None, tick=None):
    """Refine poses of free cameras, all points, and optionally the focal length.

    R0 [C,3,3], t0 [C,3]: world-to-camera; X0 [P,3]; K [3,3]; cam_idx, pt_idx int [N]; obs [N,2]
    pixels; free_cams bool [C]. fix_translation keeps t (rotation-only cameras). The focal stays
    inside focal_bounds (a tiny focal is a degenerate way to shrink every error). device: where
    the algebra runs (pick_device's default); tick: called after each iteration (a heartbeat).
    The normal equations are summed BA_RUN observations at a time, in order (the same sums as in
    one piece); what is kept per observation is its indices and its camera-point block W (~250 B).
    Returns numpy (R [C,3,3], t [C,3], X [P,3], K [3,3]).
    """
    K = K.copy()
    N, P = len(obs), len(X0)
    if N == 0:
        return R0.copy(), t0.copy(), X0.copy(), K
    dev = pick_device(device)
    T = lambda a, dt=torch.float64: torch.as_tensor(np.ascontiguousarray(a), dtype=dt, device=dev)
    R, t, X = T(R0), T(t0), T(X0)
    ci, pi, obs_t = T(cam_idx, torch.int64), T(pt_idx, torch.int64), T(obs)
    cb = 3 if fix_translation else 6
    fc = np.flatnonzero(free_cams)
    slot = np.full(len(R0), -1)
    slot[fc] = np.arange(len(fc))
    nC = len(fc) * cb
    fcol, trash = nC, nC + 1  # focal column, then a bin for the columns of fixed cameras
    D = nC + 1 + cb
    s = slot[cam_idx]
    cols = np.where(s[:, None] >= 0, s[:, None] * cb + np.arange(cb), trash + np.arange(cb))
    cols = T(np.concatenate([cols, np.full((N, 1), fcol)], 1), torch.int64)  # [N, cb + 1]
    keep = T(np.r_[np.arange(nC), [fcol] if opt_focal else []], torch.int64)
    runs = [slice(a, min(a + BA_RUN, N)) for a in range(0, N, BA_RUN)]
    three, nine = torch.arange(3, device=dev), torch.arange(9, device=dev)
    fct = T(fc, torch.int64)
    c = T(K[:2, 2])
    eye3 = torch.eye(3, dtype=torch.float64, device=dev)
    eyeD = torch.eye(D, dtype=torch.float64, device=dev)

    def zeros(n):
        return torch.zeros(n, dtype=torch.float64, device=dev)

    def cost_of(R, t, X, f):
        e = torch.empty(N, dtype=torch.float64, device=dev)  # each observation's, then one sum as before
        for r in runs:
            e[r] = _huber(torch.linalg.norm(_project(R[ci[r]], t[ci[r]], X[pi[r]], f, c, obs_t[r])[1], dim=1), delta)
        return float(e.sum())

    f = float(K[0, 0])
    cost = cost_of(R, t, X, f)
    lam = 1e-3
    W = torch.empty(N, cb + 1, 3, dtype=torch.float64, device=dev)  # per observation: A^T B
    for _ in range(iters):
        H, g, V, gp = zeros(D * D), zeros(D), zeros(9 * P), zeros(3 * P)
        for r in runs:
            cr, pr, o = ci[r], pi[r], obs_t[r]
            Xc, res = _project(R[cr], t[cr], X[pr], f, c, o)
            du, Jw, sw = _jacobians(Xc, t[cr], res, o, c, f, delta)
            A = torch.cat([Jw] + ([] if fix_translation else [du]) + [(res + o - c)[:, :, None]], 2) * sw[:, :, None]
            B = (du @ R[cr]) * sw[:, :, None]
            rw = res * sw
            cl = cols[r]
            H.index_add_(0, (cl[:, :, None] * D + cl[:, None, :]).reshape(-1), (A.transpose(1, 2) @ A).reshape(-1))
            g.index_add_(0, cl.reshape(-1), torch.einsum("nki,nk->ni", A, rw).reshape(-1))
            V.index_add_(0, (pr[:, None] * 9 + nine).reshape(-1), (B.transpose(1, 2) @ B).reshape(-1))
            gp.index_add_(0, (pr[:, None] * 3 + three).reshape(-1), torch.einsum("nki,nk->ni", B, rw).reshape(-1))
            W[r] = A.transpose(1, 2) @ B  # [n, cb+1, 3]
        H, V, gp = H.reshape(D, D), V.reshape(P, 3, 3), gp.reshape(P, 3)
        while True:
            Hd = H + lam * torch.diag(torch.diag(H)) + 1e-9 * eyeD
            Vd = V + lam * V * eye3 + 1e-9 * eye3
            Vinv = torch.linalg.inv(Vd)
            L = torch.linalg.cholesky(0.5 * (Vinv + Vinv.transpose(1, 2)))
            Vg = torch.einsum("pij,pj->pi", Vinv, gp)
            Z, WVg = zeros(3 * P * D), zeros(D)
            for r in runs:
                pr, cl = pi[r], cols[r]
                zidx = ((3 * pr[:, None, None] + three[None, None, :]) * D + cl[:, :, None]).reshape(-1)
                Z.index_add_(0, zidx, (W[r] @ L[pr]).reshape(-1))
                WVg.index_add_(0, cl.reshape(-1), torch.einsum("nij,nj->ni", W[r], Vg[pr]).reshape(-1))
            Z = Z.reshape(3 * P, D)
            rhs = g - WVg
            dc = torch.zeros(D, dtype=torch.float64, device=dev)
            if len(keep):
                dc[keep] = _reduced_solve(Hd[keep][:, keep], Z[:, keep], -rhs[keep])
            back = zeros(3 * P)
            for r in runs:
                back.index_add_(0, (pi[r][:, None] * 3 + three).reshape(-1),
                                torch.einsum("nij,ni->nj", W[r], dc[cols[r]]).reshape(-1))
            back = back.reshape(P, 3)
            dX = -torch.einsum("pij,pj->pi", Vinv, gp + back)
            dcam = dc[:nC].reshape(-1, cb)
            R1, t1 = R.clone(), t.clone()
            R1[fct] = so3_exp(dcam[:, :3]) @ R[fct]
            if not fix_translation:
                t1[fct] = t[fct] + dcam[:, 3:]
            f1 = float(np.clip(f * np.exp(float(dc[fcol])), *focal_bounds)) if opt_focal else f
            X1 = X + dX
            new = cost_of(R1, t1, X1, f1)
            if new < cost:
                R, t, X, f = R1, t1, X1, f1
                improved = (cost - new) / max(cost, 1e-12)
                cost, lam = new, max(lam / 3, 1e-7)
                break
            lam *= 10
            if lam > 1e8:
                improved = 0.0
                break
        if tick is not None:
            tick()
        if improved < 1e-5:
            break
    K[0, 0] = K[1, 1] = f
    return R.cpu().numpy(), t.cpu().numpy(), X.cpu().numpy(), K


def refine_poses(R0: np.ndarray, t0: np.ndarray, X: np.ndarray, K: np.ndarray, cam_idx: np.ndarray,
                 obs: np.ndarray, fix_translation: bool = False, iters: int = 10, delta: float = 1.0, device=None):
    """Pose-only Levenberg-Marquardt for many cameras at once, points fixed: each camera solves
    its own 6x6 (3x3 with fix_translation) damped system, all in one batch.

    R0 [C,3,3], t0 [C,3] world-to-camera starting poses; X [N,3] the point of each observation;
    K [3,3]; cam_idx int [N]; obs [N,2] pixels. A camera's step is kept only where it lowers that
    camera's Huber cost. Returns numpy (R [C,3,3], t [C,3], error per observation [N] in pixels).
    """
    dev = pick_device(device)
    T = lambda a, dt=torch.float64: torch.as_tensor(np.ascontiguousarray(a), dtype=dt, device=dev)
    R, t, Xo, ci, obs_t = T(R0), T(t0), T(X), T(cam_idx, torch.int64), T(obs)
    C, cb = len(R0), 3 if fix_translation else 6
    f, c = float(K[0, 0]), T(K[:2, 2])

    def costs(R, t):
        _, r = _project(R[ci], t[ci], Xo, f, c, obs_t)
        return torch.zeros(C, dtype=torch.float64, device=dev).index_add_(0, ci, _huber(torch.linalg.norm(r, dim=1),
                                                                                          delta))

    cost = costs(R, t)
    lam = torch.full((C,), 1e-3, dtype=torch.float64, device=dev)
    eye = torch.eye(cb, dtype=torch.float64, device=dev)
    for _ in range(iters):
        Xc, r = _project(R[ci], t[ci], Xo, f, c, obs_t)
        du, Jw, sw = _jacobians(Xc, t[ci], r, obs_t, c, f, delta)
        J = (Jw if fix_translation else torch.cat([Jw, du], 2)) * sw[:, :, None]  # [N,2,cb]
        H = torch.zeros(C, cb, cb, dtype=torch.float64, device=dev).index_add_(0, ci, J.transpose(1, 2) @ J)
        g = torch.zeros(C, cb, dtype=torch.float64, device=dev).index_add_(0, ci, torch.einsum("nki,nk->ni", J,
                                                                                              r * sw))
        Hd = H + lam[:, None, None] * (H * eye) + 1e-9 * eye
        step = -torch.linalg.solve(Hd, g)
        R1 = so3_exp(step[:, :3]) @ R
        t1 = t if fix_translation else t + step[:, 3:]
        new = costs(R1, t1)
        better = new < cost
        R = torch.where(better[:, None, None], R1, R)
        t = torch.where(better[:, None], t1, t)
        cost = torch.where(better, new, cost)
        lam = torch.where(better, (lam / 3).clamp_min(1e-7), lam * 10)
    _, r = _project(R[ci], t[ci], Xo, f, c, obs_t)
    err = torch.linalg.norm(r, dim=1)
    Xc_z = (torch.einsum("nij,nj->ni", R[ci], Xo) + t[ci])[:, 2]
    err = torch.where(Xc_z > 1e-9, err, torch.full_like(err, float("inf")))
    return R.cpu().numpy(), t.cpu().numpy(), err.cpu().numpy()
