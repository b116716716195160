"""One-pass kernels of the monocular scene flow (numba): the window fit's displacement and
the shrinkage's neighbourhood means.

At 30k points a cloud their NumPy forms made (n, 3) and (n, k) temporaries every pass: the
centred displacement's per-cloud object-frame positions ~2.3 ms a cloud of a 640x480 stream,
the shrinkage's two neighbourhood gathers ~2 ms.  Serial and ``nogil`` as the other kernels."""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def add_object_displacement(out: np.ndarray, X: np.ndarray, rows: np.ndarray, t: np.ndarray,
                            R: np.ndarray, h: float) -> None:
    """``out[p] += h (X[rows[p]] - t) @ R`` for every row p of ``out`` (n, 3): one cloud's
    object-frame positions weighted into a displacement; ``rows`` empty: row p of X itself."""
    n = out.shape[0]
    same = rows.shape[0] == 0
    for p in range(n):
        q = p if same else rows[p]
        x0, x1, x2 = X[q, 0] - t[0], X[q, 1] - t[1], X[q, 2] - t[2]
        for j in range(3):
            out[p, j] += h * (x0 * R[0, j] + x1 * R[1, j] + x2 * R[2, j])


@njit(cache=True, nogil=True)
def neighbour_means(values: np.ndarray, index: np.ndarray) -> np.ndarray:
    """(N,) the mean of ``values`` over each row of the neighbour ``index`` (N, k)."""
    N, k = index.shape
    out = np.empty(N)
    for p in range(N):
        s = 0.0
        for j in range(k):
            s += values[index[p, j]]
        out[p] = s / k
    return out
