"""Fused kernels of the nuclear-norm ADMM of ``bmm.bmm_shapes`` (numba).

The ADMM's data step and its dual update are element-wise over the (F, 3, P) shape arrays:
written as NumPy expressions they take ~20 passes over memory per iteration (memory-bound,
~25 ms at F = 60, P = 8k); fused they take two, and the iteration is dominated by the singular
value thresholding's two BLAS products.  Measured on a 320x240 face's batch (60 frames, 8k
tracks, 100 iterations): 2.5 s -> 1.2 s per ``bmm_shapes`` call, shapes equal to 4e-12.
Serial on purpose: numba's parallel loops were slower here (1.6 s) and its default threading
layer forbids concurrent calls from several threads of one node process.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def data_step(Z: np.ndarray, U: np.ndarray, RtW: np.ndarray, E: np.ndarray, ev: np.ndarray,
              V: np.ndarray, rho: float, rho_den: float, S: np.ndarray, T: np.ndarray
              ) -> None:
    """S = argmin of the data term + rho/2 |S - Z + U/rho|^2 per point and frame, in closed
    form through the eigenvectors E (F, 3, 3) and eigenvalues ev (F, 3) of R_f^T R_f:
    S_f = E diag(1 / (rho_den + ev V_fp)) E^T (rho Z - U + RtW); and T = S + U / rho (the
    thresholding's argument).  ``RtW`` carries any further linear term (the trajectory
    prior's rho Y - U2), ``rho_den`` its weight on the diagonal (rho or 2 rho)."""
    F, _, P = Z.shape
    inv = 1.0 / rho
    for f in range(F):
        e00, e01, e02 = E[f, 0, 0], E[f, 0, 1], E[f, 0, 2]
        e10, e11, e12 = E[f, 1, 0], E[f, 1, 1], E[f, 1, 2]
        e20, e21, e22 = E[f, 2, 0], E[f, 2, 1], E[f, 2, 2]
        l0, l1, l2 = ev[f, 0], ev[f, 1], ev[f, 2]
        for p in range(P):
            u0, u1, u2 = U[f, 0, p], U[f, 1, p], U[f, 2, p]
            r0 = rho * Z[f, 0, p] - u0 + RtW[f, 0, p]
            r1 = rho * Z[f, 1, p] - u1 + RtW[f, 1, p]
            r2 = rho * Z[f, 2, p] - u2 + RtW[f, 2, p]
            v = V[f, p]
            c0 = (e00 * r0 + e10 * r1 + e20 * r2) / (rho_den + l0 * v)
            c1 = (e01 * r0 + e11 * r1 + e21 * r2) / (rho_den + l1 * v)
            c2 = (e02 * r0 + e12 * r1 + e22 * r2) / (rho_den + l2 * v)
            s0 = e00 * c0 + e01 * c1 + e02 * c2
            s1 = e10 * c0 + e11 * c1 + e12 * c2
            s2 = e20 * c0 + e21 * c1 + e22 * c2
            S[f, 0, p] = s0
            S[f, 1, p] = s1
            S[f, 2, p] = s2
            T[f, 0, p] = s0 + u0 * inv
            T[f, 1, p] = s1 + u1 * inv
            T[f, 2, p] = s2 + u2 * inv


@njit(cache=True, nogil=True)
def dual_step(S: np.ndarray, Zn: np.ndarray, Z: np.ndarray, U: np.ndarray, rho: float
              ) -> tuple[float, float]:
    """U += rho (S - Zn) in place; returns the primal residual |S - Zn| and the dual one
    rho |Zn - Z|."""
    F, K, P = S.shape
    a = 0.0
    b = 0.0
    for f in range(F):
        for i in range(K):
            for p in range(P):
                d = S[f, i, p] - Zn[f, i, p]
                a += d * d
                U[f, i, p] += rho * d
                g = Zn[f, i, p] - Z[f, i, p]
                b += g * g
    return np.sqrt(a), rho * np.sqrt(b)
