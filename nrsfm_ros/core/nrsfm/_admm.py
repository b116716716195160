"""Fused kernels of the nuclear-norm ADMM of ``bmm.bmm_shapes`` (numba).

The ADMM's data step and its dual update are element-wise over the (F, 3, P) shape arrays:
written as NumPy expressions they take ~20 passes over memory per iteration (memory-bound,
~25 ms at F = 60, P = 8k); fused they take two, and the iteration is dominated by the singular
value thresholding's two BLAS products.  Measured on a 320x240 face's batch (60 frames, 8k
tracks, 100 iterations): 2.5 s -> 1.2 s per ``bmm_shapes`` call, shapes equal to 4e-12.
Written over one-dimensional rows so that LLVM vectorises the point loop (over the 3-d
indices it did not: float64 data step 3.8 -> 1.8 ms at F = 80, P = 7.9k; float32 0.8 ms), and
with numpy's error model (no division-by-zero branch in the loop).
Serial on purpose: numba's parallel loops were slower here (1.6 s) and its default threading
layer forbids concurrent calls from several threads of one node process.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, error_model='numpy')
def data_step(Z: np.ndarray, U: np.ndarray, RtW: np.ndarray, E: np.ndarray, ev: np.ndarray,
              V: np.ndarray, rho: float, rho_den: float, inv: float, S: np.ndarray,
              T: np.ndarray) -> None:
    """S = argmin of the data term + rho/2 |S - Z + U/rho|^2 per point and frame, in closed
    form through the eigenvectors E (F, 3, 3) and eigenvalues ev (F, 3) of R_f^T R_f:
    S_f = E diag(1 / (rho_den + ev V_fp)) E^T (rho Z - U + RtW); and T = S + U / rho (the
    thresholding's argument).  ``RtW`` carries any further linear term (the trajectory
    prior's rho Y - U2), ``rho_den`` its weight on the diagonal (rho or 2 rho); ``inv`` = 1 /
    rho.  The scalars come in the arrays' dtype (float32 or float64), so the loop stays in
    it."""
    F, _, P = Z.shape
    for f in range(F):
        e00, e01, e02 = E[f, 0, 0], E[f, 0, 1], E[f, 0, 2]
        e10, e11, e12 = E[f, 1, 0], E[f, 1, 1], E[f, 1, 2]
        e20, e21, e22 = E[f, 2, 0], E[f, 2, 1], E[f, 2, 2]
        l0, l1, l2 = ev[f, 0], ev[f, 1], ev[f, 2]
        # one-dimensional rows: LLVM vectorises the point loop over them, not over 3-d indices
        z0, z1, z2 = Z[f, 0], Z[f, 1], Z[f, 2]
        U0, U1, U2 = U[f, 0], U[f, 1], U[f, 2]
        w0, w1, w2 = RtW[f, 0], RtW[f, 1], RtW[f, 2]
        S0, S1, S2 = S[f, 0], S[f, 1], S[f, 2]
        T0, T1, T2 = T[f, 0], T[f, 1], T[f, 2]
        Vf = V[f]
        for p in range(P):
            u0, u1, u2 = U0[p], U1[p], U2[p]
            r0 = rho * z0[p] - u0 + w0[p]
            r1 = rho * z1[p] - u1 + w1[p]
            r2 = rho * z2[p] - u2 + w2[p]
            v = Vf[p]
            c0 = (e00 * r0 + e10 * r1 + e20 * r2) / (rho_den + l0 * v)
            c1 = (e01 * r0 + e11 * r1 + e21 * r2) / (rho_den + l1 * v)
            c2 = (e02 * r0 + e12 * r1 + e22 * r2) / (rho_den + l2 * v)
            s0 = e00 * c0 + e01 * c1 + e02 * c2
            s1 = e10 * c0 + e11 * c1 + e12 * c2
            s2 = e20 * c0 + e21 * c1 + e22 * c2
            S0[p] = s0
            S1[p] = s1
            S2[p] = s2
            T0[p] = s0 + u0 * inv
            T1[p] = s1 + u1 * inv
            T2[p] = s2 + u2 * inv


@njit(cache=True, nogil=True, fastmath={'reassoc', 'nsz'})
def dual_step(S: np.ndarray, Zn: np.ndarray, Z: np.ndarray, U: np.ndarray, rho: float
              ) -> tuple[float, float]:
    """U += rho (S - Zn) in place; returns the primal residual |S - Zn| and the dual one
    rho |Zn - Z|."""
    F, K, P = S.shape
    a = 0.0
    b = 0.0
    for f in range(F):
        for i in range(K):
            s, zn, z, u = S[f, i], Zn[f, i], Z[f, i], U[f, i]
            for p in range(P):
                d = s[p] - zn[p]
                a += d * d
                u[p] += rho * d
                g = zn[p] - z[p]
                b += g * g
    return np.sqrt(a), rho * np.sqrt(b)
