"""Batch solves on a spread subset of the tracks, extended to every track by least squares.

The batch methods cost O(P) and more per iteration (``bmm``'s nuclear-norm shapes: 106 s of a
640x480 ``process`` run over ~25k tracks).  A solve on ``max_tracks`` tracks spread evenly over
the track order (the tracker's raster order: spread over the image) gives the cameras and a
temporal basis of the shapes: the object-frame shapes S_f = sum_k C_fk B_k of the subset, C
(F, K) from the SVD of S# (F, 3P) (the components that hold all but ``BASIS_ENERGY`` of its
energy, at most ``MAX_BASIS``).  Every other track p then has 3K unknowns, its own basis
coordinates b_kp, seen in 2F measurements w_fp = scale_f R_f[:2] sum_k C_fk b_kp + t_f: a
visibility-weighted linear least-squares problem per track, solved for all at once (a ridge of
``RIDGE`` x the mean diagonal keeps tracks seen in few frames near the subset's scale).
``planar``'s tracks are extended by its own model instead (rest positions and a height per
frame along the normal, for the subset's cameras).  The subset's own shapes are kept as solved.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from .result import NRSfMResult

BASIS_ENERGY = 1e-4   # energy of S# the temporal basis may leave out
MAX_BASIS = 8         # components of the temporal basis at most
RIDGE = 1e-6          # relative ridge of the per-track normal equations


def spread_subset(P: int, max_tracks: int) -> np.ndarray:
    """``max_tracks`` indices spread evenly over 0..P-1 (all of them when P <= max_tracks)."""
    if max_tracks < 4:
        raise ValueError(f'max_tracks: expected >= 4, got {max_tracks}')
    if P <= max_tracks:
        return np.arange(P)
    return np.unique(np.linspace(0, P - 1, max_tracks).round().astype(np.intp))


def extend(sub: NRSfMResult, idx: np.ndarray, W: np.ndarray, V: np.ndarray) -> NRSfMResult:
    """The solve ``sub`` of the tracks ``idx`` extended to every track of (W, V) (see the module
    docstring); cameras, scales and translations are the subset's."""
    F, P = V.shape
    S_obj = (sub.S @ sub.R).reshape(F, -1)                      # (F, Ps x 3) object frame
    # the left singular vectors from the F x F Gram matrix (a thin SVD of F x 3Ps is ~20x
    # slower at 10k tracks; only components above 1e-4 of the energy are kept)
    lam, U = np.linalg.eigh(S_obj @ S_obj.T)
    lam, U = np.maximum(lam[::-1], 0.0), U[:, ::-1]
    energy = np.cumsum(lam) / max(float(lam.sum()), 1e-300)
    K = int(min(MAX_BASIS, np.searchsorted(energy, 1.0 - BASIS_ENERGY) + 1))
    C = U[:, :K] * np.sqrt(lam[:K])                              # (F, K)
    R2 = sub.R[:, :2] * sub.scale[:, None, None]                 # (F, 2, 3)
    M = np.einsum('fk,fij->fikj', C, R2).reshape(F, 2, 3 * K)    # w_f = M_f vec(B) + t_f
    rest = np.setdiff1d(np.arange(P), idx)
    # every track's normal equations and coefficients (the subset's are overwritten with its
    # own shapes after): no gather of the other tracks' (F, 2, Pr) measurements nor scatter of
    # their shapes, half of a 640x480 batch's extension
    Wc = W.reshape(F, 2, P) - sub.t[:, :, None]                  # (F, 2, P)
    # the per-track normal equations as matrix products (an einsum over these axes runs
    # unblocked: 1.4 s of a 640x480 batch's four extensions)
    n = 3 * K
    G = np.einsum('fai,faj->fij', M, M)                          # (F, 3K, 3K)
    N = (V.T @ G.reshape(F, n * n)).reshape(-1, n, n)
    # the ridge from the other tracks' mean diagonal (as when only they were solved)
    mean_trace = float(V[:, rest].mean(axis=1) @ np.trace(G, axis1=1, axis2=2))
    N += RIDGE * max(mean_trace / n, 1e-300) * np.eye(n)
    rhs = ((V[:, None, :] * Wc).reshape(2 * F, -1).T @ M.reshape(2 * F, n))    # (P, 3K)
    b = np.linalg.solve(N, rhs[:, :, None])[:, :, 0]                  # (P, 3K)
    if K == 1:      # NumPy's matmul over an inner dimension of 1 is not BLAS (~10x slower)
        obj = np.multiply.outer(C[:, 0], b).reshape(F, P, 3)
    else:
        obj = (C @ b.reshape(P, K, 3).transpose(1, 0, 2).reshape(K, -1)).reshape(F, P, 3)
    S = obj @ sub.R.transpose(0, 2, 1)                            # camera frame (F, P, 3)
    if sub.method == 'planar':
        S[:, rest] = _planar_rest(sub, S[:, rest], Wc[:, :, rest], V[:, rest])
    S[:, idx] = sub.S
    return replace(sub, S=S)


def _planar_rest(sub: NRSfMResult, S_basis: np.ndarray, Wr: np.ndarray, Vr: np.ndarray
                 ) -> np.ndarray:
    """``planar``'s own model for the other tracks: rest positions and per-frame heights
    along the normal for the subset's cameras (its height field has a free height per point and
    frame, more than a temporal basis holds), hidden entries first filled by the basis'
    reprojection (as ``planar`` fills them by coherent motion fields)."""
    from .planar import height_field
    F = Wr.shape[0]
    pred = sub.scale[:, None, None] * S_basis[:, :, :2].transpose(0, 2, 1)
    X = np.where((Vr >= 0.5)[:, None, :], Wr, pred).reshape(2 * F, -1)
    S_obj = height_field(X, Vr, sub.R[:, :2] * sub.scale[:, None, None])   # (F, 3, Pr)
    return np.einsum('fij,fjp->fpi', sub.R, S_obj)


def subset_solve(solve: Callable[[np.ndarray, np.ndarray], NRSfMResult], W: np.ndarray,
                 V: np.ndarray, max_tracks: int) -> NRSfMResult:
    """``solve(W, V)`` on at most ``max_tracks`` spread tracks, extended to all of them."""
    idx = spread_subset(V.shape[1], max_tracks)
    if idx.size == V.shape[1]:
        return solve(W, V)
    sub = solve(W[:, idx], V[:, idx])
    return extend(sub, idx, W, V)
