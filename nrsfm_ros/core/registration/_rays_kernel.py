"""The Gauss-Newton normal equations of ``rays.ray_pose`` in one pass over the points (numba).

Its NumPy form built (n, 3, 6) Jacobians and their weighted copies every iteration: ~0.3 ms an
iteration at its 1000 points, 3 ms a cloud (the registrar's per-cloud pose at 320x240 and at
640x480 alike).  Serial and ``nogil`` as the other kernels."""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def ray_normal_equations(G: np.ndarray, p: np.ndarray, x: np.ndarray, d: np.ndarray,
                         c: float, threshold: float
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For the target points p (n, 3) mapped by G (4, 4) into the source camera (y = G p) and
    the source points x (n, 3) with their ray directions d (n, 3): the weighted error
    e = v - c d (d . v) of v = y - x, its length r (n,), and the Cauchy-weighted (scale
    ``threshold``) normal equations H (6, 6), g (6,) of the left update of G (a rotation
    vector, then a translation): J = A - c d (d^T A), A = [-[y]x | I]."""
    n = p.shape[0]
    H = np.zeros((6, 6))
    g = np.zeros(6)
    r = np.empty(n)
    J = np.empty((3, 6))
    A = np.zeros((3, 6))
    A[0, 3] = A[1, 4] = A[2, 5] = 1.0
    e = np.empty(3)
    for i in range(n):
        y0 = G[0, 0] * p[i, 0] + G[0, 1] * p[i, 1] + G[0, 2] * p[i, 2] + G[0, 3]
        y1 = G[1, 0] * p[i, 0] + G[1, 1] * p[i, 1] + G[1, 2] * p[i, 2] + G[1, 3]
        y2 = G[2, 0] * p[i, 0] + G[2, 1] * p[i, 1] + G[2, 2] * p[i, 2] + G[2, 3]
        d0, d1, d2 = d[i, 0], d[i, 1], d[i, 2]
        v0, v1, v2 = y0 - x[i, 0], y1 - x[i, 1], y2 - x[i, 2]
        dv = d0 * v0 + d1 * v1 + d2 * v2
        e[0], e[1], e[2] = v0 - c * d0 * dv, v1 - c * d1 * dv, v2 - c * d2 * dv
        ri = np.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
        r[i] = ri
        w = 1.0 / (1.0 + (ri / threshold) ** 2)
        # -[y]x
        A[0, 0], A[0, 1], A[0, 2] = 0.0, y2, -y1
        A[1, 0], A[1, 1], A[1, 2] = -y2, 0.0, y0
        A[2, 0], A[2, 1], A[2, 2] = y1, -y0, 0.0
        for k in range(6):
            dA = d0 * A[0, k] + d1 * A[1, k] + d2 * A[2, k]
            J[0, k] = A[0, k] - c * d0 * dA
            J[1, k] = A[1, k] - c * d1 * dA
            J[2, k] = A[2, k] - c * d2 * dA
        for a in range(6):
            g[a] += w * (J[0, a] * e[0] + J[1, a] * e[1] + J[2, a] * e[2])
            for b in range(6):
                H[a, b] += w * (J[0, a] * J[0, b] + J[1, a] * J[1, b] + J[2, a] * J[2, b])
    return H, g, r


@njit(cache=True, nogil=True)
def ray_residual_lengths(G: np.ndarray, p: np.ndarray, x: np.ndarray, d: np.ndarray,
                         depth_weight: float) -> np.ndarray:
    """``rays.ray_residuals`` in one pass over the points: r (n,) of the target points p
    (n, 3) mapped by G (4, 4) against the source points x (n, 3) with ray directions d."""
    n = p.shape[0]
    r = np.empty(n)
    for i in range(n):
        e0 = G[0, 0] * p[i, 0] + G[0, 1] * p[i, 1] + G[0, 2] * p[i, 2] + G[0, 3] - x[i, 0]
        e1 = G[1, 0] * p[i, 0] + G[1, 1] * p[i, 1] + G[1, 2] * p[i, 2] + G[1, 3] - x[i, 1]
        e2 = G[2, 0] * p[i, 0] + G[2, 1] * p[i, 1] + G[2, 2] * p[i, 2] + G[2, 3] - x[i, 2]
        along = e0 * d[i, 0] + e1 * d[i, 1] + e2 * d[i, 2]
        lateral2 = max(e0 * e0 + e1 * e1 + e2 * e2 - along * along, 0.0)
        r[i] = np.sqrt(lateral2 + (depth_weight * along) ** 2)
    return r
