"""Low-rank motion subspace of dense flow trajectories (the multi-frame constraint of MFOF).

The reference->frame displacements of all P reference pixels over F frames form D (2F x P; rows
du_1, dv_1, du_2, ...).  Smooth non-rigid motion makes D close to rank R: D ~= Q B, with Q (2F x R)
per-frame coefficients and B (R x P) basis images (per-pixel coefficients of the trajectory
basis).  B always contains a fixed quadratic polynomial block (so global affine-like motion is
representable from the first frame on) plus R learned images, initialised by one EM-SVD step
(unreliable entries, weight ~0 such as occluded ones, imputed from the current model) and refined
by weighted alternating least squares with a pull towards the spatially smoothed basis, so pixels
hidden in most frames are filled from their neighbours.  All functions are vectorised over
pixels; ``GridSampler`` moves the smooth basis between the full and a coarse grid.
"""
from __future__ import annotations

import cv2
import numpy as np


def polynomial_basis(height: int, width: int, degree: int = 2) -> np.ndarray:
    """Orthonormal polynomial images up to ``degree`` in x, y: (M, H*W) float32."""
    if degree not in (0, 1, 2):
        raise ValueError(f'degree={degree}: expected 0, 1 or 2')
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    x = (x - (width - 1) / 2) / max(width, height)
    y = (y - (height - 1) / 2) / max(width, height)
    cols = [np.ones_like(x)]
    if degree >= 1:
        cols += [x, y]
    if degree >= 2:
        cols += [x * x, x * y, y * y]
    A = np.stack([c.ravel() for c in cols], axis=1)
    q, _ = np.linalg.qr(A)
    return q.T.astype(np.float32)


def smooth_images(B: np.ndarray, shape: tuple[int, int], sigma: float,
                  confidence: np.ndarray | None = None) -> np.ndarray:
    """Normalised Gaussian smoothing of basis images B (R, H*W) on the (H, W) grid, weighted by
    ``confidence`` (H*W,) so unreliable pixels are filled from reliable neighbours."""
    if sigma <= 0 or B.shape[0] == 0:
        return B
    h, w = shape
    out = np.empty_like(B)
    if confidence is None:
        for r in range(B.shape[0]):
            out[r] = cv2.GaussianBlur(B[r].reshape(h, w), (0, 0), sigma).ravel()
        return out
    c = confidence.reshape(h, w).astype(np.float32)
    norm = cv2.GaussianBlur(c, (0, 0), sigma) + 1e-6
    for r in range(B.shape[0]):
        out[r] = (cv2.GaussianBlur(B[r].reshape(h, w) * c, (0, 0), sigma) / norm).ravel()
    return out


def fit_coefficients(B: np.ndarray, d: np.ndarray, weight: np.ndarray,
                     huber_px: float = 2.0, iterations: int = 2, ridge: float = 1e-6,
                     sample: np.ndarray | None = None, prior: np.ndarray | None = None,
                     prior_weight: float = 0.0) -> np.ndarray:
    """Per-frame coefficients q (2, R) with d ~= q B, by weighted least squares over pixels,
    robustified by ``iterations`` Huber IRLS steps on the per-pixel residual length.

    B (R, P) basis, d (2, P) measured displacement, weight (P,) data confidence in [0, 1];
    ``sample`` optionally restricts the fit to a subset of pixel indices (speed).  ``prior``
    (2, R) pulls the coefficients with ``prior_weight`` (relative to the information of a fully
    visible frame), so components that the visible pixels do not determine (basis images living
    under an occluder) follow the prior (the temporal prediction) instead of the noise."""
    if sample is not None:
        B, d, weight = B[:, sample], d[:, sample], weight[sample]
    w = weight.astype(np.float32)
    R = B.shape[0]
    q = np.zeros((2, R), np.float32)
    mu = 0.0
    if prior is not None and prior_weight > 0:
        mu = prior_weight * float((B * B).sum()) / R
    for it in range(iterations + 1):
        Bw = B * w
        A = Bw @ B.T
        A += (ridge * float(np.trace(A)) / R + mu + 1e-12) * np.eye(R, dtype=np.float32)
        rhs = Bw @ d.T
        if mu > 0:
            rhs = rhs + mu * prior.T
        q = np.linalg.solve(A, rhs).T
        if it == iterations:
            break
        r = np.sqrt(((q @ B - d) ** 2).sum(0))
        w = weight * np.minimum(1.0, huber_px / np.maximum(r, 1e-6)).astype(np.float32)
    return q


def fit_basis(D: np.ndarray, weight: np.ndarray, fixed: np.ndarray, rank: int,
              shape: tuple[int, int], sigma: float = 0.0, iterations: int = 3,
              initial: np.ndarray | None = None, smooth_weight: float = 0.05,
              start: np.ndarray | None = None) -> np.ndarray:
    """Learned basis images (rank, P) for displacements D (2N, P) with per-frame weights
    (N, P), orthonormal and orthogonal to the ``fixed`` (M, P, orthonormal) block.

    Initialisation: one EM-SVD step (low-weight entries imputed from ``initial`` (2N, P), by
    default the projection onto ``fixed``).  Then ``iterations`` weighted alternating least
    squares steps: per-frame coefficients by weighted LS over pixels, per-pixel basis values by
    weighted LS over frames (batched R x R solves) with a pull of ``smooth_weight`` (relative to
    a fully visible frame) towards the spatially smoothed basis, so pixels hidden in most of the
    window are filled from their neighbours."""
    n2, P = D.shape
    N = n2 // 2
    rank = int(min(rank, n2))
    if rank == 0:
        return np.zeros((0, P), np.float32)
    w2 = np.repeat(weight, 2, axis=0).astype(np.float32)
    if start is not None and start.shape == (rank, P):
        L = _orthonormal(start, fixed)         # warm start from the previous basis
    else:
        if initial is None:     # weighted fit of the fixed block, frame by frame
            initial = np.concatenate([fit_coefficients(fixed, D[2 * f:2 * f + 2], weight[f],
                                                       iterations=0) @ fixed
                                      for f in range(N)])
        X = w2 * D + (1 - w2) * initial
        X -= (X @ fixed.T) @ fixed
        _, evecs = np.linalg.eigh((X @ X.T).astype(np.float64))
        U = evecs[:, ::-1][:, :rank].astype(np.float32)
        L = _orthonormal(U.T @ X, fixed)
    conf = weight.mean(axis=0)
    for _ in range(iterations):
        # per-frame coefficients for [fixed; L]
        B = np.concatenate([fixed, L])
        Q = np.empty((n2, B.shape[0]), np.float32)
        for f in range(N):
            Q[2 * f:2 * f + 2] = fit_coefficients(B, D[2 * f:2 * f + 2], weight[f],
                                                  iterations=0)
        Qf, QL = Q[:, :fixed.shape[0]], Q[:, fixed.shape[0]:]
        Rres = D - Qf @ fixed                         # (2N, P) what L must explain
        # per-pixel normal equations: A_p = sum_f w_fp G_f, b_p = sum_rows w QL^T r
        G = QL[0::2, :, None] * QL[0::2, None, :] + QL[1::2, :, None] * QL[1::2, None, :]
        A = (weight.T @ G.reshape(N, -1)).reshape(P, rank, rank)
        b = ((w2 * Rres).T @ QL)                      # (P, rank)
        lam = smooth_weight * float(np.trace(G.sum(0))) / max(N, 1) / rank
        prior = smooth_images(L, shape, max(sigma, 1.0), conf).T
        A += lam * np.eye(rank, dtype=np.float32)
        b += lam * prior
        L = _orthonormal(np.linalg.solve(A, b[..., None])[..., 0].T, fixed)
    return _orthonormal(smooth_images(L, shape, sigma, conf), fixed)


def _orthonormal(L: np.ndarray, fixed: np.ndarray) -> np.ndarray:
    """Rows of L made orthonormal and orthogonal to the (orthonormal) fixed rows."""
    L = L.astype(np.float64)
    L = L - (L @ fixed.T) @ fixed
    q, _ = np.linalg.qr(L.T)
    return q.T.astype(np.float32)


class GridSampler:
    """Maps between the full (H, W) grid and a coarser one with about ``target`` pixels, for
    fitting the smooth learned basis cheaply (area averaging down, bilinear up)."""

    def __init__(self, shape: tuple[int, int], target: int = 8000) -> None:
        h, w = shape
        self.shape = shape
        self.step = max(1, int(round(np.sqrt(h * w / target))))
        self.small = (max(1, h // self.step), max(1, w // self.step))
        self.fixed_small = polynomial_basis(*self.small, 2)
        self.fixed = polynomial_basis(h, w, 2)

    def down(self, X: np.ndarray) -> np.ndarray:
        """(K, H*W) -> (K, h*w)."""
        return self._resize(X, self.shape, self.small, cv2.INTER_AREA)

    def up(self, X: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """(K, h*w) -> (K, H*W) (bilinear; not re-orthonormalised: fits use least squares),
        written to ``out`` (K, H*W) float32 where given."""
        return self._resize(X, self.small, self.shape, cv2.INTER_LINEAR, out)

    def _resize(self, X: np.ndarray, src: tuple[int, int], dst: tuple[int, int],
                interpolation: int, out: np.ndarray | None = None) -> np.ndarray:
        """Every row of X, an image of shape ``src`` (h, w), resized to ``dst`` (into ``out``
        where given)."""
        if self.step == 1:
            if out is None:
                return X
            out[...] = X
            return out
        if out is None:
            out = np.empty((X.shape[0], dst[0] * dst[1]), np.float32)
        for k in range(X.shape[0]):
            out[k] = cv2.resize(X[k].reshape(src), (dst[1], dst[0]),
                                interpolation=interpolation).ravel()
        return out
