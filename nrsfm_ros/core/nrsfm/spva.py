"""SPVA: shape-prior variational NRSfM for severe occlusions (METHODS.md section 4; Golyanik,
Fetzer, Stricker, WACV 2017), the variational energy of ``va`` plus a shape prior weighted per
pixel by the occlusion tensor O = 1 - V.

1. **Frame selection** (total-intensity criterion): frames are scored by their summed occlusion
   sum_p O_fp (:func:`total_occlusion`); the ``prior_frames`` lowest of the initial batch
   (:func:`select_prior_frames`) give the prior.
2. **Prior**: the object-frame shapes of an initial reconstruction (any batch method) of those
   frames, aligned by similarity Procrustes and averaged: T (P, 3).  The batch's shapes aligned
   to T span the low-rank shape subspace B (``rank`` right singular vectors, uncentred, so the
   mean shape lies in it).
3. **Per frame** (:meth:`ShapePrior.step`, streaming once the prior exists), over the object-frame
   shape X (P, 3) for the orthographic camera (rows R2, scale s, translation t):

       E(X) = 1/2 sum_p v_p ||w_p - s R2 X_p - t||^2                 (data, visible tracks)
            + mu sum_(i,j) in G h_eps(X_i - X_j)                      (Huber-TV on the track grid)
            + lam/2 ||(I - B^T B) vec X||^2                           (low rank: off the subspace)
            + gamma/2 sum_p o_p ||X_p - T_p||^2                       (prior, occlusion-weighted)

   with o_p from the occlusion tensor by ``weighting``: ``pixel`` o_p = 1 - v_p, ``frame`` the
   frame's mean occlusion for every pixel, ``sequence`` 1 everywhere (gamma alone).  Linearised
   ADMM as ``va.va_shapes``: splits Z = X (the low-rank prox: the subspace part kept, the rest
   shrunk by rho / (rho + lam)) and Q = D X (group Huber shrinkage per edge); the X-step is a
   closed form per pixel, the prior adding gamma o_p to the diagonal:
   (c_p I + v_p s^2 R2^T R2)^-1 = (I - R2^T R2) / c_p + R2^T R2 / (c_p + v_p s^2),
   c_p = rho + rho_tv ||D||^2 + gamma o_p.  The start is the least-squares fit of the subspace to
   the visible tracks; the camera is fitted (weighted orthographic Procrustes, ``dspr._fit``) to
   the previous frame's shape, then once more to the solution, which is refined again.  The
   scaled duals (U, U2) start from the previous solve's: consecutive frames are nearly the same
   problem, so 10 warm-started iterations per frame match 20 cold ones (the latency).
4. **Refresh** (``refresh`` > 0): after each frame, T_p += refresh v_p (X_p - T_p): the prior
   follows the surface where it is seen and keeps its last seen state where it is hidden.

Units: shapes in image pixels of the initial batch, so ``gamma`` and ``lam`` are relative to the
data weight and ``eps`` is in pixels.  The cost per frame is O((K + edges) P) per iteration
(edges about 2P), no P x P operator.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .dspr import _align, _check_frame, _fit, object_shapes
from .result import NRSfMResult, check_tracks
from .va import _norm2, grid_graph

WEIGHTINGS = ('pixel', 'frame', 'sequence')
RHO = 1.0          # ADMM penalty of the low-rank split (relative to the data weight)
RHO_TV = 0.25      # ... of the TV split
EPS_PX = 1.0       # Huber threshold (px per edge): quadratic below, so smooth parts stay smooth


def total_occlusion(V: np.ndarray) -> np.ndarray:
    """The total-intensity criterion: sum_p (1 - V_fp) per frame (F,) of the visibility V
    (F, P) in [0, 1] (the occlusion tensor is 1 - V)."""
    V = np.asarray(V, dtype=np.float64)
    if V.ndim != 2 or np.isnan(V).any() or (V < 0).any() or (V > 1).any():
        raise ValueError(f'V: expected (F, P) values in [0, 1], got shape {V.shape}')
    return (1.0 - V).sum(axis=1)


def select_prior_frames(V: np.ndarray, count: int, among: int | None = None) -> np.ndarray:
    """Indices (sorted) of the ``count`` least-occluded frames among the first ``among``
    (default all) by :func:`total_occlusion`; ties go to the earlier frame."""
    score = total_occlusion(V)
    n = score.size if among is None else int(among)
    if not 1 <= n <= score.size:
        raise ValueError(f'among: expected 1..{score.size}, got {among}')
    if not 1 <= count <= n:
        raise ValueError(f'prior_frames: expected 1..{n} (the frames to choose from), '
                         f'got {count}')
    return np.sort(np.argsort(score[:n], kind='stable')[:count])


def prior_weights(vis: np.ndarray, weighting: str) -> np.ndarray:
    """The prior term's weights o (same shape as ``vis``, (P,) or (F, P)) of the occlusion
    1 - vis: ``pixel`` per pixel, ``frame`` each frame's mean, ``sequence`` ones."""
    if weighting not in WEIGHTINGS:
        raise ValueError(f'weighting={weighting!r}: expected one of {WEIGHTINGS}')
    occ = 1.0 - np.asarray(vis, dtype=np.float64)
    if weighting == 'pixel':
        return occ
    if weighting == 'frame':
        return np.broadcast_to(occ.mean(axis=-1, keepdims=True), occ.shape).copy()
    return np.ones_like(occ)


@dataclass(frozen=True)
class SPVAFrame:
    """One frame: ``X`` (P, 3) camera frame, image units, centred on the visible tracks'
    weighted centroid whose image position is ``t`` (2,); ``R`` (3, 3) object -> camera,
    ``scale``; ``residual_px`` the RMS reprojection error over the visible tracks; ``X_object``
    (P, 3) the shape in the prior's object frame."""

    X: np.ndarray
    t: np.ndarray
    R: np.ndarray
    scale: float
    residual_px: float
    X_object: np.ndarray
    seconds: float


def _positive_int(name: str, v: int, lo: int = 1) -> int:
    if isinstance(v, (bool, np.bool_)) or int(v) != v or v < lo:
        raise ValueError(f'{name}: expected an integer >= {lo}, got {v!r}')
    return int(v)


class ShapePrior:
    """The SPVA prior and its per-frame solver: ``step(uv, vis)`` -> :class:`SPVAFrame`.

    ``shapes`` (F0, P, 3) object-frame shapes (image units, one common object frame) of an
    initial batch with visibility ``V`` (F0, P); ``ref`` (P, 2) the tracks' reference image
    positions (the grid of the TV term).  ``prior_frames`` least-occluded frames of the batch
    make the prior T; ``rank`` the dimension of the shape subspace; ``prior_weight`` gamma,
    ``smoothness`` mu, ``low_rank`` lam; ``iterations`` ADMM steps per frame; ``refresh`` the
    prior's update rate (0: fixed)."""

    def __init__(self, shapes: np.ndarray, V: np.ndarray, ref: np.ndarray,
                 prior_frames: int = 10, weighting: str = 'pixel', prior_weight: float = 10.0,
                 smoothness: float = 0.05, low_rank: float = 10.0, rank: int = 4,
                 iterations: int = 10, refresh: float = 0.0, neighbours: int = 4) -> None:
        shapes = np.asarray(shapes, dtype=np.float64)
        if shapes.ndim != 3 or shapes.shape[2] != 3 or shapes.shape[1] < 4:
            raise ValueError(f'shapes: expected (F0, P, 3) with P >= 4, got {shapes.shape}')
        if not np.isfinite(shapes).all():
            raise ValueError('shapes: non-finite values')
        F0, P, _ = shapes.shape
        V = np.asarray(V, dtype=np.float64)
        if V.shape != (F0, P):
            raise ValueError(f'V: expected shape {(F0, P)}, got {V.shape}')
        ref = np.asarray(ref, dtype=np.float64)
        if ref.shape != (P, 2) or not np.isfinite(ref).all():
            raise ValueError(f'ref: expected finite (P, 2) = ({P}, 2), got {ref.shape}')
        if weighting not in WEIGHTINGS:
            raise ValueError(f'weighting={weighting!r}: expected one of {WEIGHTINGS}')
        for name, val in (('prior_weight', prior_weight), ('smoothness', smoothness),
                          ('low_rank', low_rank)):
            if not (np.isfinite(val) and val >= 0):
                raise ValueError(f'{name}: expected a finite value >= 0, got {val!r}')
        if not (np.isfinite(refresh) and 0 <= refresh <= 1):
            raise ValueError(f'refresh: expected 0..1, got {refresh!r}')
        self.rank = min(_positive_int('rank', rank), F0)
        self.iterations = _positive_int('iterations', iterations)
        neighbours = _positive_int('neighbours', neighbours)
        self.frames = select_prior_frames(V, _positive_int('prior_frames', prior_frames))
        self.weighting, self.gamma = weighting, float(prior_weight)
        self.mu, self.lam, self.refresh = float(smoothness), float(low_rank), float(refresh)
        # the prior: the selected frames' shapes aligned to the first of them, averaged
        first = shapes[self.frames[0]] - shapes[self.frames[0]].mean(axis=0)
        T = np.mean([_align(shapes[f], first) for f in self.frames], axis=0)
        self.T = T - T.mean(axis=0)
        aligned = np.stack([_align(s, self.T) for s in shapes])           # (F0, P, 3)
        _, _, Vt = np.linalg.svd(aligned.reshape(F0, 3 * P), full_matrices=False)
        self.B = Vt[:self.rank]                                            # (K, 3P) orthonormal
        self.D = grid_graph(ref, neighbours)
        coo = self.D.tocoo()                   # row e: +1 at ei[e], -1 at ej[e]
        ei, ej = np.empty(self.D.shape[0], np.intp), np.empty(self.D.shape[0], np.intp)
        ei[coo.row[coo.data > 0]] = coo.col[coo.data > 0]
        ej[coo.row[coo.data < 0]] = coo.col[coo.data < 0]
        self._edges = (ei, ej)
        self.L = _norm2(self.D)
        self._last = self.T.copy()         # the previous frame's shape: its camera's start
        self._duals: tuple[np.ndarray, np.ndarray] | None = None   # ADMM's, for the next solve
        self.seconds: list[float] = []

    @classmethod
    def from_batch(cls, res: NRSfMResult, W: np.ndarray, V: np.ndarray, **kw
                   ) -> ShapePrior:
        """The prior of a batch result on tracks W (2F, P), V (F, P): its object-frame shapes
        (``dspr.object_shapes``) and the tracks of its least-occluded frame as the grid."""
        W, V = check_tracks(W, V)
        F, P = V.shape
        ref = W.reshape(F, 2, P)[int(np.argmin(total_occlusion(V)))].T
        return cls(object_shapes(res), V, ref, **kw)

    # ------------------------------------------------------------------ per frame
    def step(self, uv: np.ndarray, vis: np.ndarray | None = None) -> SPVAFrame:
        """Reconstruct one frame from its tracks uv (P, 2) (non-finite: missing) and
        visibility vis (P,) in [0, 1] on the prior's tracks."""
        t0 = time.perf_counter()
        P = self.T.shape[0]
        uv, v = _check_frame(uv, vis, P)
        g = prior_weights(v, self.weighting)
        fit = _fit(np.stack([self._last, self.T]), uv, v)
        k = int(np.argmin(fit.residual_px))
        R2, s, t = fit.R2[k], float(fit.scale[k]), fit.t[k]
        t = t - s * R2 @ (v @ (self._last, self.T)[k] / v.sum())      # image of the origin
        X = self._subspace_fit(uv, v, R2, s, t)
        half = max(self.iterations // 2, 1)
        X = self._admm(X, uv, v, g, R2, s, t, half)
        f1 = _fit(X[None], uv, v)                                          # camera of X, again
        R2, s = f1.R2[0], float(f1.scale[0])
        t = f1.t[0] - s * R2 @ (v @ X / v.sum())
        X = self._admm(X, uv, v, g, R2, s, t, max(self.iterations - half, 1))
        res = uv - (s * X @ R2.T + t)
        resid = float(np.sqrt((v * (res ** 2).sum(1)).sum() / max(v.sum(), 1e-12)))
        if self.refresh:
            self.T = self.T + self.refresh * v[:, None] * (X - self.T)
        self._last = X
        R = np.concatenate([R2, np.cross(R2[0], R2[1])[None]])
        c = v @ X / v.sum()
        sec = time.perf_counter() - t0
        self.seconds.append(sec)
        return SPVAFrame(X=s * (X - c) @ R.T, t=t + s * R2 @ c, R=R, scale=s,
                         residual_px=resid, X_object=X, seconds=sec)

    def _subspace_fit(self, uv: np.ndarray, v: np.ndarray, R2: np.ndarray, s: float,
                      t: np.ndarray) -> np.ndarray:
        """The shape in the subspace whose projection best fits the visible tracks (weighted
        least squares over the K coefficients, a small ridge towards the prior's)."""
        K, P = self.rank, self.T.shape[0]
        Bk = self.B.reshape(K, P, 3)
        A = s * (Bk @ R2.T)                                                # (K, P, 2)
        Av = A * v[None, :, None]
        G = np.einsum('kpi,lpi->kl', Av, A)
        rhs = np.einsum('kpi,pi->k', Av, uv - t)
        a0 = self.B @ self.T.ravel()
        ridge = 1e-6 * max(np.trace(G), 1e-300) / K
        a = np.linalg.solve(G + ridge * np.eye(K), rhs + ridge * a0)
        return (a @ self.B).reshape(P, 3)

    def _admm(self, X: np.ndarray, uv: np.ndarray, v: np.ndarray, g: np.ndarray,
              R2: np.ndarray, s: float, t: np.ndarray, iterations: int) -> np.ndarray:
        """``iterations`` linearised ADMM steps from X for the fixed camera (R2, s, t), as one
        numba loop over the points and the grid's edges (``_spva_kernels``: the per-frame
        latency)."""
        from ._spva_kernels import spva_admm
        vs = v * s * s                                                     # data weight
        pg = self.gamma * g
        cp = RHO + RHO_TV * self.L + pg                                    # (P,)
        inv = 1.0 / cp
        gain = 1.0 / (cp + vs) - 1.0 / cp
        base = (((uv - t) / s) @ R2) * vs[:, None] + pg[:, None] * self.T  # (P, 3)
        X = np.array(X, dtype=np.float64)                                  # (a new buffer)
        ei, ej = self._edges
        if self._duals is not None:            # warm start: the last solve's scaled duals
            U, U2 = self._duals                # (its own buffers, no one else holds them)
        else:
            U, U2 = np.zeros_like(X), np.zeros((ei.size, 3))
        thresh = self.mu / RHO_TV
        spva_admm(X, U, U2, np.ascontiguousarray(base), inv, gain, R2.T @ R2, self.B, ei, ej,
                  RHO / (RHO + self.lam), RHO_TV * self.L, thresh, EPS_PX / (EPS_PX + thresh),
                  bool(self.mu), int(iterations), RHO, RHO_TV)
        self._duals = (U, U2)
        return X

    def solve(self, W: np.ndarray, V: np.ndarray) -> NRSfMResult:
        """Every frame of tracks W (2F, P), V (F, P) through :meth:`step`, in order, as a
        batch result (camera-frame shapes, unit scale per frame in ``S``, cameras)."""
        t0 = time.perf_counter()
        W, V = check_tracks(W, V)
        F, P = V.shape
        if P != self.T.shape[0]:
            raise ValueError(f'W: expected {self.T.shape[0]} tracks (the prior\'s), got {P}')
        Wf = W.reshape(F, 2, P)
        S, R = np.empty((F, P, 3)), np.empty((F, 3, 3))
        scale, tt, resid = np.empty(F), np.empty((F, 2)), np.empty(F)
        for f in range(F):
            fr = self.step(Wf[f].T, V[f])
            S[f], R[f], scale[f], tt[f], resid[f] = (fr.X / fr.scale, fr.R, fr.scale, fr.t,
                                                     fr.residual_px)
        return NRSfMResult(S=S, R=R, scale=scale, t=tt, method='spva', rank=self.rank,
                           residual_px=float(np.sqrt(np.mean(resid ** 2))),
                           iterations=self.iterations * F, converged=True,
                           seconds=time.perf_counter() - t0)


def spva(W: np.ndarray, V: np.ndarray | None = None, prior_frames: int = 10,
         weighting: str = 'pixel', prior_weight: float = 10.0, smoothness: float = 0.05,
         low_rank: float = 10.0, rank: int = 4, iterations: int = 10, refresh: float = 0.0,
         init: str | NRSfMResult = 'cdf') -> NRSfMResult:
    """SPVA on a whole sequence: the ``init`` batch method (any of ``reconstruct``'s, or a
    result of one on these tracks) gives the object-frame shapes that the prior (the
    least-occluded ``prior_frames``) and the subspace come from, then every frame is solved in
    order by :class:`ShapePrior` (see the module docstring for the other parameters)."""
    from . import reconstruct
    t0 = time.perf_counter()
    W, V = check_tracks(W, V)
    prior_frames = _positive_int('prior_frames', prior_frames)
    if prior_frames > V.shape[0]:
        raise ValueError(f'prior_frames: expected 1..{V.shape[0]} (the frames), '
                         f'got {prior_frames}')
    if isinstance(init, NRSfMResult):
        if init.S.shape[:2] != V.shape:
            raise ValueError(f'init: expected a result of {V.shape[0]} frames x {V.shape[1]} '
                             f'tracks, got S {init.S.shape}')
        first = init
    elif init == 'spva':
        raise ValueError("init: expected a batch method other than 'spva'")
    else:
        first = reconstruct(W, V, method=init)
    prior = ShapePrior.from_batch(first, W, V, prior_frames=prior_frames, weighting=weighting,
                                  prior_weight=prior_weight, smoothness=smoothness,
                                  low_rank=low_rank, rank=rank, iterations=iterations,
                                  refresh=refresh)
    res = prior.solve(W, V)
    return NRSfMResult(S=res.S, R=res.R, scale=res.scale, t=res.t, method='spva',
                       rank=res.rank, residual_px=res.residual_px, iterations=res.iterations,
                       converged=res.converged, seconds=time.perf_counter() - t0)
