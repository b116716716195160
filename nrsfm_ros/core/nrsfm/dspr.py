"""DSPR: Dynamic Shape Prior Reconstruction (METHODS.md section 5; Golyanik et al. 1909.02468).

A *dynamic shape prior* is a set of distinct shape states, object-frame shapes ``states``
(K, P, 3) in image units, built from an initial batch of frames (any batch method) by clustering
its shapes after Procrustes alignment (:func:`cluster_states`).  Each new frame's tracks are then
explained by every state at once: a weighted orthographic Procrustes fit (2 x 3 camera rows with
orthonormal rows, scale, translation; weights = visibility) batched over the states
(:func:`fit_states`, O(KP) for the moments, then 2 x 3 / 3 x 3 algebra per state).

* Residual (RMS px over the visible tracks) below ``recurrence_px``: the frame *is* that state
  seen again (temporally-disjoint rigidity).  Only (camera, state index) is stored; the shape is
  the state seen by the fitted camera.
* Otherwise a small per-frame energy started from the best state,
  E(X, c, a) = sum_p v_p ||w_p - s R2 X_p - t||^2 + prior_weight sum_p ||X_p - T_p||^2,
  T = sum_k a_k S_k over the ``blend`` best states, is minimised by alternation: the target's
  coefficients a >= 0 (and t) by non-negative least squares on the data for the current camera
  (a restart from a state that alone explains the data better, so that a start from the wrong
  state still reaches the right one), the shape X in closed form per point
  for the fixed camera (its in-plane part is pulled to the data, its depth along the viewing
  direction is the target's), then the camera by Procrustes on X.  The shape joins the prior
  when its :func:`shape_distance` to every state exceeds ``distinct``.

Compression ratio = frames seen (batch included) / states stored.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import nnls

from ..arrays import contiguous64
from .perspective import RATIO_RANGE
from .extend import spread_subset
from .planar_pinhole import pose_steps, stream_convention
from .result import NRSfMResult

PROCRUSTES_ITERATIONS = 8     # majorisation steps of the orthonormal-rows fit after the affine


@dataclass(frozen=True)
class StateFit:
    """Every state's best orthographic fit to one frame: ``R2`` (K, 2, 3) orthonormal camera
    rows, ``scale`` (K,), ``t`` (K, 2) the image position of the state's weighted centroid,
    ``residual_px`` (K,) the RMS reprojection error over the visible tracks."""

    R2: np.ndarray
    scale: np.ndarray
    t: np.ndarray
    residual_px: np.ndarray


@dataclass(frozen=True)
class DSPRFrame:
    """One frame's reconstruction: ``X`` (P, 3) camera frame, image units, centred on the
    visible tracks' weighted centroid whose image position is ``t`` (2,); ``R`` (3, 3) object ->
    camera of the state frame, ``scale``; ``state`` the state index the frame is stored as (the
    matched state, the new state it became, or the nearest one); ``recurring`` when it is a
    recurrence (stored as camera + index only), ``added`` when its shape joined the prior."""

    X: np.ndarray
    t: np.ndarray
    R: np.ndarray
    scale: float
    state: int
    recurring: bool
    added: bool
    residual_px: float
    seconds: float


def _check_states(states: np.ndarray, name: str = 'states') -> np.ndarray:
    states = np.asarray(states, dtype=np.float64)
    if states.ndim != 3 or states.shape[2] != 3 or states.shape[0] < 1 or states.shape[1] < 4:
        raise ValueError(f'{name}: expected shape (K, P, 3) with K >= 1, P >= 4, '
                         f'got {states.shape}')
    if not np.isfinite(states).all():
        raise ValueError(f'{name}: non-finite values')
    return states


def _check_frame(uv: np.ndarray, vis: np.ndarray | None, P: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    uv = np.asarray(uv, dtype=np.float64)
    if uv.shape != (P, 2):
        raise ValueError(f'uv: expected shape ({P}, 2), got {uv.shape}')
    v = np.ones(P) if vis is None else np.asarray(vis, dtype=np.float64)
    if v.shape != (P,):
        raise ValueError(f'vis: expected shape ({P},), got {v.shape}')
    if np.isnan(v).any() or (v < 0).any() or (v > 1).any():
        raise ValueError('vis: values must lie in [0, 1]')
    bad = ~np.isfinite(uv).all(axis=1)
    if bad.any():                       # non-finite measurements are missing, never used
        v = np.where(bad, 0.0, v)
        uv = np.where(bad[:, None], 0.0, uv)
    if (v > 0).sum() < 4:
        raise ValueError(f'vis: need at least 4 visible tracks, got {(v > 0).sum()}')
    return uv, v


def _polar_rows(M: np.ndarray) -> np.ndarray:
    """The nearest matrices with orthonormal rows (..., 2, 3) to M (..., 2, 3)."""
    U, _, Vt = np.linalg.svd(M, full_matrices=False)
    return U @ Vt


def fit_states(states: np.ndarray, uv: np.ndarray, vis: np.ndarray | None = None) -> StateFit:
    """Weighted orthographic Procrustes of every state (K, P, 3) onto one frame's tracks
    uv (P, 2) with visibility weights vis (P,): min over R2 (orthonormal rows), s, t of
    sum_p v_p ||uv_p - s R2 S_kp - t||^2, for all k at once.  From the weighted moments
    B_k = sum v w~ S~^T (2 x 3) and C_k = sum v S~ S~^T (3 x 3): the affine solution's polar
    part, then majorisation steps R2 <- polar(s B + s^2 R2 (lambda_max I - C)) with the optimal
    scale s = tr(R2 B^T) / tr(R2 C R2^T) (monotone in the energy)."""
    states = _check_states(states)
    uv, v = _check_frame(uv, vis, states.shape[1])
    return _fit(states, uv, v)


def _fit(states: np.ndarray, uv: np.ndarray, v: np.ndarray) -> StateFit:
    K = states.shape[0]
    Vs = v.sum()
    wbar = v @ uv / Vs                                       # (2,)
    wc = uv - wbar
    St = states.transpose(0, 2, 1)                           # (K, 3, P)
    c = (St @ v) / Vs                                        # (K, 3) weighted centroids
    B = np.matmul((wc * v[:, None]).T[None], states)         # (K, 2, 3); sum v wc = 0
    C = np.matmul(St * v, states) - Vs * c[:, :, None] * c[:, None, :]   # (K, 3, 3)
    ww = float(np.einsum('p,pi,pi->', v, wc, wc))
    eps = 1e-12 * np.maximum(np.trace(C, axis1=1, axis2=2), 1e-300)
    M = np.linalg.solve(C + eps[:, None, None] * np.eye(3), B.transpose(0, 2, 1)
                        ).transpose(0, 2, 1)                 # affine camera (K, 2, 3)
    R2 = _polar_rows(M)

    # the majorisation steps, per state in one numba loop (8 steps of tiny NumPy calls were
    # ~1 ms of every call, three calls a frame in dspr and spva)
    from ._pinhole_kernels import orthonormal_rows_fit
    R2, s, num = orthonormal_rows_fit(*contiguous64(B, C, np.linalg.eigvalsh(C)[:, -1], R2),
                                      PROCRUSTES_ITERATIONS)
    neg = s < 0                      # a mirrored image: flip the camera rows, keep s > 0
    if neg.any():
        R2 = np.where(neg[:, None, None], -R2, R2)
        s = np.abs(s)
        num = np.abs(num)
    res = np.maximum(ww - s * num, 0.0)
    return StateFit(R2=R2, scale=s, t=np.broadcast_to(wbar, (K, 2)).copy(),
                    residual_px=np.sqrt(res / Vs))


_FLIP = np.diag([1.0, 1.0, -1.0])
PINHOLE_STEPS = 5             # Gauss-Newton steps of each state's pinhole pose
PINHOLE_TRACKS = 1000         # ... on at most this many tracks spread over the visible ones
#   (then the residual on all): 9.4k tracks, 5 states, 24 -> 13 ms per frame


def _pinhole_sign(X: np.ndarray, R2: np.ndarray, v: np.ndarray, depth: np.ndarray
                  ) -> np.ndarray:
    """The orthographic camera rows R2 (2, 3) of the object-frame shape X (P, 3), or those of
    its Necker partner D R H (D the camera's depth reflection, H the reflection about X's best
    plane: the same image for a planar X, the depths mirrored), whichever gives camera-frame
    depths that agree with ``depth`` (P,), the pinhole-posed best state's: a near-planar shape's
    orthographic fit leaves the sign to chance (a third of the flag's per-frame steps came out
    with their depths reflected)."""
    R = np.concatenate([R2, np.cross(R2[0], R2[1])[None]])
    c = v @ X / v.sum()
    z = (X - c) @ R[2]
    zp = depth - v @ depth / v.sum()
    if float((v * z) @ zp) >= 0:
        return R2
    return necker_partner(R, X, v)[:2]


def necker_partner(R: np.ndarray, X: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """The other pose of a near-planar shape X (P, 3) that an orthographic camera cannot tell
    from R (3, 3, object -> camera): D R H, D the camera's depth reflection and H the reflection
    about X's best plane (its least principal axis; ``w`` (P,): point weights), proper; it
    images a planar X the same with its depths mirrored."""
    if w is None:
        A = X - X.mean(axis=0)
    else:
        A = (X - w @ X / w.sum()) * np.sqrt(w)[:, None]
    n = np.linalg.svd(A, full_matrices=False)[2][2]
    return _FLIP @ R @ (np.eye(3) - 2.0 * np.outer(n, n))


@dataclass(frozen=True)
class PinholeFit:
    """Every state's pinhole pose on one frame: ``R`` (K, 3, 3), ``T`` (K, 3) (the state in
    units of the focal length, ``states / focal``, posed as ``R S + T``), ``residual_px`` (K,)
    the RMS reprojection error over the visible tracks."""

    R: np.ndarray
    T: np.ndarray
    residual_px: np.ndarray


def fit_states_pinhole(states: np.ndarray, uv: np.ndarray, v: np.ndarray, focal: float,
                       principal: np.ndarray, start: StateFit, mirror: bool = False
                       ) -> PinholeFit:
    """Every state (K, P, 3; image units of a frame whose centroid is at depth 1) posed by the
    pinhole camera on the raw tracks uv (P, 2), weights v (P,): ``PINHOLE_STEPS`` Gauss-Newton
    steps from the orthographic fit ``start`` (the camera rows, the scale as the inverse
    centroid depth, the image position of the weighted centroid).  ``mirror``: the best state
    also from its orthographic fit's Necker partner (D R H: the camera's depth reflection, H
    the reflection about the state's best plane), the lower residual kept: Gauss-Newton stays
    on the side it starts from."""
    K, P, _ = states.shape
    O = states / focal
    R = np.concatenate([start.R2, np.cross(start.R2[:, 0], start.R2[:, 1])[:, None]], 1)
    c = np.einsum('p,kpi->ki', v, O) / v.sum()                  # weighted centroids
    depth = 1.0 / np.maximum(start.scale, 1e-12)
    T = np.concatenate([(start.t - principal) / focal * depth[:, None], depth[:, None]], 1) \
        - np.einsum('kij,kj->ki', R, c)
    m = np.broadcast_to((uv - principal) / focal, (K, P, 2))
    seen = np.flatnonzero(v > 0)        # the pose from at most PINHOLE_TRACKS spread tracks
    sub = seen[spread_subset(seen.size, PINHOLE_TRACKS)]
    R, T = pose_steps(O[:, sub], m[:, sub], np.broadcast_to(v[sub], (K, sub.size)), R, T,
                      PINHOLE_STEPS)
    resid = _pinhole_residual(O, R, T, m[0], v, focal)
    if mirror:
        k = int(np.argmin(resid))
        R0 = np.concatenate([start.R2[k], np.cross(start.R2[k, 0], start.R2[k, 1])[None]])
        Rm = necker_partner(R0, O[k])
        Tm = np.concatenate([(start.t[k] - principal) / focal * depth[k], [depth[k]]]) - Rm @ c[k]
        Rm, Tm = pose_steps(O[k:k + 1, sub], m[:1, sub], v[sub][None], Rm[None], Tm[None],
                            PINHOLE_STEPS)
        rm = _pinhole_residual(O[k:k + 1], Rm, Tm, m[0], v, focal)
        if rm[0] < resid[k]:
            R, T, resid = R.copy(), T.copy(), resid.copy()
            R[k], T[k], resid[k] = Rm[0], Tm[0], rm[0]
    return PinholeFit(R=R, T=T, residual_px=resid)


def _pinhole_residual(O: np.ndarray, R: np.ndarray, T: np.ndarray, m: np.ndarray,
                      v: np.ndarray, focal: float) -> np.ndarray:
    """(K,) weighted RMS pixel error of the posed states (inf where a point is behind), in one
    pass over each state's points (``_pinhole_kernels``)."""
    from ._pinhole_kernels import posed_residuals
    return posed_residuals(*contiguous64(O, R, T, m, v), float(focal))


def shape_distance(X: np.ndarray, states: np.ndarray, centred: bool = False,
                   norms: np.ndarray | None = None) -> np.ndarray:
    """Distance of a shape X (P, 3) to every state (K, P, 3) up to rotation (proper), scale and
    translation: sqrt(1 - (sum sigma)^2 / (||X~||^2 ||S~_k||^2)), the sine of the angle between
    them after Procrustes (0: the same shape; symmetric, scale-free).  ``centred``: the states
    are already centred; ``norms`` their squared norms (K,), if known."""
    A = X - X.mean(axis=0)
    Bs = states if centred else states - states.mean(axis=1, keepdims=True)
    M = np.matmul(A.T[None], Bs)                            # (K, 3, 3)
    sig = np.linalg.svd(M, compute_uv=False)
    d = np.sign(np.linalg.det(M))
    tr = sig[:, 0] + sig[:, 1] + d * sig[:, 2]
    na = float(np.sum(A * A))
    nb = np.einsum('kpi,kpi->k', Bs, Bs) if norms is None else norms
    cos2 = tr ** 2 / np.maximum(na * nb, 1e-300)
    return np.sqrt(np.clip(1.0 - cos2, 0.0, 1.0))


def _align(X: np.ndarray, S: np.ndarray) -> np.ndarray:
    """X (P, 3) rotated (proper), scaled and translated onto S (P, 3)."""
    A = X - X.mean(axis=0)
    B = S - S.mean(axis=0)
    U, sig, Vt = np.linalg.svd(A.T @ B)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    s = float((sig * np.diag(D)).sum() / max(float(np.sum(A * A)), 1e-300))
    return s * A @ R + S.mean(axis=0)


def cluster_states(shapes: np.ndarray, distinct: float) -> tuple[np.ndarray, np.ndarray]:
    """Distinct states of a batch's object-frame shapes (F, P, 3): greedy in frame order, a
    shape within ``distinct`` (:func:`shape_distance`) of a state merges into it (the state
    becomes the mean of its members aligned to it), else it starts a new state.  Returns
    states (K, P, 3) and labels (F,)."""
    shapes = _check_states(shapes, 'shapes')
    if not (np.isfinite(distinct) and distinct >= 0):
        raise ValueError(f'distinct: expected >= 0, got {distinct}')
    states = [shapes[0] - shapes[0].mean(axis=0)]
    counts = [1]
    labels = np.zeros(shapes.shape[0], np.int64)
    for f in range(1, shapes.shape[0]):
        d = shape_distance(shapes[f], np.stack(states))
        k = int(np.argmin(d))
        if d[k] <= distinct:
            n = counts[k]
            states[k] = (n * states[k] + _align(shapes[f], states[k])) / (n + 1)
            counts[k] = n + 1
        else:
            k = len(states)
            states.append(shapes[f] - shapes[f].mean(axis=0))
            counts.append(1)
        labels[f] = k
    return np.stack(states), labels


def object_shapes(res: NRSfMResult) -> np.ndarray:
    """A batch result's shapes in its object frame, image units: S_f R_f scale_f (F, P, 3),
    with R_f made proper (R_f diag(1, 1, det R_f): a solver may return a depth-flipped S_f
    with an improper R_f), so that each is a rotation of the camera-frame shape S_f, whose depth
    reflection it keeps."""
    R = res.R.copy()
    R[:, :, 2] *= np.sign(np.linalg.det(R))[:, None]
    return np.einsum('fpi,fij->fpj', res.S * res.scale[:, None, None], R)


class DynamicShapePrior:
    """The dynamic shape prior and its per-frame solver: ``step(uv, vis)`` -> :class:`DSPRFrame`.

    ``states`` (K, P, 3) object-frame shapes (image units) on the P tracks every frame is given
    in; ``frames`` the number of frames already represented by them (the initial batch), for
    the compression ratio."""

    def __init__(self, states: np.ndarray, frames: int = 0, recurrence_px: float = 1.0,
                 distinct: float = 0.05, prior_weight: float = 0.01, iterations: int = 5,
                 blend: int = 3, max_states: int = 256) -> None:
        states = _check_states(states)
        for name, val, ok in (('recurrence_px', recurrence_px, recurrence_px >= 0),
                              ('distinct', distinct, distinct >= 0),
                              ('prior_weight', prior_weight, prior_weight > 0),
                              ('iterations', iterations, iterations >= 1),
                              ('blend', blend, blend >= 1),
                              ('max_states', max_states, max_states >= states.shape[0]),
                              ('frames', frames, frames >= 0)):
            if not (np.isfinite(val) and ok):
                raise ValueError(f'{name}: invalid value {val!r}')
        self._states = list(states - states.mean(axis=1, keepdims=True))
        self._stack: np.ndarray | None = None
        self._norms: np.ndarray | None = None
        self.recurrence_px, self.distinct = float(recurrence_px), float(distinct)
        self.prior_weight, self.iterations = float(prior_weight), int(iterations)
        self.blend, self.max_states = int(blend), int(max_states)
        self.frames = int(frames)
        self.recurrences = 0
        self.stored: list[tuple[int, np.ndarray, float, np.ndarray]] = []  # (k, R2, s, t)

    @classmethod
    def from_batch(cls, res: NRSfMResult, distinct: float = 0.05, recurrence_px: float = 1.0,
                   prior_weight: float = 0.01, iterations: int = 5, blend: int = 3
                   ) -> tuple[DynamicShapePrior, np.ndarray]:
        """The prior of a batch result (its object-frame shapes clustered) and the batch
        frames' state labels (F,)."""
        states, labels = cluster_states(object_shapes(res), distinct)
        return cls(states, frames=res.S.shape[0], recurrence_px=recurrence_px,
                   distinct=distinct, prior_weight=prior_weight, iterations=iterations,
                   blend=blend), labels

    @property
    def states(self) -> np.ndarray:
        if self._stack is None or self._stack.shape[0] != len(self._states):
            self._stack = np.stack(self._states)
        return self._stack

    @property
    def compression_ratio(self) -> float:
        """Frames represented / states stored."""
        return self.frames / max(len(self._states), 1)

    # ------------------------------------------------------------------ per frame
    def step(self, uv: np.ndarray, vis: np.ndarray | None = None,
             camera: tuple[float, np.ndarray] | None = None) -> DSPRFrame:
        """Reconstruct one frame from its tracks uv (P, 2) (non-finite: missing) and visibility
        vis (P,) in [0, 1] on the prior's tracks.  ``camera`` (focal px, principal point): uv
        are the camera's pixels, and the recurrence test poses every state by the pinhole
        camera (:func:`fit_states_pinhole`; a recurrence is then the state in that pose);
        otherwise the energy runs on the tracks corrected by the depth ratios of the best
        posed state (the orthographic camera's equivalent image, perspective.py)."""
        t0 = time.perf_counter()
        states = self.states
        uv, v = _check_frame(uv, vis, states.shape[1])
        fit = _fit(states, uv, v)
        self.frames += 1
        if camera is not None:
            focal, principal = float(camera[0]), np.asarray(camera[1], np.float64)
            pin = fit_states_pinhole(states, uv, v, focal, principal, fit)
            best = int(np.argmin(pin.residual_px))
            X = states[best] / focal @ pin.R[best].T + pin.T[best]
            pose_depth = X[:, 2]
            if pin.residual_px[best] <= self.recurrence_px:
                self.recurrences += 1
                Xc, sc, tc = stream_convention(X[None], v[None], focal, principal)
                s, t = float(sc[0]), tc[0]
                self.stored.append((best, pin.R[best][:2], s, t))
                return DSPRFrame(X=Xc[0] * s, t=t, R=pin.R[best], scale=s,
                                 state=best, recurring=True, added=False,
                                 residual_px=float(pin.residual_px[best]),
                                 seconds=time.perf_counter() - t0)
            if np.isfinite(pin.residual_px[best]):
                ratio = np.clip(X[:, 2] / (v @ X[:, 2] / v.sum()), *RATIO_RANGE)
                uv = principal + (uv - principal) * ratio[:, None]
                fit = _fit(states, uv, v)
        best = int(np.argmin(fit.residual_px))
        if camera is None and fit.residual_px[best] <= self.recurrence_px:
            self.recurrences += 1
            self.stored.append((best, fit.R2[best], float(fit.scale[best]), fit.t[best]))
            return self._frame(states[best], fit.R2[best], float(fit.scale[best]), v,
                               fit.t[best], best, True, False,
                               float(fit.residual_px[best]), t0)
        order = np.argsort(fit.residual_px)[:self.blend]
        X, R2, s, t, resid, _ = self._refine(uv, v, best, order, fit)
        if camera is not None and np.isfinite(pin.residual_px).any():
            R2 = _pinhole_sign(X, R2, v, pose_depth)
        if self._norms is None or self._norms.size != states.shape[0]:
            self._norms = np.einsum('kpi,kpi->k', states, states)
        d = shape_distance(X, states, centred=True, norms=self._norms)
        k = int(np.argmin(d))
        added = bool(d[k] > self.distinct and len(self._states) < self.max_states)
        if added:
            self._states.append(X - X.mean(axis=0))
            k = len(self._states) - 1
        self.stored.append((k, R2, s, t))
        return self._frame(X, R2, s, v, t, k, False, added, resid, t0)

    def refine(self, uv: np.ndarray, vis: np.ndarray | None, start: int,
               candidates: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, int]:
        """The per-frame energy alone, started from state ``start`` with the target a blend of
        ``candidates`` (default: every state).  Returns the shape X (P, 3) in the camera frame
        (image units, centred), its coefficients over the candidates, and the candidate with
        the nearest shape to X (:func:`shape_distance`: the state reached)."""
        states = self.states
        uv, v = _check_frame(uv, vis, states.shape[1])
        if not 0 <= start < states.shape[0]:
            raise ValueError(f'start: expected 0..{states.shape[0] - 1}, got {start}')
        cand = np.arange(states.shape[0]) if candidates is None else np.asarray(candidates)
        if start not in cand:
            cand = np.concatenate([[start], cand])
        fit = _fit(states, uv, v)
        X, R2, s, t, _, a = self._refine(uv, v, start, cand, fit)
        fr = self._frame(X, R2, s, v, t, start, False, False, 0.0, time.perf_counter())
        return fr.X, a, int(np.argmin(shape_distance(X, states)))

    def _refine(self, uv: np.ndarray, v: np.ndarray, start: int, cand: np.ndarray,
                fit: StateFit
                ) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, float, np.ndarray]:
        """The per-frame energy from state ``start`` over the candidate states ``cand``:
        X (P, 3) object frame, camera rows R2, scale, t, residual (px), coefficients (m,)."""
        S = self.states[cand]                                  # (m, P, 3)
        m = S.shape[0]
        R2, s = fit.R2[start], float(fit.scale[start])
        lam = self.prior_weight
        Vs = float(v.sum())
        ubar = v @ uv / Vs
        ww0 = float(np.einsum('p,pi,pi->', v, uv - ubar, uv - ubar))
        alpha = (cand == start).astype(np.float64)
        T = self.states[start]
        for _ in range(self.iterations):
            # target: the non-negative blend of candidate states (and t) that best explains
            # the data, from the weighted moments of q_k = s R2 S_k (t eliminated by centring;
            # non-negative: similar states would otherwise extrapolate to wild depths)
            q = s * (S @ R2.T)                                   # (m, P, 2)
            qbar = (v @ q) / Vs                                  # (m, 2)
            qv = (q * v[None, :, None]).reshape(m, -1)           # the sums as BLAS products
            G = qv @ q.reshape(m, -1).T - Vs * qbar @ qbar.T
            G[np.arange(m), np.arange(m)] += 1e-9 * max(np.trace(G), 1e-300) / m
            rhs = qv @ uv.ravel() - Vs * qbar @ ubar
            L = np.linalg.cholesky(G)
            alpha = nnls(L.T, np.linalg.solve(L, rhs))[0]
            t = ubar - alpha @ qbar
            # descent guard: a candidate fitted alone explaining the data better than this
            # blend (a start from the wrong state, its camera wrong too) restarts from it
            r2 = max(ww0 - 2 * alpha @ rhs + alpha @ G @ alpha, 0.0) / Vs
            j = int(np.argmin(fit.residual_px[cand]))
            if fit.residual_px[cand[j]] ** 2 < 0.999 * r2:
                R2, s = fit.R2[cand[j]], float(fit.scale[cand[j]])
                alpha = np.eye(m)[j]
                t = fit.t[cand[j]] - s * R2 @ (v @ S[j] / Vs)
            T = (alpha @ S.reshape(m, -1)).reshape(-1, 3)        # (P, 3)
            # camera: Procrustes of the target
            f1 = _fit(T[None], uv, v)
            R2, s = f1.R2[0], float(f1.scale[0])
            t = f1.t[0] - s * R2 @ (v @ T / v.sum())
        # shape: closed form per point for the fixed camera (in-plane towards the data, the
        # depth along the viewing direction the target's)
        Pi_T = (T @ R2.T) @ R2
        X = T - Pi_T + ((v * s)[:, None] * ((uv - t) @ R2) + lam * Pi_T) \
            / (v * s * s + lam)[:, None]
        f1 = _fit(X[None], uv, v)
        return X, f1.R2[0], float(f1.scale[0]), f1.t[0], float(f1.residual_px[0]), alpha

    def _frame(self, S: np.ndarray, R2: np.ndarray, s: float, v: np.ndarray, t: np.ndarray,
               k: int, recurring: bool, added: bool, resid: float, t0: float) -> DSPRFrame:
        R = np.concatenate([R2, np.cross(R2[0], R2[1])[None]])
        c = v @ S / v.sum()
        X = s * (S - c) @ R.T
        return DSPRFrame(X=X, t=np.asarray(t, dtype=np.float64), R=R, scale=s, state=k,
                         recurring=recurring, added=added, residual_px=resid,
                         seconds=time.perf_counter() - t0)
