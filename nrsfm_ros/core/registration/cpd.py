"""Coherent Point Drift (Myronenko & Song; METHODS §9): rigid, affine and non-rigid.

The target X (N, D) is a Gaussian-mixture sample of the transformed source Y (M, D) plus a
uniform outlier component of weight ``w``.  EM: the E-step posteriors P (M, N) are computed in
row chunks (two passes: the per-target normaliser, then P's sums), so memory stays O(chunk x N);
the M-steps are the closed forms of the paper.  Non-rigid: the displacement field is G W with the
Gaussian kernel G (width ``beta``) approximated by a Nystrom factor G ~= B B^T (``landmarks``
columns), so each M-step is a Woodbury solve in O(M r^2) instead of O(M^3).

Large inputs are registered coarse-to-fine: CPD on a random subsample of at most
``max_points`` per set, then (rigid, affine) the transform is applied to all points, and
(non-rigid) the displacement is interpolated to every source point with the same kernel.
"""
from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from .icp import RegistrationResult, check_points, normalise_pair


def _sigma2(X: np.ndarray, Y: np.ndarray) -> float:
    N, D = X.shape
    M = Y.shape[0]
    return float((M * (X ** 2).sum() + N * (Y ** 2).sum() - 2 * X.sum(0) @ Y.sum(0))
                 / (D * M * N))


def estep(X: np.ndarray, TY: np.ndarray, sigma2: float, w: float, chunk: int = 2048
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """P1 (M,) = P 1, Pt1 (N,) = P^T 1, PX (M, D) = P X for the CPD posteriors."""
    N, D = X.shape
    M = TY.shape[0]
    c = (2 * np.pi * sigma2) ** (D / 2) * w / (1 - w) * M / N
    X32, TY32 = X.astype(np.float32), TY.astype(np.float32)
    xx = (X32 ** 2).sum(1)
    den = np.zeros(N, np.float64)
    cache = [] if M * N <= 4e7 else None      # keep the kernel chunks when they fit (~160 MB)
    scale = np.float32(-0.5 / sigma2)

    def kernel(a: int) -> np.ndarray:
        Yc = TY32[a:a + chunk]
        d2 = (Yc ** 2).sum(1)[:, None] + xx[None] - 2 * Yc @ X32.T
        np.maximum(d2, 0, out=d2)
        d2 *= scale
        return np.exp(d2, out=d2)
    for a in range(0, M, chunk):
        K = kernel(a)
        den += K.sum(0)
        if cache is not None:
            cache.append(K)
    den += c
    inv = np.where(den > 1e-30, 1.0 / np.maximum(den, 1e-30), 0.0).astype(np.float32)
    P1 = np.empty(M)
    Pt1 = np.zeros(N)
    PX = np.empty((M, D))
    for i, a in enumerate(range(0, M, chunk)):
        Pc = cache[i] if cache is not None else kernel(a)
        Pc *= inv[None]
        P1[a:a + chunk] = Pc.sum(1)
        Pt1 += Pc.sum(0)
        PX[a:a + chunk] = Pc @ X32
    return P1, Pt1, PX


def estep_pairs(X: np.ndarray, TY: np.ndarray, sigma2: float, w: float, idx: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The E-step restricted to candidate pairs: ``idx`` (N, k) holds, for each target point,
    the source points it may belong to (its k nearest); the rest of P is taken as 0."""
    N, D = X.shape
    M = TY.shape[0]
    d2 = ((X[:, None, :] - TY[idx]) ** 2).sum(-1)
    K = np.exp(-d2 / (2 * sigma2))
    c = (2 * np.pi * sigma2) ** (D / 2) * w / (1 - w) * M / N
    P = K / np.maximum(K.sum(1, keepdims=True) + c, 1e-300)
    flat = idx.ravel()
    P1 = np.bincount(flat, P.ravel(), minlength=M)
    PX = np.stack([np.bincount(flat, (P * X[:, j:j + 1]).ravel(), minlength=M)
                   for j in range(D)], axis=1)
    return P1, P.sum(1), PX


def _rigid_mstep(X, Y, P1, Pt1, PX, scale: bool):
    Np = max(P1.sum(), 1e-12)
    mux = Pt1 @ X / Np
    muy = P1 @ Y / Np
    A = PX.T @ Y - Np * np.outer(mux, muy)          # (D, D) = Xh^T P^T Yh
    U, _, Vt = np.linalg.svd(A)
    C = np.eye(X.shape[1])
    C[-1, -1] = np.sign(np.linalg.det(U @ Vt))
    R = U @ C @ Vt
    yPy = (P1 * (Y ** 2).sum(1)).sum() - Np * muy @ muy
    trAR = np.trace(A.T @ R)
    s = trAR / max(yPy, 1e-300) if scale else 1.0
    t = mux - s * R @ muy
    xPx = (Pt1 * (X ** 2).sum(1)).sum() - Np * mux @ mux
    sigma2 = (xPx - 2 * s * trAR + s * s * yPy) / (Np * X.shape[1])
    return R, s, t, max(float(sigma2), 1e-10)


def _affine_mstep(X, Y, P1, Pt1, PX):
    Np = max(P1.sum(), 1e-12)
    mux = Pt1 @ X / Np
    muy = P1 @ Y / Np
    A = PX.T @ Y - Np * np.outer(mux, muy)
    YPY = (Y * P1[:, None]).T @ Y - Np * np.outer(muy, muy)
    Bm = np.linalg.solve(YPY.T, A.T).T
    t = mux - Bm @ muy
    xPx = (Pt1 * (X ** 2).sum(1)).sum() - Np * mux @ mux
    sigma2 = (xPx - np.trace(A @ Bm.T)) / (Np * X.shape[1])
    return Bm, t, max(float(sigma2), 1e-10)


class Nystrom:
    """Nystrom features of the Gaussian kernel G_ij = exp(-|y_i - y_j|^2 / (2 beta^2)) from
    ``landmarks`` sampled points: features(A) (n, r) with features(A) features(B)^T ~= G(A, B).
    The same features extend the field to new points consistently."""

    def __init__(self, Y: np.ndarray, beta: float, landmarks: int,
                 rng: np.random.Generator) -> None:
        idx = np.sort(rng.choice(len(Y), min(landmarks, len(Y)), replace=False))
        self.L, self.beta = Y[idx], beta
        lam, U = np.linalg.eigh(_kernel(self.L, self.L, beta))
        keep = lam > 1e-8 * lam[-1]
        self.proj = U[:, keep] / np.sqrt(lam[keep])

    def features(self, A: np.ndarray) -> np.ndarray:
        return _kernel(A, self.L, self.beta) @ self.proj


def _kernel(A: np.ndarray, B: np.ndarray, beta: float, chunk: int = 4096) -> np.ndarray:
    out = np.empty((A.shape[0], B.shape[0]))
    bb = (B ** 2).sum(1)
    for a in range(0, A.shape[0], chunk):
        Ac = A[a:a + chunk]
        d2 = (Ac ** 2).sum(1)[:, None] + bb[None] - 2 * Ac @ B.T
        out[a:a + chunk] = np.exp(-np.maximum(d2, 0) / (2 * beta ** 2))
    return out


def cpd(source: np.ndarray, target: np.ndarray, kind: str = 'rigid', w: float = 0.1,
        max_iterations: int = 100, tolerance: float = 1e-6, scale: bool = False,
        beta: float = 2.0, lam: float = 2.0, landmarks: int = 300, max_points: int = 3000,
        seed: int = 0, normalise: bool = True, priors: np.ndarray | None = None,
        alpha: float = 1e-3, refine_points: int = 5000, fine_iterations: int = 30,
        sigma2: float | None = None, knn: int = 0, sparse_points: int = 100_000,
        sparse_iterations: int = 100, sparse_knn: int = 16) -> RegistrationResult:
    """CPD of ``source`` onto ``target`` (kind rigid | affine | nonrigid).

    ``w`` outlier weight in [0, 1); ``beta``, ``lam`` kernel width and smoothness of the
    non-rigid field (in units of the normalised data: both sets are centred and scaled to unit
    RMS radius when ``normalise``); ``max_points`` subsample size for large inputs.

    ECPD: ``priors`` (K, 2) integer pairs (source index, target index) of known
    correspondences add a fixed-assignment term weighted by sigma^2 / ``alpha`` to the M-step
    (small ``alpha``: nearly hard constraints); the subsamples always keep the prior points.

    ``knn`` > 0: sparse E-step -- each target point shares its posterior only among its ``knn``
    nearest transformed source points (pairs refreshed every 5 iterations), O((M + N) knn) per
    iteration instead of O(M N); the non-rigid field update is then over-relaxed (factor 1.9),
    which speeds up EM's slow sliding along the surface.

    Non-rigid inputs larger than ``max_points`` are refined coarse-to-fine after the first
    stage, each stage starting from the previous one's result and variance, with the sparse
    E-step (``sparse_knn`` pairs per target point; 0: all pairs): a fine stage on a subsample
    of ``refine_points`` per set for ``fine_iterations`` (0 disables), then a sparse stage on
    (a subsample of) ``sparse_points`` for ``sparse_iterations`` with a kernel half as wide
    (beta / 2, lam / 2: the residual field has finer structure), so all points of a 35k cloud
    take part and the field is fitted to the data rather than to two independent subsamples
    (0 disables).  ``sigma2`` overrides the initial variance (normalised units)."""
    t0 = time.perf_counter()
    if kind not in ('rigid', 'affine', 'nonrigid'):
        raise ValueError(f"kind={kind!r}: expected 'rigid', 'affine' or 'nonrigid'")
    Y0 = check_points('source', source)
    X0 = check_points('target', target)
    if not 0 <= w < 1:
        raise ValueError(f'w={w}: expected 0 <= w < 1')
    if beta <= 0 or lam <= 0:
        raise ValueError(f'beta={beta}, lam={lam}: expected > 0')
    if max_points < 10:
        raise ValueError(f'max_points={max_points}: expected >= 10')
    if knn < 0 or sparse_knn < 0:
        raise ValueError(f'knn={knn}, sparse_knn={sparse_knn}: expected >= 0')
    rng = np.random.default_rng(seed)
    if priors is not None:
        priors = np.asarray(priors)
        if priors.ndim != 2 or priors.shape[1] != 2 or not np.issubdtype(priors.dtype,
                                                                          np.integer):
            raise ValueError(f'priors: expected (K, 2) integer pairs, got {priors.dtype} '
                             f'{priors.shape}')
        if priors.size and (priors.min() < 0 or priors[:, 0].max() >= len(Y0)
                            or priors[:, 1].max() >= len(X0)):
            raise ValueError('priors: an index is out of range of source/target')
        if alpha <= 0:
            raise ValueError(f'alpha={alpha}: expected > 0')
    # normalisation (undone at the end): one scale for both sets
    cx, cy, sc = np.zeros(3), np.zeros(3), 1.0
    if normalise:
        Xn, Yn, cx, cy, sc = normalise_pair(X0, Y0)
    else:
        Xn, Yn = X0, Y0

    def subsample(n: int, keep: np.ndarray) -> np.ndarray:
        if n <= max_points:
            return np.arange(n)
        rest = np.setdiff1d(np.arange(n), keep)
        extra = rng.choice(rest, max(max_points - keep.size, 0), replace=False)
        return np.sort(np.concatenate([keep, extra]))
    has_priors = priors is not None and len(priors) > 0
    xi = subsample(len(Xn), np.unique(priors[:, 1]) if has_priors else np.zeros(0, int))
    yi = subsample(len(Yn), np.unique(priors[:, 0]) if has_priors else np.zeros(0, int))
    X, Y = Xn[xi], Yn[yi]
    if has_priors:     # prior pairs in subsample indices
        pm = np.searchsorted(yi, priors[:, 0])
        pn = np.searchsorted(xi, priors[:, 1])
    sigma2 = _sigma2(X, Y) if sigma2 is None else float(sigma2)
    R, s, t, Bm = np.eye(3), 1.0, np.zeros(3), np.eye(3)
    nys = Nystrom(Y, beta, landmarks, rng) if kind == 'nonrigid' else None
    Bf = nys.features(Y) if nys is not None else None
    TY = Y.copy()
    coef = np.zeros((Bf.shape[1], Y.shape[1])) if Bf is not None else None
    relax = 1.9 if knn else 1.0
    knn = min(knn, len(Y))
    pairs = None
    it, converged, prev = 0, False, np.inf
    for it in range(1, max_iterations + 1):
        if knn:
            if (it - 1) % 5 == 0:
                pairs = cKDTree(TY).query(X, k=knn, workers=-1)[1].reshape(len(X), knn)
            P1, Pt1, PX = estep_pairs(X, TY, sigma2, w, pairs)
        else:
            P1, Pt1, PX = estep(X, TY, sigma2, w)
        gP1, gPt1, gPX = P1, Pt1, PX               # the mixture part, for sigma^2
        if has_priors:
            k = sigma2 / alpha
            P1 = P1 + k * np.bincount(pm, minlength=len(Y))
            Pt1 = Pt1 + k * np.bincount(pn, minlength=len(X))
            PX = PX.copy()
            np.add.at(PX, pm, k * X[pn])
        if kind == 'rigid':
            R, s, t, sigma2 = _rigid_mstep(X, Y, P1, Pt1, PX, scale)
            TY = s * Y @ R.T + t
        elif kind == 'affine':
            Bm, t, sigma2 = _affine_mstep(X, Y, P1, Pt1, PX)
            TY = Y @ Bm.T + t
        else:
            assert Bf is not None
            d = np.maximum(P1, 1e-12)
            rhs = PX - d[:, None] * Y                       # (diag(P1) G + lam s2 I) W = rhs
            ls2 = lam * sigma2
            inner = ls2 * np.eye(Bf.shape[1]) + Bf.T @ (d[:, None] * Bf)
            Wn = (rhs - d[:, None] * (Bf @ np.linalg.solve(inner, Bf.T @ rhs))) / ls2
            coef += relax * (Bf.T @ Wn - coef)           # the field is Bf @ coef
            TY = Y + Bf @ coef
        if kind == 'nonrigid' or has_priors:    # sigma^2 of the mixture, any transform
            Np = max(gP1.sum(), 1e-12)
            sigma2 = max(float(((gPt1 * (X ** 2).sum(1)).sum() - 2 * (gPX * TY).sum()
                                + (gP1 * (TY ** 2).sum(1)).sum()) / (Np * 3)), 1e-10)
        change = abs(prev - sigma2) / max(prev, 1e-300) if np.isfinite(prev) else np.inf
        prev = sigma2
        if change < tolerance or sigma2 < 1e-9:
            converged = True
            break
    # apply to all source points, back in the input units
    if kind == 'rigid':
        A_full = s * R
        TYall = Yn @ A_full.T + t
    elif kind == 'affine':
        A_full = Bm
        TYall = Yn @ A_full.T + t
    else:
        A_full = np.eye(3)
        if len(Yn) == len(Y):
            TYall = TY
        else:   # the field G W extended to every source point by the same features
            assert nys is not None and Bf is not None
            TYall = Yn + nys.features(Yn) @ coef
    aligned = TYall * sc + cx
    tree = cKDTree(X0)
    stages = [(refine_points, fine_iterations, sparse_knn, 1.0),
              (sparse_points, sparse_iterations, sparse_knn, 0.5)]
    n_done = len(Y)
    for n_pts, n_it, n_knn, f in stages:
        # each stage runs when the coarse stage was a subsample and it adds points (the sparse
        # stage also when it only narrows the kernel on the same points)
        if kind != 'nonrigid' or len(Yn) <= len(Y) or n_it < 1 or n_pts <= len(Y) \
                or (f == 1.0 and n_pts <= n_done):
            continue
        if n_done > len(Y) or f < 1.0:   # its start variance, from the nearest distances
            sigma2 = 2 * float(np.mean(tree.query(aligned, workers=-1)[0] ** 2)) / 3 / sc ** 2
        fine = cpd(aligned, X0, 'nonrigid', w=w, max_iterations=n_it, tolerance=tolerance,
                   beta=f * beta, lam=f * lam, landmarks=landmarks, max_points=n_pts,
                   seed=seed + 1,
                   normalise=normalise, refine_points=0, sparse_points=0, sigma2=sigma2,
                   knn=n_knn, priors=priors if has_priors else None, alpha=alpha)
        aligned, n_done = fine.aligned, min(n_pts, len(Yn))
        it += fine.iterations
    T = np.eye(4)
    if kind != 'nonrigid':
        # aligned = sc * (A (y - cy) / sc + t) + cx = A y + (cx + sc t - A cy)
        T[:3, :3] = A_full
        T[:3, 3] = cx + sc * t - A_full @ cy
    dist, corr = tree.query(aligned, k=1, workers=-1)
    thr = 3 * np.sqrt(sigma2) * sc
    ok = dist <= max(thr, 1e-12)
    method = f'ecpd-{kind}' if has_priors else f'cpd-{kind}'
    return RegistrationResult(T_target_source=T, aligned=aligned, displacement=aligned - Y0,
                              correspondences=np.where(ok, corr, -1), iterations=it,
                              converged=converged,
                              residual=float(np.sqrt(np.mean(dist[ok] ** 2))) if ok.any()
                              else float('nan'), fitness=float(ok.mean()),
                              seconds=time.perf_counter() - t0, method=method)
