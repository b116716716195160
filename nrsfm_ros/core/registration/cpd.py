"""Coherent Point Drift (Myronenko & Song; METHODS §9): rigid, affine and non-rigid.

The target X (N, D) is a Gaussian-mixture sample of the transformed source Y (M, D) plus a
uniform outlier component of weight ``w``.  One EM core (``em``) serves every transform kind:
the E-step posteriors P (M, N) are computed in row chunks (two passes: the per-target
normaliser, then P's sums), so memory stays O(chunk x N), or restricted to k nearest pairs;
each kind is one M-step class (``RigidStep``, ``AffineStep``, ``NonrigidStep``) with the closed
forms of the paper.  Non-rigid: the displacement field is G W with the Gaussian kernel G (width
``beta``) approximated by a Nystrom factor G ~= B B^T (``landmarks`` columns), so each M-step is
a Woodbury solve in O(M r^2) instead of O(M^3).

Large inputs are registered coarse-to-fine, as a list of stages run in one loop, each starting
from the previous one's positions: CPD on a random subsample of at most ``max_points`` per set,
then (rigid, affine) the transform is applied to all points, and (non-rigid) the displacement is
extended to every source point by the same kernel features, followed by the fine and sparse
stages (see ``cpd``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .base import (RegistrationResult, check_param, check_points, check_priors, make_result,
                   normalise_pair, resolve_threshold)
from .kernels import Nystrom, gaussian_kernel  # noqa: F401  (Nystrom: used by nrsfm.cdf too)


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


class RigidStep:
    """Rigid (optionally scaled) M-step: x = s R y + t."""

    def __init__(self, scale: bool) -> None:
        self.scale = scale
        self.A, self.t = np.eye(3), np.zeros(3)
        self.own_sigma2 = True               # the closed form gives the variance too

    def mstep(self, X: np.ndarray, Y: np.ndarray, P1: np.ndarray, Pt1: np.ndarray,
              PX: np.ndarray, sigma2: float) -> tuple[np.ndarray, float]:
        Np = max(P1.sum(), 1e-12)
        mux, muy = Pt1 @ X / Np, P1 @ Y / Np
        A = PX.T @ Y - Np * np.outer(mux, muy)          # (D, D) = Xh^T P^T Yh
        U, _, Vt = np.linalg.svd(A)
        C = np.eye(X.shape[1])
        C[-1, -1] = np.sign(np.linalg.det(U @ Vt))
        R = U @ C @ Vt
        yPy = (P1 * (Y ** 2).sum(1)).sum() - Np * muy @ muy
        trAR = np.trace(A.T @ R)
        s = trAR / max(yPy, 1e-300) if self.scale else 1.0
        self.A, self.t = s * R, mux - s * R @ muy
        xPx = (Pt1 * (X ** 2).sum(1)).sum() - Np * mux @ mux
        s2 = (xPx - 2 * s * trAR + s * s * yPy) / (Np * X.shape[1])
        return self.apply(Y), max(float(s2), 1e-10)

    def apply(self, Y: np.ndarray) -> np.ndarray:
        return Y @ self.A.T + self.t


class AffineStep(RigidStep):
    """Affine M-step: x = B y + t."""

    def __init__(self) -> None:
        super().__init__(scale=False)

    def mstep(self, X: np.ndarray, Y: np.ndarray, P1: np.ndarray, Pt1: np.ndarray,
              PX: np.ndarray, sigma2: float) -> tuple[np.ndarray, float]:
        Np = max(P1.sum(), 1e-12)
        mux, muy = Pt1 @ X / Np, P1 @ Y / Np
        A = PX.T @ Y - Np * np.outer(mux, muy)
        YPY = (Y * P1[:, None]).T @ Y - Np * np.outer(muy, muy)
        self.A = np.linalg.solve(YPY.T, A.T).T
        self.t = mux - self.A @ muy
        xPx = (Pt1 * (X ** 2).sum(1)).sum() - Np * mux @ mux
        s2 = (xPx - np.trace(A @ self.A.T)) / (Np * X.shape[1])
        return self.apply(Y), max(float(s2), 1e-10)


class NonrigidStep:
    """Non-rigid M-step: x = y + G W, G ~= B B^T in the Nystrom features B of the stage's
    source points; the field extends to any point by the same features.  ``relax`` > 1
    over-relaxes the update (used with the sparse E-step)."""

    own_sigma2 = False                       # the variance comes from the mixture

    def __init__(self, Y: np.ndarray, beta: float, lam: float, landmarks: int,
                 rng: np.random.Generator, relax: float) -> None:
        self.nys = Nystrom(Y, beta, landmarks, rng)
        self.B = self.nys.features(Y)
        self.coef = np.zeros((self.B.shape[1], Y.shape[1]))
        self.lam, self.relax = lam, relax

    def mstep(self, X: np.ndarray, Y: np.ndarray, P1: np.ndarray, Pt1: np.ndarray,
              PX: np.ndarray, sigma2: float) -> tuple[np.ndarray, float]:
        B = self.B
        d = np.maximum(P1, 1e-12)
        rhs = PX - d[:, None] * Y                       # (diag(P1) G + lam s2 I) W = rhs
        ls2 = self.lam * sigma2
        inner = ls2 * np.eye(B.shape[1]) + B.T @ (d[:, None] * B)
        Wn = (rhs - d[:, None] * (B @ np.linalg.solve(inner, B.T @ rhs))) / ls2
        self.coef += self.relax * (B.T @ Wn - self.coef)     # the field is B @ coef
        return Y + B @ self.coef, sigma2

    def apply(self, Y: np.ndarray) -> np.ndarray:
        return Y + self.nys.features(Y) @ self.coef


Step = RigidStep | AffineStep | NonrigidStep


def mixture_sigma2(X: np.ndarray, TY: np.ndarray, P1: np.ndarray, Pt1: np.ndarray,
                   PX: np.ndarray) -> float:
    Np = max(P1.sum(), 1e-12)
    return max(float(((Pt1 * (X ** 2).sum(1)).sum() - 2 * (PX * TY).sum()
                      + (P1 * (TY ** 2).sum(1)).sum()) / (Np * X.shape[1])), 1e-10)


def em(X: np.ndarray, Y: np.ndarray, step: Step, sigma2: float, w: float, max_iterations: int,
       tolerance: float, knn: int = 0, priors: tuple[np.ndarray, np.ndarray] | None = None,
       alpha: float = 1e-3) -> tuple[np.ndarray, float, int, bool]:
    """EM of the CPD mixture for one M-step kind: (TY, sigma2, iterations, converged).

    ``knn`` > 0: sparse E-step among the knn nearest transformed source points of each target
    point (refreshed every 5 iterations).  ``priors`` (source rows, target rows) of known
    matches add a fixed-assignment term of weight sigma^2 / ``alpha`` (ECPD); the variance is
    then taken from the mixture part alone."""
    TY = Y.copy()
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
        if priors is not None:
            pm, pn = priors
            k = sigma2 / alpha
            P1 = P1 + k * np.bincount(pm, minlength=len(Y))
            Pt1 = Pt1 + k * np.bincount(pn, minlength=len(X))
            PX = PX.copy()
            np.add.at(PX, pm, k * X[pn])
        TY, sigma2 = step.mstep(X, Y, P1, Pt1, PX, sigma2)
        if not step.own_sigma2 or priors is not None:
            sigma2 = mixture_sigma2(X, TY, gP1, gPt1, gPX)
        change = abs(prev - sigma2) / max(prev, 1e-300) if np.isfinite(prev) else np.inf
        prev = sigma2
        if change < tolerance or sigma2 < 1e-9:
            converged = True
            break
    return TY, sigma2, it, converged


@dataclass(frozen=True)
class Stage:
    """One pass of EM: at most ``points`` per set, ``iterations``, ``knn`` pairs (0: all),
    the kernel scaled by ``kernel`` (beta and lam), and whether the variance restarts from the
    nearest distances (``restart``) or carries over from the previous stage."""

    points: int
    iterations: int
    knn: int
    kernel: float
    restart: bool


def plan_stages(kind: str, n_source: int, max_points: int, max_iterations: int, knn: int,
                refine_points: int, fine_iterations: int, sparse_points: int,
                sparse_iterations: int, sparse_knn: int) -> list[Stage]:
    """The coarse stage, then (non-rigid, when the coarse stage was a subsample) a fine stage on
    ``refine_points`` and a sparse stage on ``sparse_points`` with a kernel half as wide, each
    only when it adds points (the sparse one also when it only narrows the kernel)."""
    stages = [Stage(max_points, max_iterations, knn, 1.0, False)]
    coarse = min(max_points, n_source)
    if kind != 'nonrigid' or n_source <= coarse:
        return stages
    if fine_iterations >= 1 and refine_points > coarse:
        stages.append(Stage(refine_points, fine_iterations, sparse_knn, 1.0, False))
    if sparse_iterations >= 1 and sparse_points > coarse:
        stages.append(Stage(sparse_points, sparse_iterations, sparse_knn, 0.5, True))
    return stages


def cpd(source: np.ndarray, target: np.ndarray, kind: str = 'rigid', w: float = 0.1,
        max_iterations: int = 100, tolerance: float = 1e-6, scale: bool = False,
        beta: float = 2.0, lam: float = 2.0, landmarks: int = 300, max_points: int = 3000,
        seed: int = 0, normalise: bool = True, priors: np.ndarray | None = None,
        alpha: float = 1e-3, refine_points: int = 5000, fine_iterations: int = 30,
        sigma2: float | None = None, knn: int = 0, sparse_points: int = 100_000,
        sparse_iterations: int = 100, sparse_knn: int = 16, inlier_threshold: float = 0.0
        ) -> RegistrationResult:
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
    stage (``plan_stages``), each stage starting from the previous one's positions, with the
    sparse E-step (``sparse_knn`` pairs per target point; 0: all pairs): a fine stage on a
    subsample of ``refine_points`` per set for ``fine_iterations`` (0 disables), then a sparse
    stage on (a subsample of) ``sparse_points`` for ``sparse_iterations`` with a kernel half as
    wide (beta / 2, lam / 2: the residual field has finer structure), its variance restarted
    from the nearest distances (0 disables).  ``sigma2`` overrides the initial variance
    (normalised units).  ``inlier_threshold``: the distance of the reported fitness and inlier
    RMSE (``base``)."""
    t0 = time.perf_counter()
    if kind not in ('rigid', 'affine', 'nonrigid'):
        raise ValueError(f"kind={kind!r}: expected 'rigid', 'affine' or 'nonrigid'")
    Y0 = check_points('source', source)
    X0 = check_points('target', target)
    for name, value in (('w', w), ('beta', beta), ('lam', lam), ('tolerance', tolerance),
                        ('max_iterations', max_iterations)):
        check_param(name, value)
    if max_points < 10:
        raise ValueError(f'max_points={max_points}: expected >= 10')
    if knn < 0 or sparse_knn < 0:
        raise ValueError(f'knn={knn}, sparse_knn={sparse_knn}: expected >= 0')
    if priors is not None and alpha <= 0:
        raise ValueError(f'alpha={alpha}: expected > 0')
    priors = check_priors(priors, len(Y0), len(X0))
    threshold = resolve_threshold(X0, inlier_threshold)
    cx, cy, sc = np.zeros(3), np.zeros(3), 1.0     # normalisation, undone at the end
    Xn, Yn = (X0, Y0)
    if normalise:
        Xn, Yn, cx, cy, sc = normalise_pair(X0, Y0)
    cur = Yn                                       # the source's current positions
    A, t = np.eye(3), np.zeros(3)                  # rigid / affine: cur = Yn A^T + t
    total, converged = 0, False
    stages = plan_stages(kind, len(Yn), max_points, max_iterations, knn, refine_points,
                         fine_iterations, sparse_points, sparse_iterations, sparse_knn)
    keep_y = np.unique(priors[:, 0]) if priors is not None else np.zeros(0, np.intp)
    keep_x = np.unique(priors[:, 1]) if priors is not None else np.zeros(0, np.intp)
    for i, st in enumerate(stages):
        # a refinement stage works in the frame of the current pair (its kernel in units of
        # their RMS radius, its translation centred away)
        Xs, Ys, fx, fy, fs = (Xn, cur, np.zeros(3), np.zeros(3), 1.0) if i == 0 \
            else normalise_pair(Xn, cur)
        rng = np.random.default_rng(seed if i == 0 else seed + 1)
        xi = _subsample(len(Xs), st.points, keep_x, rng)
        yi = _subsample(len(Ys), st.points, keep_y, rng)
        X, Y = Xs[xi], Ys[yi]
        if i == 0:
            sigma2 = _sigma2(X, Y) if sigma2 is None else float(sigma2)
        elif st.restart:                           # from the nearest distances
            sigma2 = 2 * float(np.mean(cKDTree(Xs).query(Ys, workers=-1)[0] ** 2)) / 3
        else:
            sigma2 /= fs ** 2
        pairs = None if priors is None else (np.searchsorted(yi, priors[:, 0]),
                                             np.searchsorted(xi, priors[:, 1]))
        step: Step = RigidStep(scale) if kind == 'rigid' else AffineStep() \
            if kind == 'affine' else NonrigidStep(Y, st.kernel * beta, st.kernel * lam,
                                                  landmarks, rng, 1.9 if st.knn else 1.0)
        TY, sigma2, it, converged = em(X, Y, step, sigma2, w, st.iterations, tolerance,
                                       st.knn, pairs, alpha)
        total += it
        cur = (TY if len(yi) == len(Ys) else step.apply(Ys)) * fs + fx
        sigma2 *= fs ** 2
        if kind != 'nonrigid':                     # one stage: cur = Yn A^T + t
            A, t = step.A, step.t
    aligned = cur * sc + cx
    T = np.eye(4)
    if kind != 'nonrigid':
        # aligned = sc * (A (y - cy) / sc + t) + cx = A y + (cx + sc t - A cy)
        T[:3, :3] = A
        T[:3, 3] = cx + sc * t - A @ cy
    method = f'ecpd-{kind}' if priors is not None else f'cpd-{kind}'
    return make_result(Y0, aligned, T, cKDTree(X0), threshold, method, total, converged, t0)


def _subsample(n: int, m: int, keep: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Sorted indices of at most ``m`` of ``n`` points, always including ``keep``."""
    if n <= m:
        return np.arange(n)
    rest = np.setdiff1d(np.arange(n), keep)
    extra = rng.choice(rest, max(m - keep.size, 0), replace=False)
    return np.sort(np.concatenate([keep, extra]))
