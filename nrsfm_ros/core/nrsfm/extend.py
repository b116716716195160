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
BLOCK = 4096          # tracks a block of the extension


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
    # own shapes after), as matrix products (an einsum over these axes runs unblocked: 1.4 s
    # of a 640x480 batch's four extensions), a block of tracks at a time: the temporaries stay
    # a few MB that the allocator reuses, where whole-batch (F, 2, P) ones were fresh memory at
    # every call (0.35 s of page faults in a 640x480 batch's 0.4 s extension on this machine)
    n = 3 * K
    G = np.einsum('fai,faj->fij', M, M).reshape(F, n * n)        # (F, 3K x 3K)
    # the ridge from the other tracks' mean diagonal (as when only they were solved)
    V_rest = (V.sum(axis=1) - V[:, idx].sum(axis=1)) / max(rest.size, 1)
    mean_trace = float(V_rest @ np.trace(G.reshape(F, n, n), axis1=1, axis2=2))
    ridge = RIDGE * max(mean_trace / n, 1e-300) * np.eye(n)
    Mt = M.reshape(2 * F, n)
    # S_fp = R_f sum_k C_fk b_kp = b_p @ A_f with A_f[(k, j), i] = C_fk R_f[i, j]
    A = (C[:, :, None, None] * sub.R.transpose(0, 2, 1)[:, None]).reshape(F, n, 3)
    S = np.empty((F, P, 3))
    W3 = W.reshape(F, 2, P)
    for p0 in range(0, P, BLOCK):
        sl = slice(p0, min(p0 + BLOCK, P))
        Vb = V[:, sl]
        N = (Vb.T @ G).reshape(-1, n, n) + ridge
        rhs = (Vb[:, None, :] * (W3[:, :, sl] - sub.t[:, :, None])).reshape(2 * F, -1).T @ Mt
        b = np.linalg.solve(N, rhs[:, :, None])[:, :, 0]           # (Pb, 3K)
        np.matmul(b, A, out=S[:, sl])
    if sub.method == 'planar':
        Wr = W3[:, :, rest] - sub.t[:, :, None]
        S[:, rest] = _planar_rest(sub, S[:, rest], Wr, V[:, rest])
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
