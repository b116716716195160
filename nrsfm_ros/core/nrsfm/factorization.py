"""Factorisation NRSfM: Tomasi-Kanade rigid with metric upgrade, and a low-rank non-rigid
alternation (rank-K shape space, orthographic cameras) with visibility weights.

Notation (METHODS.md §1): W (2F, P) tracks, S_f (3, P) shape of frame f, R_f (2, 3) orthonormal
rows, W_f = s_f R_f S_f + t_f.  S# (F, 3P) stacks each frame's x, y, z rows; rank(S#) <= K.
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
from scipy.optimize import least_squares

from ..arrays import contiguous64
from ._lowrank_kernels import camera_update, frame_moments, mean_distance, shape_step
from .result import NRSfMResult, check_tracks


def impute_low_rank(W: np.ndarray, V: np.ndarray, rank: int, iterations: int = 20
                    ) -> np.ndarray:
    """Fill the entries of W with V < 0.5 by iterated rank-``rank`` SVD (hard impute)."""
    M = np.repeat(V >= 0.5, 2, axis=0)
    if M.all():
        return W
    X = W.copy()
    mean = (W * M).sum(axis=1, keepdims=True) / np.maximum(M.sum(axis=1, keepdims=True), 1)
    X[~M] = np.broadcast_to(mean, X.shape)[~M]
    n, P = X.shape
    J = np.flatnonzero((~M).any(axis=0))          # the tracks with hidden entries
    if n > P or 2 * J.size > P:
        for _ in range(iterations):
            mu = X.mean(axis=1, keepdims=True)
            L = _rank_project(X - mu, rank) + mu      # through the smaller Gram matrix
            X[~M] = L[~M]
        return X
    # Wide tracks, hidden entries in few of them: only those columns change, so the Gram
    # matrix X X^T and the row sums are updated by their change (exact up to rounding), and
    # the rank-K projection is evaluated on those columns alone (5-8x less per iteration)
    H = ~M[:, J]
    XJ = X[:, J]
    G = X @ X.T
    rows = X.sum(axis=1)
    for _ in range(iterations):
        mu = rows / P
        E = np.linalg.eigh(G - np.outer(rows, mu))[1][:, -rank:]
        LJ = E @ (E.T @ (XJ - mu[:, None])) + mu[:, None]
        D = np.where(H, LJ - XJ, 0.0)
        A = D @ XJ.T
        G += A + A.T + D @ D.T
        rows += D.sum(axis=1)
        XJ += D
    X[:, J] = XJ
    return X


_TRIL = np.tril_indices(3)
_QIDX = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))  # q11 q12 q13 q22 q23 q33


def _upgrade_system(M_hat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear constraints C q = d on the 6 unknowns of the symmetric Q (METHODS §1.1):
    a Q a^T - b Q b^T = 0 and a Q b^T = 0 per frame, and the mean of a Q a^T + b Q b^T is 2."""
    a, b = M_hat[0::2], M_hat[1::2]
    F = a.shape[0]

    def rows(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        # coefficients of (q11 q12 q13 q22 q23 q33) in x Q y^T
        return np.stack([x[:, 0] * y[:, 0], x[:, 0] * y[:, 1] + x[:, 1] * y[:, 0],
                         x[:, 0] * y[:, 2] + x[:, 2] * y[:, 0], x[:, 1] * y[:, 1],
                         x[:, 1] * y[:, 2] + x[:, 2] * y[:, 1], x[:, 2] * y[:, 2]], axis=1)

    aa, bb, ab = rows(a, a), rows(b, b), rows(a, b)
    C = np.vstack([aa - bb, ab, np.sqrt(F) * (aa + bb).mean(axis=0, keepdims=True) / 2])
    d = np.zeros(C.shape[0])
    d[-1] = np.sqrt(F)
    return C, d


def _psd_least_squares(C: np.ndarray, d: np.ndarray, Q0: np.ndarray) -> np.ndarray:
    """argmin ||C vec(Q) - d|| over Q = L L^T (L lower-triangular, 6 parameters), by
    Levenberg-Marquardt from the Cholesky factor of the positive definite Q0."""
    def residual(p: np.ndarray) -> np.ndarray:
        L = np.zeros((3, 3))
        L[_TRIL] = p
        return C @ (L @ L.T)[_QIDX] - d

    def jacobian(p: np.ndarray) -> np.ndarray:
        L = np.zeros((3, 3))
        L[_TRIL] = p
        J = np.empty((C.shape[0], 6))
        for k, (i, j) in enumerate(zip(*_TRIL)):
            E = np.zeros((3, 3))
            E[i, j] = 1.0
            dQ = E @ L.T + L @ E.T           # d(L L^T) / d L_ij
            J[:, k] = C @ dQ[_QIDX]
        return J

    sol = least_squares(residual, np.linalg.cholesky(Q0)[_TRIL], jac=jacobian, method='lm',
                        xtol=1e-14, ftol=1e-14, gtol=1e-14, max_nfev=200)
    L = np.zeros((3, 3))
    L[_TRIL] = sol.x
    return L @ L.T


def depth_ratio(M_hat: np.ndarray, S_hat: np.ndarray, A: np.ndarray) -> float:
    """Median over frames of std(depth) / rms(in-plane extent) of the upgraded reconstruction
    (cameras from M_hat A, shape A^-1 S_hat); about 0.1-0.8 on real surfaces.  Computed from
    the 3x3 second-moment matrix of the shape, so O(F) for any number of points."""
    F = M_hat.shape[0] // 2
    R2, _ = scaled_orthonormal((M_hat @ A).reshape(F, 2, 3))
    Sc = S_hat - S_hat.mean(axis=1, keepdims=True)
    Ainv = np.linalg.inv(A)
    C = Ainv @ (Sc @ Sc.T / Sc.shape[1]) @ Ainv.T          # shape covariance, 3 x 3
    r3 = np.cross(R2[:, 0], R2[:, 1])
    depth_var = np.einsum('fi,ij,fj->f', r3, C, r3)
    inplane_var = np.einsum('fki,ij,fkj->f', R2, C, R2) / 2
    return float(np.median(np.sqrt(np.maximum(depth_var, 0.0)
                                   / np.maximum(inplane_var, 1e-300))))


def metric_upgrade(M_hat: np.ndarray, S_hat: np.ndarray | None = None,
                   max_depth_ratio: float = 1.0, degenerate_cond: float = 1e3) -> np.ndarray:
    """Corrective A (3x3) making each 2x3 block of M_hat A scaled-orthonormal (METHODS §1.1).

    1. Linear least squares for Q = A A^T from  a Q a^T - b Q b^T = 0,  a Q b^T = 0  per frame
       and a mean-scale constraint.
    2. If that Q is not positive definite, the PSD Q minimising the same residual:
       Q = L L^T, Levenberg-Marquardt on the 6 entries of L, started from the linear Q projected
       onto the PSD cone with its eigenvalues floored at 1e-3 x the largest.
    3. Bound (needs the shape factor ``S_hat``, W ~= M_hat S_hat).  With small camera motion or
       a (nearly) planar surface the PSD optimum is (close to) rank 2, and A^-1 stretches the
       recovered shape along the viewing direction without limit (the bas-relief ambiguity:
       clipping a negative eigenvalue to 1e-9 gave depths ~1000x too large).  The eigenvalues
       of Q are floored at tau x the largest, tau >= 1e-9, and tau is raised (bisection in
       log tau) until the implied depth extent ``depth_ratio`` (median std of depth over rms
       in-plane extent; the rms of a frame's image extent is what the data measure) is at most
         * ``max_depth_ratio`` (default 1.0: depth no larger than the in-plane extent) when
           the upgrade is degenerate: cond(Q) > ``degenerate_cond`` (1e3; well-posed data give
           1-50) or the linear Q was not positive definite;
         * 4 x ``max_depth_ratio`` otherwise (a surface tilted by up to ~75 degrees).
       The bound is inactive on well-conditioned data, so noise-free rigid tracks under varied
       camera motion stay exact.  If the ratio exceeds the bound even at tau = 1 (A a scaled
       rotation, the shape of the SVD), that A is returned.
    """
    M_hat = np.asarray(M_hat, dtype=float)
    if M_hat.ndim != 2 or M_hat.shape[1] != 3 or M_hat.shape[0] % 2 or M_hat.shape[0] < 4:
        raise ValueError(f'M_hat: expected shape (2F, 3) with F >= 2, got {M_hat.shape}')
    if not max_depth_ratio > 0:
        raise ValueError(f'max_depth_ratio={max_depth_ratio}: expected > 0')
    C, d = _upgrade_system(M_hat)
    q = np.linalg.lstsq(C, d, rcond=None)[0]
    Q = np.zeros((3, 3))
    Q[_QIDX] = q
    Q = Q + np.triu(Q, 1).T
    lam, E = np.linalg.eigh(Q)
    linear_pd = lam[0] > 1e-12 * abs(lam[-1])
    if lam[-1] <= 0:                         # no positive direction: fall back to the scale alone
        lam = np.ones(3)
    if not linear_pd:
        Q0 = (E * np.maximum(lam, 1e-3 * lam.max())) @ E.T
        lam, E = np.linalg.eigh(_psd_least_squares(C, d, Q0))
    lam = np.maximum(lam, 0.0)
    top = max(float(lam[-1]), 1e-300)

    def corrective(tau: float) -> np.ndarray:
        return E * np.sqrt(np.maximum(lam, tau * top))

    tau_min = 1e-9
    A = corrective(tau_min)
    if S_hat is None:
        return A
    degenerate = (not linear_pd) or lam[0] < top / degenerate_cond
    bound = max_depth_ratio * (1.0 if degenerate else 4.0)
    if depth_ratio(M_hat, S_hat, A) <= bound:
        return A
    if depth_ratio(M_hat, S_hat, corrective(1.0)) > bound:
        return corrective(1.0)
    lo, hi = np.log(tau_min), 0.0            # ratio(lo) > bound >= ratio(hi)
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if depth_ratio(M_hat, S_hat, corrective(float(np.exp(mid)))) > bound:
            lo = mid
        else:
            hi = mid
    return corrective(float(np.exp(hi)))


def scaled_orthonormal(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest s_f R_f for each 2x3 block M_f (F, 2, 3): polar decomposition, batched."""
    U, sig, Vt = np.linalg.svd(M, full_matrices=False)
    return U @ Vt, sig.mean(axis=1)


def complete_rotations(R2: np.ndarray) -> np.ndarray:
    """(F, 2, 3) orthonormal rows -> (F, 3, 3) rotations (third row = r1 x r2)."""
    return np.concatenate([R2, np.cross(R2[:, 0], R2[:, 1])[:, None]], axis=1)


def _centre(W: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    wsum = np.maximum(V.sum(axis=1), 1e-12)
    t = np.stack([(W[0::2] * V).sum(axis=1), (W[1::2] * V).sum(axis=1)], axis=1) / wsum[:, None]
    return W - t.reshape(-1, 1), t


def _rank3_factors(Wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rank-3 factors M_hat (2F, 3) = U3 sqrt(s3), S_hat (3, P) = sqrt(s3) V3^T of the centred
    tracks, through the 2F x 2F Gram matrix (the full SVD of a 2F x P matrix is far slower)."""
    lam, U = np.linalg.eigh(Wc @ Wc.T)
    lam, U = lam[::-1][:3], U[:, ::-1][:, :3]
    sv = np.sqrt(np.maximum(lam, 0.0))
    S_hat = (U.T @ Wc) / np.maximum(np.sqrt(sv), 1e-300)[:, None]
    return U * np.sqrt(sv), S_hat


ROBUST_LOSSES = ('huber', 'cauchy')


def rigid(W: np.ndarray, V: np.ndarray | None = None, robust: float = 0.0,
          robust_rounds: int = 3, loss: str = 'huber') -> NRSfMResult:
    """Tomasi-Kanade: rank-3 factorisation + metric upgrade; one rigid shape for all frames.

    ``robust`` > 0: then ``robust_rounds`` rounds of iteratively reweighted least squares on
    every entry's reprojection distance r with the weights of ``loss``: ``huber`` min(1, k / r)
    or ``cauchy`` 1 / (1 + (r / k)^2) (redescending: an entry many k off counts next to
    nothing), k = ``robust`` x the robust spread (1.4826 x median of r over the visible
    entries, at least 0.5 px), so that gross track errors and the part of a deformation one
    rigid shape cannot follow pull the shape less.  ``residual_px`` stays the mean distance
    under the given visibility."""
    t0 = time.perf_counter()
    W, V = _every_frame_seen(*check_tracks(W, V), 'rigid')
    if robust < 0 or not np.isfinite(robust):
        raise ValueError(f'robust: expected a finite value >= 0 (0: off), got {robust}')
    if robust_rounds < 0:
        raise ValueError(f'robust_rounds: expected >= 0, got {robust_rounds}')
    if loss not in ROBUST_LOSSES:
        raise ValueError(f'loss: expected one of {ROBUST_LOSSES}, got {loss!r}')
    res = _rigid(W, V)
    if robust == 0 or robust_rounds == 0:
        return replace(res, seconds=time.perf_counter() - t0)
    seen = V >= 0.5
    for _ in range(robust_rounds):
        r = _entry_residuals(res, W)
        k = max(robust * 1.4826 * float(np.median(r[seen])), 0.5)
        w = np.minimum(1.0, k / np.maximum(r, 1e-12)) if loss == 'huber' else \
            1.0 / (1.0 + (r / k) ** 2)
        Vw = np.maximum(V * w, 1e-3 * V)
        res = _rigid(W, Vw)
    r = _entry_residuals(res, W)
    return replace(res, residual_px=float((r * V).sum() / max(V.sum(), 1e-12)),
                   iterations=res.iterations * (robust_rounds + 1),
                   seconds=time.perf_counter() - t0)


def _every_frame_seen(W: np.ndarray, V: np.ndarray, method: str
                      ) -> tuple[np.ndarray, np.ndarray]:
    """W, V as they are; a ValueError naming the frames where V sees no point (their cameras
    are undetermined: the factorisations' translations and Procrustes fits divide by nothing
    there; ``bmm`` and the other methods fill such frames from the rest)."""
    empty = np.flatnonzero(V.sum(axis=1) == 0)
    if empty.size:
        raise ValueError(f'V: frame(s) {empty[:10].tolist()} see no point (all weights 0); '
                         f'{method} needs every frame to see points: drop those frames or '
                         f'use another method')
    return W, V


def _entry_residuals(res: NRSfMResult, W: np.ndarray) -> np.ndarray:
    """(F, P) image distance between each track entry and its reprojection."""
    F = res.S.shape[0]
    pred = res.scale[:, None, None] * res.S[:, :, :2].transpose(0, 2, 1) + res.t[:, :, None]
    return np.linalg.norm(pred - W.reshape(F, 2, -1), axis=1)


FULL_TRACKS = 50     # _rigid: this many tracks visible in every frame are enough to factorise
#   on (a rank-3 factorisation needs few; imputing the rest instead failed where the tracker's
#   gross errors are hidden: the face at 60 deg through the tracker, only its observations
#   within 1 px of the truth kept visible, 410 of 4171 tracks fully visible: e3D 0.77 imputed,
#   0.056 factorised on them)


def _rigid(W: np.ndarray, V: np.ndarray) -> NRSfMResult:
    t0 = time.perf_counter()
    F, P = V.shape
    # factorise the fully visible tracks when there are enough (imputing a track seen in few
    # frames gives garbage that corrupts the SVD); otherwise impute the missing entries
    full = V.min(axis=0) >= 0.5
    if full.sum() >= min(FULL_TRACKS, max(8, P // 5)):
        Wsub = W[:, full]
    else:
        Wsub = impute_low_rank(W, V, 3)
    Wc_sub, t = _centre(Wsub, np.ones((F, Wsub.shape[1])))
    M_hat, S_hat = _rank3_factors(Wc_sub)
    A = metric_upgrade(M_hat, S_hat)
    R2, scale = scaled_orthonormal((M_hat @ A).reshape(F, 2, 3))
    Wf = W.reshape(F, 2, P)
    # refine shape, cameras and translations jointly (exact for noise-free data); the steps
    # read the tracks only as the weighted centred tracks v_fp (w_fp - t_f), and the
    # translations' sums over the points are matrix products
    WV = Wf * V[:, None, :]
    WV_sum, V_sum = WV.sum(axis=2), V.sum(axis=1)
    S0 = None
    for _ in range(4):
        WVc = (WV - t[:, :, None] * V[:, None, :]).reshape(2 * F, P)
        S0 = _rigid_shape_step(WVc, V, R2, scale, prior=S0)
        R2, scale = _rigid_camera_step(WVc, V, S0)
        pred_sum = np.einsum('fki,if->fk', R2 * scale[:, None, None], S0 @ V.T)
        t = (WV_sum - pred_sum) / V_sum[:, None]
    Wc = (Wf - t[:, :, None]).reshape(2 * F, P)
    R = complete_rotations(R2)
    S = np.ascontiguousarray((R.reshape(3 * F, 3) @ S0).reshape(F, 3, P).transpose(0, 2, 1))
    res = _residual(Wc, V, R2, scale, S0)
    return NRSfMResult(S=S, R=R, scale=scale, t=t, method='rigid', rank=1, residual_px=res,
                       iterations=4, converged=True, seconds=time.perf_counter() - t0)


def _solve_rigid_shape(Wc: np.ndarray, V: np.ndarray, R2: np.ndarray, scale: np.ndarray,
                       prior: np.ndarray | None = None, prior_weight: float = 1e-4
                       ) -> np.ndarray:
    """Least-squares rigid shape (3, P) for known cameras: per point
    (sum_f v_fp G_f + mu_p I) S_p = sum_f v_fp sR_f^T w_fp + mu_p prior_p,  G_f = sR_f^T sR_f.

    With near-identical cameras the viewing direction is observed only through the small
    spread of the cameras, and the depth of each point would amplify noise without limit.  With
    a ``prior`` shape (the previous estimate), mu_p = prior_weight x trace(A_p) / 2 holds each
    point's depth there when the spread is below ~sqrt(prior_weight) rad (0.6 degrees) and is
    negligible otherwise; the prior is a fixed point on exact data.  Without one, a 1e-9 ridge
    keeps tracks seen in too few frames near the centroid instead of arbitrary."""
    F, P = V.shape
    return _rigid_shape_step((Wc.reshape(F, 2, P) * V[:, None, :]).reshape(2 * F, P), V, R2,
                             scale, prior, prior_weight)


def _rigid_shape_step(WVc: np.ndarray, V: np.ndarray, R2: np.ndarray, scale: np.ndarray,
                      prior: np.ndarray | None = None, prior_weight: float = 1e-4
                      ) -> np.ndarray:
    """``_solve_rigid_shape`` from the weighted centred tracks WVc (2F, P) = v_fp w_fp."""
    sR = R2 * scale[:, None, None]  # F x 2 x 3
    F, P = V.shape
    G = np.einsum('fki,fkj->fij', sR, sR)
    # the two sums over frames as matrix products (BLAS; ~10x the einsums at 10k tracks)
    A = (V.T @ G.reshape(F, 9)).reshape(P, 3, 3)
    b = (sR.transpose(2, 0, 1).reshape(3, 2 * F) @ WVc).T
    if prior is None:
        A = A + 1e-9 * float(np.trace(G.mean(axis=0))) * np.eye(3)
    else:
        mu = prior_weight * np.trace(A, axis1=1, axis2=2) / 2 \
            + 1e-9 * float(np.trace(G.mean(axis=0)))
        A = A + mu[:, None, None] * np.eye(3)
        b = b + mu[:, None] * prior.T
    return np.linalg.solve(A, b[..., None])[..., 0].T


def _rigid_camera_step(WVc: np.ndarray, V: np.ndarray, S0: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Per frame, s_f R_f for w_fp ~= s R S_p (one rigid shape ``S0`` (3, P)) from the weighted
    centred tracks WVc (2F, P) = v_fp w_fp: weighted least squares for the 2x3 motion block
    M_f, then its nearest scaled-orthonormal matrix (polar decomposition; exact on clean data).
    The frames' normal equations are two BLAS products over the points (per-frame batched
    products of an (F, 3, P) copy were ~10x slower)."""
    F, P = V.shape
    WSt = (WVc @ S0.T).reshape(F, 2, 3)
    SSt = (V @ (S0[:, None, :] * S0[None, :, :]).reshape(9, P).T).reshape(F, 3, 3)
    # a relative ridge: a (nearly) planar shape leaves M's normal component at 0, not arbitrary
    SSt = SSt + (1e-12 * np.trace(SSt, axis1=1, axis2=2) + 1e-300)[:, None, None] * np.eye(3)
    M = np.linalg.solve(SSt, WSt.transpose(0, 2, 1)).transpose(0, 2, 1)
    R2, scale = scaled_orthonormal(M)
    return R2, scale


def _residual(Wc: np.ndarray, V: np.ndarray, R2: np.ndarray, scale: np.ndarray,
              S0: np.ndarray) -> float:
    """Mean image distance of the visible entries from the rigid shape ``S0`` (3, P)."""
    F, P = V.shape
    r = Wc.reshape(F, 2, P) - ((R2 * scale[:, None, None]).reshape(2 * F, 3) @ S0
                               ).reshape(F, 2, P)
    d = np.hypot(r[:, 0], r[:, 1])
    return float((d * V).sum() / max(V.sum(), 1e-12))


def _object_frame(R: np.ndarray, S: np.ndarray) -> np.ndarray:
    """R_f^T S_fp for camera-frame shapes S (F, P, 3): (F, 3, P) (a batched product: the
    einsum was ~30x slower at 15 x 10k)."""
    return R.transpose(0, 2, 1) @ S.transpose(0, 2, 1)


def _rank_project(Ssharp: np.ndarray, rank: int) -> np.ndarray:
    """Best rank-K approximation of S# (F, 3P) through the smaller Gram matrix."""
    F, N = Ssharp.shape
    if F <= N:
        E = np.linalg.eigh(Ssharp @ Ssharp.T)[1][:, -rank:]
        return E @ (E.T @ Ssharp)
    E = np.linalg.eigh(Ssharp.T @ Ssharp)[1][:, -rank:]
    return (Ssharp @ E) @ E.T


def low_rank(W: np.ndarray, V: np.ndarray | None = None, rank: int = 3, iterations: int = 60,
             rho: float = 1e-2, rho_growth: float = 1.15, tol: float = 1e-7,
             init: NRSfMResult | None = None) -> NRSfMResult:
    """Low-rank NRSfM with metric upgrade: rigid initialisation, then alternation of
    (a) per-frame shapes closest to the data and to the rank-K shape space (closed form,
        visibility-weighted), (b) rank-K projection of S#, (c) orthographic cameras by
        Procrustes, and (d) translations.  The penalty rho grows each iteration, so the final
        shapes satisfy the rank constraint.  Linear in P per iteration.

    ``init`` warm-starts cameras and shapes (used by the sliding window).
    """
    t0 = time.perf_counter()
    W, V = _every_frame_seen(*check_tracks(W, V), 'lowrank')
    F, P = V.shape
    if rank < 1:
        raise ValueError(f'rank: expected >= 1, got {rank}')
    rank = min(rank, F)
    if init is None:
        base = rigid(W, V)
        R2, scale, t = base.R[:, :2], base.scale, base.t
        Z = _object_frame(base.R, base.S)  # object-frame shapes F x 3 x P
    else:
        R2, scale, t = init.R[:, :2].copy(), init.scale.copy(), init.t.copy()
        Z = _object_frame(init.R, init.S)
    # normalise image units so rho means the same at any resolution
    unit = max(float(np.sqrt(np.mean(((W.reshape(F, 2, P) - t[:, :, None]) ** 2)))), 1e-12)
    Wn = W / unit
    tn = t / unit
    Z = Z / unit
    Wf, V = contiguous64(Wn.reshape(F, 2, P), V)
    Z = np.ascontiguousarray(Z)
    prev = np.inf
    it = 0
    converged = False
    sR = R2 * scale[:, None, None]
    lam, E = np.linalg.eigh(np.einsum('fki,fkj->fij', sR, sR))
    for it in range(1, iterations + 1):
        # (a) S_f = argmin sum_p v_fp ||w - t - sR S||^2 + rho ||S - Z||^2   (3x3 per point,
        # through each frame's eigenbasis of G = sR^T sR, rank 2)
        S = shape_step(Wf, V, tn, sR, E, lam, Z, rho)
        # (b) rank-K projection of S# (F x 3P)
        Z = _rank_project(S.reshape(F, 3 * P), rank).reshape(F, 3, P)
        # (c) cameras by Procrustes on the centred tracks u = w - t, (d) translations, and the
        # data error, all from per-frame moments of u and Z; the next step's eigenbases
        R2, scale, tn_new, E, lam, err = camera_update(*frame_moments(Wf, V, tn, Z), tn)
        sR = R2 * scale[:, None, None]
        tn = tn_new
        rho *= rho_growth
        if abs(prev - err) <= tol * max(err, 1e-12) and it > 5:
            converged = True
            break
        prev = err
    res = unit * mean_distance(Wf, V, tn, R2 * scale[:, None, None], Z)
    S = Z * unit
    R = complete_rotations(R2)
    S_cam = S.transpose(0, 2, 1) @ R.transpose(0, 2, 1)           # R_f S_f, F x P x 3
    return NRSfMResult(S=S_cam, R=R, scale=scale, t=tn * unit, method='lowrank', rank=rank,
                       residual_px=res, iterations=it, converged=converged,
                       seconds=time.perf_counter() - t0)
