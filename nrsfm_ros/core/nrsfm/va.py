"""VA: Garg's dense variational NRSfM (Garg, Roussos, Agapito, CVPR 2013; METHODS §4).

Energy over the object-frame shapes S (F, 3, P) for cameras R_f (2 x 3, orthonormal rows):

    E(S) = 1/2 sum_f || V_f o (W_f - R_f S_f) ||^2             (data, visible tracks only)
         + mu  sum_f sum_(i,j) in G  h_eps(S_f[:, i] - S_f[:, j])  (spatial Huber-TV per frame)
         + lam || S# ||_*                                          (S# = F x 3P, low rank)

G is the image grid of the tracks: the symmetrised 4-nearest-neighbour graph of their reference
image positions (for tracks on a pixel grid, the 4-connected grid); h_eps is the Huber norm of
the 3-vector of coordinate differences (isotropic, quadratic below ``eps``, so smooth regions do
not staircase).  The minimisation is a linearised ADMM, vectorised over all frames and points:
splits Z = S (nuclear norm: singular value thresholding of S#, through the F x F Gram) and
Q = D S (TV: group Huber shrinkage per edge and frame), the S-step linearised in the TV
coupling so it stays a closed-form 3 x 3 solve per point (the data and the proximal terms are
diagonal in the eigenbasis of R_f^T R_f).  Cameras and the centring come from ``cdf`` (prior-free
cameras averaged over motion ranks, Procrustean gauge, coherent fill of hidden tracks), which
also gives the starting shapes; ``camera_rounds`` alternates per-frame Procrustes camera updates
with the shape step, as in Garg's alternation.  Weights are relative: ``lam`` and ``mu`` are
multiplied by the noise level of W (its RMS outside the best rank-12 approximation), so one
setting serves clean and noisy tracks.  The cost per iteration is linear in P and in the number
of graph edges (about 2P).
"""
from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from .bmm import _finish, noise_level
from .cdf import cdf
from .result import NRSfMResult, check_tracks


def grid_graph(ref: np.ndarray, k: int = 4) -> sp.csr_matrix:
    """Incidence matrix D (E, P) of the mutual k-nearest-neighbour graph of the 2-D reference
    positions ``ref`` (P, 2): an edge (i, j) when each is among the other's k nearest; row e is
    +1 at i and -1 at j.  For tracks on a pixel grid (k = 4) it is the 4-connected grid, also
    along the borders."""
    P = ref.shape[0]
    k = min(k, P - 1)
    _, idx = cKDTree(ref).query(ref, k=k + 1)
    A = sp.csr_matrix((np.ones(P * k), (np.repeat(np.arange(P), k), idx[:, 1:].ravel())),
                      shape=(P, P))
    pairs = np.stack(sp.triu(A.multiply(A.T), k=1).nonzero(), 1)
    E = pairs.shape[0]
    return sp.csr_matrix((np.tile([1.0, -1.0], E), (np.repeat(np.arange(E), 2), pairs.ravel())),
                         shape=(E, P))


def _norm2(D: sp.csr_matrix, iterations: int = 50) -> float:
    """||D||_2^2 (largest eigenvalue of the graph Laplacian D^T D) by power iteration."""
    x = np.random.default_rng(0).normal(size=D.shape[1])
    lam = 1.0
    for _ in range(iterations):
        y = D.T @ (D @ x)
        lam = float(np.linalg.norm(y))
        x = y / max(lam, 1e-300)
    return 1.05 * lam


def huber_shrink(Qv: np.ndarray, t: float, eps: float) -> np.ndarray:
    """Prox of t * h_eps on the 3-vectors along the last axis of Qv."""
    n = np.sqrt(np.einsum('...k,...k->...', Qv, Qv))
    factor = np.where(n <= eps + t, eps / (eps + t), 1 - t / np.maximum(n, 1e-300))
    return Qv * factor[..., None]


def _svt_frames(X: np.ndarray, tau: float) -> np.ndarray:
    """Singular value soft-thresholding of S# = X.reshape(F, 3P) through its F x F Gram."""
    F = X.shape[0]
    Xs = X.reshape(F, -1)
    lam, E = np.linalg.eigh(Xs @ Xs.T)
    s = np.sqrt(np.maximum(lam, 0.0))
    keep = s > tau
    if not keep.any():
        return np.zeros_like(X)
    M = (E[:, keep] * ((s[keep] - tau) / s[keep])) @ E[:, keep].T
    return (M @ Xs).reshape(X.shape)


def va_shapes(Wc: np.ndarray, V: np.ndarray, R2: np.ndarray, D: sp.csr_matrix, S0: np.ndarray,
              lam: float, mu: float, eps: float, iterations: int = 300, rho: float = 1.0,
              rho_tv: float = 1.0) -> tuple[np.ndarray, float]:
    """Object-frame shapes (F, 3, P) minimising the VA energy for fixed cameras R2 (F, 2, 3)
    with orthonormal rows, from S0, and the final relative change of S.  Weights relative to
    the RMS of W: ``lam`` as in ``bmm_shapes`` (the nuclear weight is lam sqrt(P)), ``mu`` and
    ``eps`` per edge.  Internally shapes are (F, P, 3): per-frame products are batched matrix
    products, the graph operators act on the (P, 3F) transpose."""
    F, P = V.shape
    unit = max(float(np.sqrt(np.mean(Wc ** 2))), 1e-12)
    Wf = Wc.reshape(F, 2, P).transpose(0, 2, 1) / unit                   # (F, P, 2)
    S = np.ascontiguousarray(S0.transpose(0, 2, 1)) / unit               # (F, P, 3)
    L = _norm2(D)
    Dt = D.T.tocsr()
    nE = D.shape[0]

    def grad(X: np.ndarray) -> np.ndarray:                                # (E, F, 3)
        return (D @ X.transpose(1, 0, 2).reshape(P, 3 * F)).reshape(nE, F, 3)

    def div(Y: np.ndarray) -> np.ndarray:                                 # (F, P, 3)
        return (Dt @ Y.reshape(nE, 3 * F)).reshape(P, F, 3).transpose(1, 0, 2)
    R2t = R2.transpose(0, 2, 1)                                           # (F, 3, 2)
    RtW = (Wf @ R2) * V[:, :, None]                                       # (F, P, 3)
    c = rho + rho_tv * L
    # (c I + v R^T R)^-1 = (I - R^T R) / c + R^T R / (c + v) for orthonormal rows
    gain = (1.0 / (c + V) - 1.0 / c)[:, :, None]                          # (F, P, 1)
    Z, U = S.copy(), np.zeros_like(S)
    Q = grad(S)
    U2 = np.zeros_like(Q)
    tau = lam * np.sqrt(P)      # the nuclear weight scaled as in bmm_shapes
    change = np.inf
    for _ in range(iterations):
        rhs = RtW + rho * (Z - U) + rho_tv * (L * S - div(grad(S) - Q + U2))
        S_new = rhs / c + gain * ((rhs @ R2t) @ R2)
        change = float(np.linalg.norm(S_new - S) / max(np.linalg.norm(S_new), 1e-300))
        S = S_new
        Z = _svt_frames(S + U, tau / rho)
        GS = grad(S)
        Q = huber_shrink(GS + U2, mu / rho_tv, eps)
        U += S - Z
        U2 += GS - Q
    return Z.transpose(0, 2, 1) * unit, change


def va(W: np.ndarray, V: np.ndarray | None = None, mu: float = 0.5, lam: float = 4.0,
       eps: float = 1.0, iterations: int = 300, camera_rounds: int = 0, neighbours: int = 4,
       seed: int = 0) -> NRSfMResult:
    """Garg's variational NRSfM: data + per-frame spatial Huber-TV (weight ``mu``, threshold
    ``eps``) + nuclear norm (``lam``), both weights x the noise level of W; cameras and the
    start from ``cdf``; ``camera_rounds`` Procrustes camera updates, each followed by the shape
    step; ``neighbours`` k of the image-grid graph."""
    t0 = time.perf_counter()
    W, V = check_tracks(W, V)
    for name, v in (('mu', mu), ('lam', lam), ('eps', eps)):
        if not v >= 0 or (name == 'eps' and v == 0):
            raise ValueError(f'{name}: expected {">" if name == "eps" else ">="} 0, got {v}')
    if iterations < 1 or camera_rounds < 0 or neighbours < 1:
        raise ValueError(f'iterations={iterations}, camera_rounds={camera_rounds}, '
                         f'neighbours={neighbours}: expected >= 1, >= 0, >= 1')
    F, P = V.shape
    init = cdf(W, V, lam_nuc=lam, seed=seed)
    R = init.R
    R2 = R[:, :2, :]
    Wc = W - init.t.reshape(-1, 1)
    S = np.einsum('fji,fpj->fip', R, init.S)            # object frame (F, 3, P)
    r = int(np.argmax((V >= 0.5).sum(1)))
    D = grid_graph(Wc.reshape(F, 2, P)[r].T, neighbours)
    level = max(noise_level(Wc), 1e-4)
    for rnd in range(camera_rounds + 1):
        if rnd:         # Procrustes cameras: nearest orthonormal rows to W_f S_f^T
            U_, _, Vt = np.linalg.svd((Wc.reshape(F, 2, P) * V[:, None, :])
                                      @ S.transpose(0, 2, 1), full_matrices=False)
            R2 = U_ @ Vt
        S, change = va_shapes(Wc, V, R2, D, S, lam * level, mu * level, eps * level,
                              iterations)
    return _finish(Wc, V, R2, S, init.t, 'va', 0, iterations * (camera_rounds + 1),
                   change < 1e-4, t0)
