"""The per-frame ADMM of ``spva.ShapePrior`` as one numba loop (the per-frame latency).

Written as in-place NumPy an iteration was ~20 array operations and two sparse products over
(P, 3) and (E, 3) buffers (~1.7 ms at 9.6k tracks, 19k edges); here the grid's edges are walked
directly (row e of the incidence matrix D is +1 at ``ei[e]`` and -1 at ``ej[e]``) in three
passes a step: the points (with the previous step's dual update), the subspace projection
(BLAS), the edges (with the next step's D^T term): ~0.45 ms.  The operations are those of the
NumPy form in the same order, so the iterates agree to rounding (``test_core_spva.py``).
Serial and ``nogil`` as ``_admm``.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def spva_admm(X: np.ndarray, U: np.ndarray, U2: np.ndarray, base: np.ndarray,
              inv: np.ndarray, gain: np.ndarray, RR: np.ndarray, B: np.ndarray,
              ei: np.ndarray, ej: np.ndarray, keep: float, tv_lin: float, thresh: float,
              floor: float, shrink: bool, iterations: int, rho: float, rho_tv: float) -> None:
    """``iterations`` linearised ADMM steps (``spva.ShapePrior._admm``), in place on the shape
    X (P, 3) and the scaled duals U (P, 3) of its low-rank copy Z = X + U and U2 (E, 3) of the
    edge differences' copy Q = D X + U2 (zeros: a cold start).  ``base`` (P, 3) the data and
    prior terms, ``inv``, ``gain``
    (P,) the per-point inverse's terms, RR (3, 3) the camera's R2^T R2, B (K, 3P) the
    orthonormal subspace, ``keep`` the share of Z outside it kept; the TV split's linearisation
    ``tv_lin`` and, with ``shrink``, the group Huber shrinkage (threshold ``thresh``, at least
    ``floor``)."""
    P = X.shape[0]
    E = ei.shape[0]
    Z = X + U
    Zf = Z.reshape(3 * P)
    dv = np.zeros((P, 3))                        # Dt (D X - Q + U2) for the next step
    rhs = np.empty(3)
    for e in range(E):
        i, j = ei[e], ej[e]
        for c in range(3):                       # Q = D X + U2: D X - Q + U2 = D X - D X
            g = X[i, c] - X[j, c]
            g = g - (g + U2[e, c]) + U2[e, c]
            dv[i, c] += g
            dv[j, c] -= g
    for it in range(iterations):
        for p in range(P):
            if it > 0:                           # the last step's U += X - Z, fused here
                for c in range(3):
                    U[p, c] = U[p, c] + X[p, c] - Z[p, c]
            for c in range(3):
                r = (Z[p, c] - U[p, c]) * rho
                r += base[p, c]
                r -= dv[p, c] * rho_tv
                r += tv_lin * X[p, c]
                rhs[c] = r
            for c in range(3):                   # the per-point 3 x 3 inverse
                rr = rhs[0] * RR[0, c] + rhs[1] * RR[1, c] + rhs[2] * RR[2, c]
                x = rhs[c] * inv[p] + rr * gain[p]
                X[p, c] = x
                Z[p, c] = x + U[p, c]
        proj = np.dot(np.dot(B, Zf), B)          # subspace kept (BLAS), the rest shrunk
        for n in range(3 * P):
            Zf[n] = Zf[n] * keep + (1.0 - keep) * proj[n]
        dv[:] = 0.0
        for e in range(E):
            i, j = ei[e], ej[e]
            gx0, gx1, gx2 = X[i, 0] - X[j, 0], X[i, 1] - X[j, 1], X[i, 2] - X[j, 2]
            q0, q1, q2 = gx0 + U2[e, 0], gx1 + U2[e, 1], gx2 + U2[e, 2]
            if shrink:                           # group Huber: max(1 - t / |q|, eps / (eps + t))
                n2 = q0 * q0
                n2 += q1 * q1
                n2 += q2 * q2
                w = max(1.0 - thresh / max(np.sqrt(n2), 1e-300), floor)
                q0, q1, q2 = q0 * w, q1 * w, q2 * w
            u0, u1, u2 = U2[e, 0] + gx0 - q0, U2[e, 1] + gx1 - q1, U2[e, 2] + gx2 - q2
            U2[e, 0], U2[e, 1], U2[e, 2] = u0, u1, u2
            g0, g1, g2 = gx0 - q0 + u0, gx1 - q1 + u1, gx2 - q2 + u2   # the next step's
            dv[i, 0] += g0
            dv[i, 1] += g1
            dv[i, 2] += g2
            dv[j, 0] -= g0
            dv[j, 1] -= g1
            dv[j, 2] -= g2
    if iterations > 0:
        for p in range(P):
            for c in range(3):
                U[p, c] = U[p, c] + X[p, c] - Z[p, c]
