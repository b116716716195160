"""The passes of ``factorization.low_rank``'s iteration over every (frame, point) (numba).

``low_rank`` is the sliding window's solve (``StreamNRSfM`` mode ``window``, and the first
window of ``online``): 15 frames x ~10k tracks, 10 warm iterations a frame.  Its NumPy form
made ~40 passes over (F, 3, P) arrays an iteration: 141 ms of the window's ~170 ms a frame at
320x240.  Here the shapes' closed-form step is one pass, and the cameras' Procrustes fit,
the translations and the data error come from one pass of per-frame moments (the rank-K
projection between them stays two BLAS products).  ``fastmath``: the sums may be reordered
(vectorised), which moves results by rounding only (test_core_lowrank_kernels.py).  Serial
and ``nogil`` as the other kernels.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, fastmath=True)
def shape_step(Wf: np.ndarray, V: np.ndarray, tn: np.ndarray, sR: np.ndarray, E: np.ndarray,
               lam: np.ndarray, Z: np.ndarray, rho: float) -> np.ndarray:
    """Per frame and point, S = argmin v ||w - t - sR S||^2 + rho ||S - Z||^2 through the
    frame's eigenbasis E (F, 3, 3), lam (F, 3) of G = sR^T sR: Wf (F, 2, P), V (F, P),
    tn (F, 2), sR (F, 2, 3), Z (F, 3, P) -> S (F, 3, P)."""
    F, P = V.shape
    S = np.empty((F, 3, P))
    for f in range(F):
        a00, a01, a02 = sR[f, 0, 0], sR[f, 0, 1], sR[f, 0, 2]
        a10, a11, a12 = sR[f, 1, 0], sR[f, 1, 1], sR[f, 1, 2]
        e00, e01, e02 = E[f, 0, 0], E[f, 0, 1], E[f, 0, 2]
        e10, e11, e12 = E[f, 1, 0], E[f, 1, 1], E[f, 1, 2]
        e20, e21, e22 = E[f, 2, 0], E[f, 2, 1], E[f, 2, 2]
        l0, l1, l2 = lam[f, 0], lam[f, 1], lam[f, 2]
        t0, t1 = tn[f, 0], tn[f, 1]
        for p in range(P):
            v = V[f, p]
            u0 = Wf[f, 0, p] - t0
            u1 = Wf[f, 1, p] - t1
            r0 = (a00 * u0 + a10 * u1) * v + rho * Z[f, 0, p]
            r1 = (a01 * u0 + a11 * u1) * v + rho * Z[f, 1, p]
            r2 = (a02 * u0 + a12 * u1) * v + rho * Z[f, 2, p]
            c0 = (e00 * r0 + e10 * r1 + e20 * r2) / (rho + l0 * v)
            c1 = (e01 * r0 + e11 * r1 + e21 * r2) / (rho + l1 * v)
            c2 = (e02 * r0 + e12 * r1 + e22 * r2) / (rho + l2 * v)
            S[f, 0, p] = e00 * c0 + e01 * c1 + e02 * c2
            S[f, 1, p] = e10 * c0 + e11 * c1 + e12 * c2
            S[f, 2, p] = e20 * c0 + e21 * c1 + e22 * c2
    return S


@njit(cache=True, nogil=True, fastmath=True)
def frame_moments(Wf: np.ndarray, V: np.ndarray, tn: np.ndarray, Z: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                             np.ndarray]:
    """Visibility-weighted moments per frame of the centred tracks u = w - t (Wf (F, 2, P),
    tn (F, 2)) and the shapes Z (F, 3, P): sum v (F,), sum v u (F, 2), sum v |u|^2 (F,),
    sum v z (F, 3), sum v u z^T (F, 2, 3), sum v z z^T (F, 3, 3)."""
    F, P = V.shape
    n = np.zeros(F)
    su = np.zeros((F, 2))
    suu = np.zeros(F)
    sz = np.zeros((F, 3))
    suz = np.zeros((F, 2, 3))
    szz = np.zeros((F, 3, 3))
    for f in range(F):
        t0, t1 = tn[f, 0], tn[f, 1]
        a = b0 = b1 = c = d0 = d1 = d2 = 0.0
        g00 = g01 = g02 = g10 = g11 = g12 = 0.0
        h00 = h01 = h02 = h11 = h12 = h22 = 0.0
        for p in range(P):
            v = V[f, p]
            if v == 0.0:
                continue
            u0 = Wf[f, 0, p] - t0
            u1 = Wf[f, 1, p] - t1
            z0, z1, z2 = Z[f, 0, p], Z[f, 1, p], Z[f, 2, p]
            vu0, vu1 = v * u0, v * u1
            vz0, vz1, vz2 = v * z0, v * z1, v * z2
            a += v
            b0 += vu0
            b1 += vu1
            c += vu0 * u0 + vu1 * u1
            d0 += vz0
            d1 += vz1
            d2 += vz2
            g00 += vu0 * z0
            g01 += vu0 * z1
            g02 += vu0 * z2
            g10 += vu1 * z0
            g11 += vu1 * z1
            g12 += vu1 * z2
            h00 += vz0 * z0
            h01 += vz0 * z1
            h02 += vz0 * z2
            h11 += vz1 * z1
            h12 += vz1 * z2
            h22 += vz2 * z2
        n[f] = a
        su[f, 0], su[f, 1] = b0, b1
        suu[f] = c
        sz[f, 0], sz[f, 1], sz[f, 2] = d0, d1, d2
        suz[f, 0, 0], suz[f, 0, 1], suz[f, 0, 2] = g00, g01, g02
        suz[f, 1, 0], suz[f, 1, 1], suz[f, 1, 2] = g10, g11, g12
        szz[f, 0, 0], szz[f, 0, 1], szz[f, 0, 2] = h00, h01, h02
        szz[f, 1, 0], szz[f, 1, 1], szz[f, 1, 2] = h01, h11, h12
        szz[f, 2, 0], szz[f, 2, 1], szz[f, 2, 2] = h02, h12, h22
    return n, su, suu, sz, suz, szz


@njit(cache=True, nogil=True)
def mean_distance(Wf: np.ndarray, V: np.ndarray, tn: np.ndarray, sR: np.ndarray, Z: np.ndarray
                  ) -> float:
    """The visibility-weighted mean image distance |w - t - sR z| (``factorization._residual``)
    of Wf (F, 2, P), V (F, P), tn (F, 2), sR (F, 2, 3), Z (F, 3, P)."""
    F, P = V.shape
    num = 0.0
    den = 0.0
    for f in range(F):
        a00, a01, a02 = sR[f, 0, 0], sR[f, 0, 1], sR[f, 0, 2]
        a10, a11, a12 = sR[f, 1, 0], sR[f, 1, 1], sR[f, 1, 2]
        t0, t1 = tn[f, 0], tn[f, 1]
        for p in range(P):
            v = V[f, p]
            z0, z1, z2 = Z[f, 0, p], Z[f, 1, p], Z[f, 2, p]
            r0 = Wf[f, 0, p] - t0 - (a00 * z0 + a01 * z1 + a02 * z2)
            r1 = Wf[f, 1, p] - t1 - (a10 * z0 + a11 * z1 + a12 * z2)
            num += v * np.sqrt(r0 * r0 + r1 * r1)
            den += v
    return num / max(den, 1e-12)


@njit(cache=True, nogil=True)
def camera_update(n: np.ndarray, su: np.ndarray, suu: np.ndarray, sz: np.ndarray,
                  suz: np.ndarray, szz: np.ndarray, tn: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """From ``frame_moments``' sums: per frame the Procrustes camera (the affine fit's nearest
    scaled orthonormal rows: R2 (F, 2, 3), scale (F,)), the new translation (F, 2), the next
    shape step's eigenbasis E (F, 3, 3), lam (F, 3) of G = sR^T sR, and the data error
    sum v |u - sR z - (t_new - t)|^2 over every frame (u = w - t): the per-frame 3 x 3 algebra
    of an iteration in one call (~0.5 ms of NumPy calls an iteration at 15 frames)."""
    F = n.shape[0]
    R2 = np.empty((F, 2, 3))
    scale = np.empty(F)
    t_new = np.empty((F, 2))
    E = np.empty((F, 3, 3))
    lam = np.empty((F, 3))
    err = 0.0
    for f in range(F):
        C = szz[f].copy()
        ridge = 1e-12 * (C[0, 0] + C[1, 1] + C[2, 2]) + 1e-300
        for i in range(3):
            C[i, i] += ridge
        M = np.ascontiguousarray(np.linalg.solve(C, np.ascontiguousarray(suz[f].T)).T)
        U, sig, Vt = np.linalg.svd(M, full_matrices=False)
        R = U @ Vt
        s = 0.5 * (sig[0] + sig[1])
        R2[f] = R
        scale[f] = s
        sR = R * s
        a = su[f] - sR @ sz[f]
        nf = n[f]
        tf = (a + nf * tn[f]) / max(nf, 1e-12)
        t_new[f] = tf
        d = tf - tn[f]
        err += suu[f] - 2.0 * np.sum(sR * suz[f]) + np.sum((sR @ szz[f]) * sR) \
            - 2.0 * (d[0] * a[0] + d[1] * a[1]) + nf * (d[0] * d[0] + d[1] * d[1])
        w, vec = np.linalg.eigh(sR.T @ sR)
        lam[f] = w
        E[f] = vec
    return R2, scale, t_new, E, lam, err
