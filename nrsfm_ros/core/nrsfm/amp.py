"""AMP: accelerated metric projections (METHODS §2; Paladini et al.'s Metric Projections).

Model W_f = R_f sum_k c_fk B_k (R_f orthonormal rows, B_k 3 x P basis shapes).  Alternation:
(1) motion M = W B^+ (least squares, one thin solve for all frames); (2) metric projection of
every 2 x 3K block M_f onto the set {[c_f1 R_f ... c_fK R_f]} -- batched over all frames at
once: for fixed R_f the coefficients are c_fk = <M_fk, R_f> / 2 in closed form, and for fixed
coefficients R_f is the polar factor of sum_k c_fk M_fk; a few inner rounds per outer iteration;
(3) basis B = M^+ W (weighted least squares per point with visibility).  Every frame's projection
is independent, so the result does not depend on frame order.  Initialised from the
prior-free cameras and shapes (``bmm``).  Cost per iteration O(F K P): linear in P.
"""
from __future__ import annotations

import time

import numpy as np

from .bmm import bmm, row_space
from .factorization import _centre, complete_rotations
from .result import NRSfMResult, check_tracks


def project_blocks(M: np.ndarray, R2: np.ndarray, rounds: int = 3
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Nearest [c_f1 R_f ... c_fK R_f] to M (F, 2, 3, K), batched: returns R2 (F, 2, 3) and
    c (F, K)."""
    c = np.einsum('fijk,fij->fk', M, R2) / 2
    for _ in range(rounds):
        A = np.einsum('fijk,fk->fij', M, c)
        U, _, Vt = np.linalg.svd(A, full_matrices=False)
        R2 = U @ Vt
        c = np.einsum('fijk,fij->fk', M, R2) / 2
    return R2, c


def amp(W: np.ndarray, V: np.ndarray | None = None, rank: int = 3, iterations: int = 30,
        tol: float = 1e-7, init: NRSfMResult | None = None, prox: float = 1e-3
        ) -> NRSfMResult:
    """Metric-projection NRSfM with ``rank`` K basis shapes (see the module docstring);
    ``prox``: weight of the proximal pull of each least-squares step towards the current
    iterate, relative to the mean diagonal of its normal equations (plus a 1e-9 floor, so the
    directions the data cannot see stay where they are)."""
    t0 = time.perf_counter()
    W, V = check_tracks(W, V)
    F, P = V.shape
    if not 1 <= rank <= min(F, P):
        raise ValueError(f'rank={rank}: expected 1..min(F, P)={min(F, P)}')
    if not prox >= 0:
        raise ValueError(f'prox: expected >= 0, got {prox}')
    Wc, t = _centre(W, V)
    base = init if init is not None else bmm(W, V)
    R2 = base.R[:, :2].copy()
    S_obj = np.einsum('fji,fpj->fip', base.R, base.S)              # (F, 3, P)
    Wfull, Vfull, basis = Wc, V, None
    if (V >= 0.5).all() and P > 2 * F:
        # all tracks visible: every step is linear in the columns of W with equal weights, so
        # the iterations run on the row space of W (r <= 2F "points"; see bmm.row_space)
        Wc, basis = row_space(Wc)
        S_obj = S_obj @ basis.T
        P = Wc.shape[1]
        V = np.ones((F, P))
    # initial basis and coefficients from the rank-K approximation of S#
    U, s, Vt = np.linalg.svd(S_obj.reshape(F, 3 * P), full_matrices=False)
    c = U[:, :rank] * s[:rank]                                       # (F, K)
    B = Vt[:rank].reshape(rank, 3, P)
    Wf = Wc.reshape(F, 2, P)
    prev, it, converged = np.inf, 0, False
    for it in range(1, iterations + 1):
        # (3) basis given cameras and coefficients: per point, (3K) weighted least squares
        Rk = np.einsum('fk,fij->fikj', c, R2).reshape(F, 2, 3 * rank)
        A = np.einsum('fp,fia,fib->pab', V, Rk, Rk)
        # proximal terms (weight ``prox`` x the mean diagonal) keep every least-squares step
        # regular and its unseen directions at their current values when the data's rank is
        # below 3K (exact low-rank W): without them those directions are arbitrary and the
        # alternation drifts away from its initialisation
        mu = ((prox + 1e-9) * np.trace(A, axis1=1, axis2=2) / (3 * rank) + 1e-300)[:, None]
        A += mu[:, :, None] * np.eye(3 * rank)
        b = np.einsum('fp,fia,fip->pa', V, Rk, Wf) + mu * B.transpose(2, 0, 1).reshape(P, -1)
        B = np.linalg.solve(A, b[..., None])[..., 0].reshape(P, rank, 3).transpose(1, 2, 0)
        # (1) motion given the basis: M_f = W_f B_f^+ over the visible points, all frames
        Bs = B.transpose(1, 0, 2).reshape(3 * rank, P)               # (3K, P) rows (i, k)
        BV = Bs[None] * V[:, None, :]                                 # (F, 3K, P)
        G = BV @ Bs.T
        mu = ((prox + 1e-9) * np.trace(G, axis1=1, axis2=2) / (3 * rank) + 1e-300)[:, None, None]
        G += mu * np.eye(3 * rank)
        Mcur = np.einsum('fk,fij->fjki', c, R2).reshape(F, 3 * rank, 2)       # rows (j, k)
        M = np.linalg.solve(G, BV @ Wf.transpose(0, 2, 1) + mu * Mcur).transpose(0, 2, 1)
        # (2) metric projection, batched over frames
        R2, c = project_blocks(M.reshape(F, 2, 3, rank), R2)
        pred = np.einsum('fij,fk,kjp->fip', R2, c, B)
        err = float((V[:, None, :] * (Wf - pred) ** 2).sum())
        if abs(prev - err) <= tol * max(err, 1e-300):
            converged = True
            break
        prev = err
    S_obj = np.einsum('fk,kjp->fjp', c, B)
    if basis is not None:
        S_obj = S_obj @ basis
    R = complete_rotations(R2)
    S_cam = np.einsum('fij,fjp->fpi', R, S_obj)
    d = np.linalg.norm(Wfull.reshape(F, 2, -1) - R2 @ S_obj, axis=1)
    return NRSfMResult(S=S_cam, R=R, scale=np.ones(F), t=t, method='amp', rank=rank,
                       residual_px=float((d * Vfull).sum() / max(Vfull.sum(), 1e-12)),
                       iterations=it,
                       converged=converged, seconds=time.perf_counter() - t0)
