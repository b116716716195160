"""Fused per-point kernel of ``planar_pinhole``'s final passes (numba).

After the rounds on a spread subset, every track gets its rest coordinates and its heights'
point basis from the subset's poses and frame coefficients: per point, ``FINAL_PASSES`` times,
the Cauchy weights of its reprojection errors, the 2 x 2 (K x K) normal equations of its
heights' basis and of its rest coordinates.  Points are independent: written as NumPy over
(F, P) arrays that was ~15 passes over memory per pass (0.7 s of a 60-frame, 10k-track
refinement); here one loop per point over its frames.  Serial, as ``_admm``: numba's default
threading layer forbids concurrent calls from several threads of one node process.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def final_passes(rays: np.ndarray, w0: np.ndarray, R: np.ndarray, T: np.ndarray,
                 C: np.ndarray, rest: np.ndarray, h: np.ndarray, robust: float, passes: int,
                 ridge_rel: float) -> tuple[np.ndarray, np.ndarray]:
    """Per point p of rays (P, F, 3) and weights w0 (P, F), poses R (F, 3, 3), T (F, 3) and
    frame coefficients C (F, K) fixed: ``passes`` times the weights (Cauchy at ``robust`` from
    the second pass on; 0: w0), the height basis B_p = argmin of the algebraic error with
    h_fp = C_f . B_p (ridge ``ridge_rel`` x the visibility-weighted mean height curvature of
    the first pass, as ``planar_pinhole._solve_B``) and the rest coordinates (a 2 x 2 system,
    kept where singular, as ``planar_pinhole._solve_rest``).  Returns rest (P, 2), h (P, F)."""
    P, F, _ = rays.shape
    K = C.shape[1]
    rest = rest.copy()
    h = h.copy()
    e1e2 = np.empty(F)
    for f in range(F):
        e1e2[f] = R[f, 0, 0] * R[f, 0, 1] + R[f, 1, 0] * R[f, 1, 1] + R[f, 2, 0] * R[f, 2, 1]
    # the ridge from the first pass's terms over every point (the NumPy version's per pass)
    num = 0.0
    den = 0.0
    for p in range(P):
        for f in range(F):
            m0, m1, m2 = rays[p, f, 0], rays[p, f, 1], rays[p, f, 2]
            mm = m0 * m0 + m1 * m1 + m2 * m2
            mn = m0 * R[f, 0, 2] + m1 * R[f, 1, 2] + m2 * R[f, 2, 2]
            num += (mm - mn * mn) * w0[p, f]
            den += w0[p, f]
    ridge = ridge_rel * num / max(den, 1.0)
    w = np.empty(F)
    gg = np.empty(F)
    ga = np.empty(F)
    M = np.empty((K, K))
    b = np.empty(K)
    for p in range(P):
        x, y = rest[p, 0], rest[p, 1]
        for k in range(passes):
            for f in range(F):
                w[f] = w0[p, f]
                if robust > 0 and k > 0 and w[f] > 0:
                    X0 = R[f, 0, 0] * x + R[f, 0, 1] * y + R[f, 0, 2] * h[p, f] + T[f, 0]
                    X1 = R[f, 1, 0] * x + R[f, 1, 1] * y + R[f, 1, 2] * h[p, f] + T[f, 1]
                    X2 = R[f, 2, 0] * x + R[f, 2, 1] * y + R[f, 2, 2] * h[p, f] + T[f, 2]
                    z = max(X2, 1e-6)
                    du = X0 / z - rays[p, f, 0]
                    dv = X1 / z - rays[p, f, 1]
                    e2 = (du * du + dv * dv) / (robust * robust)
                    w[f] = w[f] / (1.0 + e2)
            # the heights' terms: |m x (A + h n)|^2 = gg h^2 + 2 ga h + const
            for f in range(F):
                m0, m1, m2 = rays[p, f, 0], rays[p, f, 1], rays[p, f, 2]
                a0 = R[f, 0, 0] * x + R[f, 0, 1] * y + T[f, 0]
                a1 = R[f, 1, 0] * x + R[f, 1, 1] * y + T[f, 1]
                a2 = R[f, 2, 0] * x + R[f, 2, 1] * y + T[f, 2]
                mm = m0 * m0 + m1 * m1 + m2 * m2
                mn = m0 * R[f, 0, 2] + m1 * R[f, 1, 2] + m2 * R[f, 2, 2]
                an = a0 * R[f, 0, 2] + a1 * R[f, 1, 2] + a2 * R[f, 2, 2]
                ma = m0 * a0 + m1 * a1 + m2 * a2
                gg[f] = (mm - mn * mn) * w[f]
                ga[f] = (mm * an - mn * ma) * w[f]
            for i in range(K):
                b[i] = 0.0
                for j in range(K):
                    M[i, j] = ridge if i == j else 0.0
            for f in range(F):
                for i in range(K):
                    b[i] -= ga[f] * C[f, i]
                    for j in range(K):
                        M[i, j] += gg[f] * C[f, i] * C[f, j]
            _solve_in_place(M, b)
            for f in range(F):
                hf = 0.0
                for i in range(K):
                    hf += C[f, i] * b[i]
                h[p, f] = hf
            # the rest coordinates: a 2 x 2 system
            a11 = a22 = a12 = b1 = b2 = 0.0
            for f in range(F):
                m0, m1, m2 = rays[p, f, 0], rays[p, f, 1], rays[p, f, 2]
                c0 = h[p, f] * R[f, 0, 2] + T[f, 0]
                c1 = h[p, f] * R[f, 1, 2] + T[f, 1]
                c2 = h[p, f] * R[f, 2, 2] + T[f, 2]
                mm = m0 * m0 + m1 * m1 + m2 * m2
                me1 = m0 * R[f, 0, 0] + m1 * R[f, 1, 0] + m2 * R[f, 2, 0]
                me2 = m0 * R[f, 0, 1] + m1 * R[f, 1, 1] + m2 * R[f, 2, 1]
                mc = m0 * c0 + m1 * c1 + m2 * c2
                ec1 = R[f, 0, 0] * c0 + R[f, 1, 0] * c1 + R[f, 2, 0] * c2
                ec2 = R[f, 0, 1] * c0 + R[f, 1, 1] * c1 + R[f, 2, 1] * c2
                wf = w[f]
                a11 += wf * (mm - me1 * me1)
                a22 += wf * (mm - me2 * me2)
                a12 += wf * (mm * e1e2[f] - me1 * me2)
                b1 -= wf * (mm * ec1 - me1 * mc)
                b2 -= wf * (mm * ec2 - me2 * mc)
            det = a11 * a22 - a12 * a12
            if det > 1e-12 * max(a11 * a22, 1e-300):
                x = (a22 * b1 - a12 * b2) / det
                y = (a11 * b2 - a12 * b1) / det
        rest[p, 0] = x
        rest[p, 1] = y
    return rest, h


@njit(cache=True, nogil=True)
def _solve_in_place(M: np.ndarray, b: np.ndarray) -> None:
    """b <- M^-1 b for a small K x K system (M overwritten): Gaussian elimination with
    partial pivoting, LAPACK's gesv without its calls' allocations (numba's np.linalg.solve
    copies both and calls LAPACK: ~2 us a point and pass, most of the final passes at K = 2).
    A singular M gives non-finite b, as its zero pivot."""
    K = b.shape[0]
    for c in range(K):
        piv = c
        for r in range(c + 1, K):
            if abs(M[r, c]) > abs(M[piv, c]):
                piv = r
        if piv != c:
            for j in range(K):
                M[c, j], M[piv, j] = M[piv, j], M[c, j]
            b[c], b[piv] = b[piv], b[c]
        for r in range(c + 1, K):
            f = M[r, c] / M[c, c]
            for j in range(c, K):
                M[r, j] -= f * M[c, j]
            b[r] -= f * b[c]
    for c in range(K - 1, -1, -1):
        acc = b[c]
        for j in range(c + 1, K):
            acc -= M[c, j] * b[j]
        b[c] = acc / M[c, c]
