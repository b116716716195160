"""Factorisation NRSfM: Tomasi-Kanade rigid with metric upgrade, and a low-rank non-rigid
alternation (rank-K shape space, orthographic cameras) with visibility weights.

Notation (METHODS.md §1): W (2F, P) tracks, S_f (3, P) shape of frame f, R_f (2, 3) orthonormal
rows, W_f = s_f R_f S_f + t_f.  S# (F, 3P) stacks each frame's x, y, z rows; rank(S#) <= K.
"""
from __future__ import annotations

import time

import numpy as np

from .result import NRSfMResult, check_tracks


def impute_low_rank(W: np.ndarray, V: np.ndarray, rank: int, iterations: int = 20
                    ) -> np.ndarray:
    """Fill the entries of W with V < 0.5 by iterated rank-``rank`` SVD (hard impute)."""
    M = np.repeat(V >= 0.5, 2, axis=0)
    if M.all():
        return W
    X = W.copy()
    mean = (W * M).sum(axis=1, keepdims=True) / np.maximum(M.sum(axis=1, keepdims=True), 1)
    X[~M] = np.broadcast_to(mean, X.shape)[~M]
    for _ in range(iterations):
        mu = X.mean(axis=1, keepdims=True)
        L = _rank_project(X - mu, rank) + mu      # through the smaller Gram matrix
        X[~M] = L[~M]
    return X


def metric_upgrade(M_hat: np.ndarray) -> np.ndarray:
    """Corrective A (3x3) making each 2x3 block of M_hat A scaled-orthonormal (METHODS §1.1).

    Solves for Q = A A^T from  a Q a^T - b Q b^T = 0,  a Q b^T = 0  per frame and a mean-scale
    constraint, by linear least squares; Q is projected onto the PSD cone.
    """
    a, b = M_hat[0::2], M_hat[1::2]
    F = a.shape[0]

    def rows(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        # coefficients of the 6 unknowns (q11 q12 q13 q22 q23 q33) in x Q y^T
        return np.stack([x[:, 0] * y[:, 0], x[:, 0] * y[:, 1] + x[:, 1] * y[:, 0],
                         x[:, 0] * y[:, 2] + x[:, 2] * y[:, 0], x[:, 1] * y[:, 1],
                         x[:, 1] * y[:, 2] + x[:, 2] * y[:, 1], x[:, 2] * y[:, 2]], axis=1)

    aa, bb, ab = rows(a, a), rows(b, b), rows(a, b)
    A_sys = np.vstack([aa - bb, ab, np.sqrt(F) * (aa + bb).mean(axis=0, keepdims=True) / 2])
    rhs = np.zeros(A_sys.shape[0])
    rhs[-1] = np.sqrt(F)
    q = np.linalg.lstsq(A_sys, rhs, rcond=None)[0]
    Q = np.array([[q[0], q[1], q[2]], [q[1], q[3], q[4]], [q[2], q[4], q[5]]])
    lam, E = np.linalg.eigh(Q)
    lam = np.maximum(lam, 1e-9 * max(lam.max(), 1e-12))
    return E * np.sqrt(lam)


def scaled_orthonormal(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest s_f R_f for each 2x3 block M_f (F, 2, 3): polar decomposition, batched."""
    U, sig, Vt = np.linalg.svd(M, full_matrices=False)
    return U @ Vt, sig.mean(axis=1)


def complete_rotations(R2: np.ndarray) -> np.ndarray:
    """(F, 2, 3) orthonormal rows -> (F, 3, 3) rotations (third row = r1 x r2)."""
    return np.concatenate([R2, np.cross(R2[:, 0], R2[:, 1])[:, None]], axis=1)


def _centre(W: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    wsum = np.maximum(V.sum(axis=1), 1e-12)
    t = np.stack([(W[0::2] * V).sum(axis=1), (W[1::2] * V).sum(axis=1)], axis=1) / wsum[:, None]
    return W - t.reshape(-1, 1), t


def rigid(W: np.ndarray, V: np.ndarray | None = None) -> NRSfMResult:
    """Tomasi-Kanade: rank-3 factorisation + metric upgrade; one rigid shape for all frames."""
    t0 = time.perf_counter()
    W, V = check_tracks(W, V)
    F, P = V.shape
    # factorise the fully visible tracks when there are enough (imputing a track seen in few
    # frames gives garbage that corrupts the SVD); otherwise impute the missing entries
    full = V.min(axis=0) >= 0.5
    if full.sum() >= max(8, P // 5):
        Wsub = W[:, full]
    else:
        Wsub = impute_low_rank(W, V, 3)
    Wc_sub, t = _centre(Wsub, np.ones((F, Wsub.shape[1])))
    U, s, Vt = np.linalg.svd(Wc_sub, full_matrices=False)
    M_hat = U[:, :3] * np.sqrt(s[:3])
    A = metric_upgrade(M_hat)
    R2, scale = scaled_orthonormal((M_hat @ A).reshape(F, 2, 3))
    Wf = W.reshape(F, 2, P)
    # refine shape, cameras and translations jointly (exact for noise-free data)
    for _ in range(4):
        Wc = (Wf - t[:, :, None]).reshape(2 * F, P)
        S0 = _solve_rigid_shape(Wc, V, R2, scale)
        R2, scale = _procrustes_cameras(Wc, V, np.broadcast_to(S0, (F, 3, P)))
        pred = np.einsum('fki,ip->fkp', R2 * scale[:, None, None], S0)
        t = ((Wf - pred) * V[:, None, :]).sum(axis=2) / V.sum(axis=1)[:, None]
    Wc = (Wf - t[:, :, None]).reshape(2 * F, P)
    R = complete_rotations(R2)
    S = np.einsum('fij,jp->fpi', R, S0)
    res = _residual(Wc, V, R2, scale, np.broadcast_to(S0, (F, 3, P)))
    return NRSfMResult(S=S, R=R, scale=scale, t=t, method='rigid', rank=1, residual_px=res,
                       iterations=4, converged=True, seconds=time.perf_counter() - t0)


def _solve_rigid_shape(Wc: np.ndarray, V: np.ndarray, R2: np.ndarray, scale: np.ndarray
                       ) -> np.ndarray:
    sR = R2 * scale[:, None, None]  # F x 2 x 3
    # normal equations per point: sum_f v_fp (sR_f^T sR_f) S_p = sum_f v_fp sR_f^T w_fp
    G = np.einsum('fki,fkj->fij', sR, sR)
    # a small ridge keeps tracks seen in too few frames near the centroid instead of arbitrary
    ridge = 1e-9 * float(np.trace(G.mean(axis=0)))
    A = np.einsum('fp,fij->pij', V, G) + ridge * np.eye(3)
    Wf = Wc.reshape(-1, 2, Wc.shape[1])
    b = np.einsum('fp,fki,fkp->pi', V, sR, Wf)
    return np.linalg.solve(A, b[..., None])[..., 0].T


def _procrustes_cameras(Wc: np.ndarray, V: np.ndarray, S: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Per frame, s_f R_f for w_fp ~= s R S_fp: weighted least squares for the 2x3 motion block
    M_f, then its nearest scaled-orthonormal matrix (polar decomposition; exact on clean data)."""
    F = V.shape[0]
    Wf = Wc.reshape(F, 2, -1)
    SV = S * V[:, None, :]
    WSt = Wf @ SV.transpose(0, 2, 1)  # F x 2 x 3
    SSt = S @ SV.transpose(0, 2, 1) + 1e-12 * np.eye(3)
    M = np.linalg.solve(SSt, WSt.transpose(0, 2, 1)).transpose(0, 2, 1)
    R2, scale = scaled_orthonormal(M)
    return R2, scale


def _residual(Wc: np.ndarray, V: np.ndarray, R2: np.ndarray, scale: np.ndarray,
              S: np.ndarray) -> float:
    F = V.shape[0]
    pred = np.einsum('fki,fip->fkp', R2 * scale[:, None, None], S)
    d = np.linalg.norm(Wc.reshape(F, 2, -1) - pred, axis=1)
    return float((d * V).sum() / max(V.sum(), 1e-12))


def _rank_project(Ssharp: np.ndarray, rank: int) -> np.ndarray:
    """Best rank-K approximation of S# (F, 3P) through the smaller Gram matrix."""
    F, N = Ssharp.shape
    if F <= N:
        E = np.linalg.eigh(Ssharp @ Ssharp.T)[1][:, -rank:]
        return E @ (E.T @ Ssharp)
    E = np.linalg.eigh(Ssharp.T @ Ssharp)[1][:, -rank:]
    return (Ssharp @ E) @ E.T


def low_rank(W: np.ndarray, V: np.ndarray | None = None, rank: int = 3, iterations: int = 60,
             rho: float = 1e-2, rho_growth: float = 1.15, tol: float = 1e-7,
             init: NRSfMResult | None = None) -> NRSfMResult:
    """Low-rank NRSfM with metric upgrade: rigid initialisation, then alternation of
    (a) per-frame shapes closest to the data and to the rank-K shape space (closed form,
        visibility-weighted), (b) rank-K projection of S#, (c) orthographic cameras by
        Procrustes, and (d) translations.  The penalty rho grows each iteration, so the final
        shapes satisfy the rank constraint.  Linear in P per iteration.

    ``init`` warm-starts cameras and shapes (used by the sliding window).
    """
    t0 = time.perf_counter()
    W, V = check_tracks(W, V)
    F, P = V.shape
    if rank < 1:
        raise ValueError(f'rank: expected >= 1, got {rank}')
    rank = min(rank, F)
    if init is None:
        base = rigid(W, V)
        R2, scale, t = base.R[:, :2], base.scale, base.t
        Z = np.einsum('fji,fpj->fip', base.R, base.S)  # object-frame shapes F x 3 x P
    else:
        R2, scale, t = init.R[:, :2].copy(), init.scale.copy(), init.t.copy()
        Z = np.einsum('fji,fpj->fip', init.R, init.S)
    # normalise image units so rho means the same at any resolution
    unit = max(float(np.sqrt(np.mean(((W.reshape(F, 2, P) - t[:, :, None]) ** 2)))), 1e-12)
    Wn = W / unit
    tn = t / unit
    Z = Z / unit
    Wf = Wn.reshape(F, 2, P)
    prev = np.inf
    it = 0
    converged = False
    for it in range(1, iterations + 1):
        Wc = Wf - tn[:, :, None]
        # (a) S_f = argmin sum_p v_fp ||w - sR S||^2 + rho ||S - Z||^2   (3x3 per point)
        sR = R2 * scale[:, None, None]
        G = np.einsum('fki,fkj->fij', sR, sR)  # F x 3 x 3, rank 2
        lam, E = np.linalg.eigh(G)  # per-frame eigenbasis
        rhs = (sR.transpose(0, 2, 1) @ Wc) * V[:, None, :] + rho * Z
        coef = (E.transpose(0, 2, 1) @ rhs) / (rho + lam[:, :, None] * V[:, None, :])
        S = E @ coef
        # (b) rank-K projection of S# (F x 3P)
        Z = _rank_project(S.reshape(F, 3 * P), rank).reshape(F, 3, P)
        # (c) cameras, (d) translations on the low-rank shapes
        R2, scale = _procrustes_cameras(Wc, V, Z)
        pred = (R2 * scale[:, None, None]) @ Z
        tn = ((Wf - pred) * V[:, None, :]).sum(axis=2) / np.maximum(V.sum(axis=1), 1e-12)[:, None]
        err = float(np.sum(V[:, None, :] * (Wf - tn[:, :, None] - pred) ** 2))
        rho *= rho_growth
        if abs(prev - err) <= tol * max(err, 1e-12) and it > 5:
            converged = True
            break
        prev = err
    S = Z * unit
    R = complete_rotations(R2)
    S_cam = np.einsum('fij,fjp->fpi', R, S)
    res = _residual((Wf - tn[:, :, None]).reshape(2 * F, P) * unit, V, R2, scale, S)
    return NRSfMResult(S=S_cam, R=R, scale=scale, t=tn * unit, method='lowrank', rank=rank,
                       residual_px=res, iterations=it, converged=converged,
                       seconds=time.perf_counter() - t0)
