"""Gaussian kernel and its Nystrom features: the smooth displacement fields of CPD (non-rigid)
and NRGA (a building block, not a method)."""
from __future__ import annotations

import numpy as np


class Nystrom:
    """Nystrom features of the Gaussian kernel G_ij = exp(-|y_i - y_j|^2 / (2 beta^2)) from
    ``landmarks`` sampled points: features(A) (n, r) with features(A) features(B)^T ~= G(A, B).
    The same features extend the field to new points consistently."""

    def __init__(self, Y: np.ndarray, beta: float, landmarks: int,
                 rng: np.random.Generator) -> None:
        idx = np.sort(rng.choice(len(Y), min(landmarks, len(Y)), replace=False))
        self.L, self.beta = Y[idx], beta
        lam, U = np.linalg.eigh(gaussian_kernel(self.L, self.L, beta))
        keep = lam > 1e-8 * lam[-1]
        self.proj = U[:, keep] / np.sqrt(lam[keep])

    def features(self, A: np.ndarray) -> np.ndarray:
        return gaussian_kernel(A, self.L, self.beta) @ self.proj


def gaussian_kernel(A: np.ndarray, B: np.ndarray, beta: float, chunk: int = 4096) -> np.ndarray:
    out = np.empty((A.shape[0], B.shape[0]))
    bb = (B ** 2).sum(1)
    for a in range(0, A.shape[0], chunk):
        Ac = A[a:a + chunk]
        d2 = (Ac ** 2).sum(1)[:, None] + bb[None] - 2 * Ac @ B.T
        out[a:a + chunk] = np.exp(-np.maximum(d2, 0) / (2 * beta ** 2))
    return out
