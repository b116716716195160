"""HDSM: the high-dimensional space model (METHODS §7).

A non-rigid sequence is encoded as projections of one lifted structure S_hat (D x P, D >= 3)
onto per-frame 3-D subspaces: S_f = Phi_f S_hat with Phi_f (3 x D) having orthonormal rows.
Storage is D P + 3 D F numbers instead of 3 F P: compression ratio c = 3 F P / (D P + 3 D F);
D = 3 is the rigid case.

Fitting (``lift``) minimises sum_f ||S_f - Phi_f S_hat||^2 by alternation, one dimension at a
time: start from the mean shape (D = 3), and for each added dimension seed it with the leading
right singular vector of the residual, then alternate
  * S_hat by least squares: (sum_f Phi_f^T Phi_f) S_hat = sum_f Phi_f^T S_f;
  * Phi_f on the Stiefel manifold by majorisation-minimisation: tr(Phi C Phi^T) with
    C = S_hat S_hat^T is majorised by its tangent at the current Phi (C - lambda_max I is
    negative semi-definite), so each step is the polar factor of
    S_f S_hat^T - Phi_f (C - lambda_max I) -- a closed-form step that never increases the
    objective (the plain Procrustes polar factor would, because Phi is not square).
Every step is monotone, so the fit error does not grow with D.  ``hdsm`` runs ``bmm`` for the
cameras and shapes and returns the lifted reconstruction with its compression ratio.  (The
thesis's permutation matrices and the lifted coherency term of L-CDF are not implemented.)
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from .bmm import bmm
from .result import NRSfMResult, check_tracks


def _stiefel(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M, full_matrices=False)
    return U @ Vt


def compression_ratio(F: int, P: int, D: int) -> float:
    """3 F P / (D P + 3 D F): numbers of the full sequence over those of the lifted model."""
    return 3.0 * F * P / (D * P + 3.0 * D * F)


def lift(S: np.ndarray, dim: int, iterations: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """Lifted model of object-frame shapes S (F, 3, P): Phi (F, 3, dim) with orthonormal rows
    and S_hat (dim, P) with S_f ~= Phi_f S_hat (see the module docstring)."""
    S = np.asarray(S, dtype=np.float64)
    if S.ndim != 3 or S.shape[1] != 3:
        raise ValueError(f'S: expected shape (F, 3, P), got {S.shape}')
    if dim < 3:
        raise ValueError(f'dim={dim}: expected >= 3 (3 is the rigid case)')
    F, _, P = S.shape
    S_hat = S.mean(0)
    Phi = np.broadcast_to(np.eye(3), (F, 3, 3)).copy()
    for D in range(3, dim + 1):
        if D > 3:
            R = S - np.einsum('fid,dp->fip', Phi, S_hat)
            _, s, vt = np.linalg.svd(R.reshape(3 * F, P), full_matrices=False)
            S_hat = np.vstack([S_hat, vt[:1] * s[0] / np.sqrt(F)])
            Phi = np.concatenate([Phi, np.zeros((F, 3, 1))], axis=2)
        for _ in range(iterations):
            C = S_hat @ S_hat.T
            shift = C - np.linalg.eigvalsh(C)[-1] * np.eye(D)
            Phi = _stiefel(np.einsum('fip,dp->fid', S, S_hat) - Phi @ shift)
            G = np.einsum('fid,fie->de', Phi, Phi)
            G += 1e-12 * np.trace(G) * np.eye(D)
            S_hat = np.linalg.solve(G, np.einsum('fid,fip->dp', Phi, S))
    return Phi, S_hat


def hdsm(W: np.ndarray, V: np.ndarray | None = None, dim: int = 9, iterations: int = 100
         ) -> NRSfMResult:
    """``bmm`` cameras and shapes, then the lifted model of dimension ``dim``; the result's
    shapes are the lifted reconstruction and ``compression`` its ratio."""
    t0 = time.perf_counter()
    W, V = check_tracks(W, V)
    F, P = V.shape
    if dim < 3:
        raise ValueError(f'dim={dim}: expected >= 3 (3 is the rigid case)')
    base = bmm(W, V)
    S_obj = np.einsum('fji,fpj->fip', base.R, base.S)
    Phi, S_hat = lift(S_obj, dim, iterations)
    S_lift = np.einsum('fid,dp->fip', Phi, S_hat)
    S_cam = np.einsum('fij,fjp->fpi', base.R, S_lift)
    Wc = W.reshape(F, 2, P) - base.t[:, :, None]
    d = np.linalg.norm(Wc - S_cam.transpose(0, 2, 1)[:, :2], axis=1)
    return replace(base, S=S_cam, method='hdsm', rank=dim,
                   residual_px=float((d * V).sum() / max(V.sum(), 1e-12)),
                   compression=compression_ratio(F, P, dim),
                   seconds=time.perf_counter() - t0)
