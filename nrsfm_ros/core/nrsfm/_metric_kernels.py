"""The FISTA loop of ``bmm.metric_projection_Q`` (numba).

``bmm``'s cameras solve the metric projection for five motion ranks a batch (``AUTO_RANKS``),
each up to 500 iterations of an eigen-decomposition of a 3K x 3K matrix (K <= 6): NumPy's
per-call overhead was as large as the decomposition itself (0.10 s of the 320x240 face's
batch solve).  The same steps in the same order (the same LAPACK routine): equal results.
Serial and ``nogil`` as the other kernels.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def fista_psd_trace(H: np.ndarray, lin: np.ndarray, Q: np.ndarray, step: float,
                    gamma: float, iterations: int, tol: float) -> np.ndarray:
    """Minimise 1/2 q^T H q - lin^T q + gamma tr(Q) over PSD Q (n x n, q its n^2 entries
    row-major) from ``Q`` (n^2,): FISTA with ``step``, the prox the eigenvalues shrunk by
    step x gamma and clipped at 0; stops after ``iterations`` or when a step moves Q by less
    than ``tol`` x |Q|."""
    n = int(round(np.sqrt(Q.size)))
    Q = Q.copy()
    Y = Q.copy()
    t = 1.0
    for _ in range(iterations):
        G = H @ Y - lin
        Z = (Y - step * G).reshape(n, n)
        Z = (Z + Z.T) / 2
        lam, E = np.linalg.eigh(Z)
        lam = np.maximum(lam - step * gamma, 0.0)
        Qn = ((E * lam) @ E.T).ravel()
        t_next = (1 + np.sqrt(1 + 4 * t * t)) / 2
        Y = Qn + ((t - 1) / t_next) * (Qn - Q)
        if np.linalg.norm(Qn - Q) <= tol * max(np.linalg.norm(Q), 1e-12):
            Q = Qn
            break
        Q, t = Qn, t_next
    return Q
