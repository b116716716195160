"""NRSfM-Flow style scene flow (METHODS §11.1): 3D motion per point between consecutive
reconstructions of one consistent stream, in the definition of :mod:`.definition`.

``frame='camera'``: ``X_b - X_a`` on the shared track ids (ego-motion included).

``frame='object'``: the camera's ego-motion is *estimated* from the stream and removed.  A
monocular stream cannot tell a camera moving round an object from the object moving rigidly,
so the object frame needs a prior; we take the one that holds for anchored or mostly rigid
objects: **the object frame is the frame in which the most rigid part of the surface stands
still**.  :func:`object_poses` finds it over a window of clouds by a weighted generalised
Procrustes fit (one pose per frame onto a common template) whose per-point weights come from
each track's spread about its template position over the window, re-estimated a few times
(IRLS): points that move least dominate the poses, deforming points get little weight and
their motion is kept as flow.  A Kabsch fit between just two consecutive clouds (the old
estimator) instead removes the rigid part of the deformation too: 0.58 (flag) / 0.91 (face)
relative EPE on perfect ground-truth shapes, against 0.60 / 0.05 for the weighted window.
The flow of pair (a, b) is then ``T_a_b X_b - X_a`` with the estimated camera motion
``T_a_b`` (the earlier camera's axes), exactly as the synthetic ground truth.

**Shrinkage toward zero** (``shrinkage='jitter'``, object frame): a reconstruction's
frame-to-frame jitter differences into flow as large as the motion itself. Over the window,
every track seen in all its clouds has an object-frame trajectory ``Y_f = R_f^T (X_f - t_f)``;
a quadratic in time per track and coordinate (linear on 3 clouds) is the motion, its pooled
residual the jitter variance ``sigma^2`` per coordinate (:func:`jitter_variance`). A
displacement is the difference of two jittered positions, noise power ``6 sigma^2`` per point,
so each point's flow is scaled by the positive-part James-Stein factor ``alpha = max(0, 1 - 6
sigma^2 / mean |d|^2)`` (:func:`shrink_factor`; ``d`` the raw displacements of its 16 nearest
points): pure jitter gives ``alpha`` ~ 0 (zero flow, the trivial baseline), a motion well above
the jitter ``alpha`` ~ 1, and a moving part of a still surface keeps its motion. Where the
clouds carry the tracker's visibility the factor is also multiplied by it (the smaller of the
two clouds'): an occluded point's position is the reconstructor's fill-in, not a measurement,
and its flow is worse than none (occluder flag 30 deg: 1.43 on the occluded points, 0.87 on the
visible). With too few clouds for a residual (the first pair) the factor is 0. Nothing is tuned
per case: ``sigma`` is measured on every cloud. What it cannot see: reconstruction error that
is as smooth in time as the motion (a wrong but steady deformation, a depth reflection) passes
as motion; motion that changes faster than a quadratic over the window (a period under ~10
clouds) is partly taken for jitter.
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from ..arrays import duplicates, sorted_unique
from ._flow_kernels import add_object_displacement, neighbour_means
Cloud = tuple[np.ndarray, np.ndarray]   # (N, 3) points, (N,) unique track ids


@dataclass(frozen=True)
class SceneFlow:
    """points (N, 3) current positions; velocity (N, 3) in units/s in the earlier camera's axes
    (``frame='object'``: ego-motion removed); ids (N,) track ids; ``T_prev_cur`` (4, 4) the
    (estimated) camera motion that maps current-camera coordinates to the previous camera's."""

    points: np.ndarray
    velocity: np.ndarray
    ids: np.ndarray
    T_prev_cur: np.ndarray
    shrinkage: float = 1.0          # factor applied to the raw velocity (1: none)
    jitter: float = float('nan')    # estimated jitter std per coordinate (cloud units)

SHRINKAGE = ('jitter', 'none')
NEIGHBOURS = 16      # points each shrinkage factor's signal power is pooled over


def weighted_kabsch(A: np.ndarray, B: np.ndarray, w: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """R (3, 3), t (3,) minimising sum_i w_i |R A_i + t - B_i|^2 (proper rotation)."""
    w = np.ones(len(A)) if w is None else np.asarray(w, np.float64)
    sw = max(float(w.sum()), 1e-300)
    ca = w @ A / sw
    cb = w @ B / sw
    H = ((A - ca) * w[:, None]).T @ (B - cb)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, cb - R @ ca


def _check_cloud(X: np.ndarray, ids: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    X = np.asarray(X, np.float64)
    ids = np.asarray(ids).astype(np.int64)
    if X.ndim != 2 or X.shape != (len(ids), 3):
        raise ValueError(f'{name}: expected (N, 3) points and N ids, got {X.shape} and '
                         f'{ids.shape}')
    if duplicates(ids):
        raise ValueError(f'{name}: {duplicates(ids)} duplicated track id(s); '
                         'ids must be unique')
    return X, ids


def _shared(ia: np.ndarray, ib: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``np.intersect1d(ia, ib, assume_unique=True, return_indices=True)`` (unique ids), the
    same arrays without the merge sort where the two clouds carry the same ids in the same
    order (consecutive clouds of one track set: most of a stream)."""
    if ia.shape == ib.shape and np.array_equal(ia, ib):
        order = np.argsort(ia, kind='stable')
        return ia[order], order, order.copy()
    return np.intersect1d(ia, ib, assume_unique=True, return_indices=True)


def _common(first: np.ndarray, rest: Sequence[np.ndarray]) -> np.ndarray:
    """The sorted ids (unique in each) that ``first`` and every array of ``rest`` share."""
    common = first
    for i in rest:
        if common is first and i.shape == first.shape and np.array_equal(i, first):
            continue
        common = np.intersect1d(common, i, assume_unique=True)
    return np.sort(common) if common is first else common


def _number(v: object) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)


def _count(v: object, lo: int) -> bool:
    return isinstance(v, numbers.Integral) and not isinstance(v, bool) and v >= lo


def object_poses(clouds: Sequence[Cloud], iterations: int = 8, softness: float = 0.1,
                 min_points: int = 3, prior: tuple[np.ndarray, np.ndarray] | None = None,
                 return_weights: bool = False, max_points: int = 0,
                 assume_checked: bool = False):
    """Camera poses of a window of clouds in one object frame: (R (F, 3, 3), t (F, 3)) with
    ``X_f ~ R_f Z + t_f`` for the template Z, frame 0's pose the identity.

    Weighted generalised Procrustes (see the module doc): per-track weight
    ``1 / (spread^2 + (softness * median spread)^2)``, ``spread`` the RMS distance of the
    track's object-frame positions from its template position; ``iterations`` re-weightings
    (0: the unweighted fit).  A frame sharing fewer than ``min_points`` tracks with the template
    keeps its previous frame's pose.

    ``prior`` (ids, weights): start from these per-track weights instead of uniform ones (a
    warm start from the previous window; fewer ``iterations`` are then needed).
    ``return_weights``: also return (ids, weights) of the last re-weighting.
    ``max_points`` > 0: fit on about that many tracks (a fixed pseudo-random subset of the ids).
    ``assume_checked``: the clouds are already (N, 3) float64 points with unique int64 ids (a node
    checks each cloud once on arrival, not again in every window it is part of)."""
    for name, value, ok, want in (
            ('iterations', iterations, _count(iterations, 0), 'an integer >= 0'),
            ('softness', softness, _number(softness) and softness > 0, 'a finite number > 0'),
            ('min_points', min_points, _count(min_points, 3), 'an integer >= 3'),
            ('max_points', max_points, _count(max_points, 0), 'an integer >= 0 (0: all)')):
        if not ok:
            raise ValueError(f'{name}={value!r}: expected {want}')
    F = len(clouds)
    if F == 0:
        raise ValueError('clouds: expected at least one cloud')
    checked = list(clouds) if assume_checked else [_check_cloud(X, i, f'clouds[{k}]')
                                                   for k, (X, i) in enumerate(clouds)]
    first = checked[0][1]
    if all(np.array_equal(i, first) for _, i in checked[1:]):   # one track set: the usual case
        uid = sorted_unique(first)
    else:
        uid = sorted_unique(np.concatenate([i for _, i in checked]))
    if max_points and uid.size > max_points:
        # a fixed pseudo-random subset of the track ids (the same track stays in or out from
        # one window to the next): the poses need a few thousand points, not every one
        m = -(-uid.size // max_points)
        uid = uid[(uid.astype(np.uint64) * np.uint64(2654435761) % np.uint64(2 ** 32)
                   % np.uint64(m)) == 0]
    P = uid.size
    Xs = np.full((F, P, 3), np.nan)
    for f, (X, i) in enumerate(checked):
        k = np.searchsorted(uid, i).clip(max=max(P - 1, 0))
        hit = uid[k] == i if P else np.zeros(len(i), bool)
        Xs[f, k[hit]] = X[hit]
    seen = np.isfinite(Xs).all(-1)                       # (F, P)
    R = np.tile(np.eye(3), (F, 1, 1))
    t = np.zeros((F, 3))
    # template: frame 0, then tracks first seen later at their first position chained by
    # consecutive fits (a rough start; the iterations refine it)
    Z = Xs[0].copy()
    for f in range(1, F):
        R[f], t[f] = R[f - 1], t[f - 1]
        m = seen[f] & np.isfinite(Z).all(-1)
        if m.sum() >= min_points:
            R[f], t[f] = weighted_kabsch(Z[m], Xs[f, m])
        new = seen[f] & ~np.isfinite(Z).all(-1)
        Z[new] = (Xs[f, new] - t[f]) @ R[f]
    w = np.ones(P)
    if prior is not None:
        pid, pw = (np.asarray(v) for v in prior)
        if pid.shape != pw.shape:
            raise ValueError(f'prior: ids {pid.shape} and weights {pw.shape} differ in shape')
        if pid.size:
            common, iu, ip = np.intersect1d(uid, pid.astype(np.int64), return_indices=True)
            if common.size:
                w[:] = float(np.min(pw[ip]))      # tracks new to the window: least trusted
                w[iu] = pw[ip]
    for it in range(iterations + 1):
        for f in range(F):
            m = seen[f] & np.isfinite(Z).all(-1)
            if m.sum() >= min_points:
                R[f], t[f] = weighted_kabsch(Z[m], Xs[f, m], w[m])
            elif f:
                R[f], t[f] = R[f - 1], t[f - 1]
        # gauge: frame 0 is the template frame
        R0, t0 = R[0].copy(), t[0].copy()
        R = R @ R0.T
        t = t - R @ t0
        Y = np.einsum('fpj,fjk->fpk', Xs - t[:, None], R)   # R_f^T (X - t_f), row vectors
        with np.errstate(invalid='ignore'):
            Z = np.nanmean(np.where(seen[..., None], Y, np.nan), axis=0)
            d2 = np.where(seen, ((Y - Z) ** 2).sum(-1), np.nan)
            spread = np.sqrt(np.nanmean(d2, axis=0))
        ok = np.isfinite(spread) & (seen.sum(0) >= 2)
        if it == iterations or not ok.any():
            break
        eps = softness * float(np.median(spread[ok])) + 1e-12
        w = np.where(ok, 1.0 / (np.where(ok, spread, 0.0) ** 2 + eps ** 2), 0.0)
        w /= w.max()
        w[~ok] = w[ok].min() if ok.any() else 1.0       # tracks seen once: least trusted
    if return_weights:
        return R, t, (uid, w)
    return R, t


def _centroid(X: np.ndarray) -> np.ndarray:
    """The mean point of X (P, 3) as one BLAS product (NumPy's mean over the first axis of a
    (P, 3) array is a strided reduction, 10x slower at 30k points)."""
    return (np.ones(X.shape[0]) @ X) / X.shape[0]


def known_poses(clouds: Sequence[Cloud], rotations: np.ndarray, assume_checked: bool = False
                ) -> tuple[np.ndarray, np.ndarray]:
    """Poses of a window of clouds in :func:`object_poses`' convention (``X_f ~ R_f Z + t_f``,
    frame 0 the identity) from their known orientations ``rotations`` (F, 3, 3), object ->
    camera of each cloud in one object frame (the reconstructor's cameras,
    ``nrsfm/object_pose``): ``R_f = rotations_f rotations_0^T``, and the translations that
    keep the centroid of the tracks two consecutive clouds share still in the object frame
    (the reconstructor's own origin, its clouds' centroid; a cloud sharing no track with the
    previous one keeps its translation).  Relative EPE on the 30 deg flag (256x192, through
    the tracker): 0.55 against 0.73 for :func:`object_poses` on the same clouds, 0.68 with
    these rotations and :func:`object_poses`' weighted translations (BENCHMARKS, issue 14)."""
    F = len(clouds)
    Q = np.asarray(rotations, np.float64)
    if Q.shape != (F, 3, 3) or not np.isfinite(Q).all() or not np.allclose(
            Q @ Q.transpose(0, 2, 1), np.eye(3), atol=1e-6):
        raise ValueError(f'rotations: expected {F} rotation matrices (F, 3, 3), got shape '
                         f'{Q.shape}')
    checked = list(clouds) if assume_checked else [_check_cloud(X, i, f'clouds[{k}]')
                                                   for k, (X, i) in enumerate(clouds)]
    R = Q @ Q[0].T
    t = np.zeros((F, 3))
    whole: dict[int, np.ndarray] = {}       # each cloud's centroid, computed once

    def centroid(f: int) -> np.ndarray:
        if f not in whole:
            whole[f] = _centroid(checked[f][0])
        return whole[f]
    for f in range(1, F):
        (Xa, ia), (Xb, ib) = checked[f - 1], checked[f]
        if ia.shape == ib.shape and np.array_equal(ia, ib):   # one track set: every point
            ma, mb = centroid(f - 1), centroid(f)
        else:
            _, pa, pb = _shared(ia, ib)
            if not pa.size:
                t[f] = t[f - 1]
                continue
            ma, mb = _centroid(Xa[pa]), _centroid(Xb[pb])
        # R_f^T (m_b - t_f) = R_{f-1}^T (m_a - t_{f-1}): the shared centroid stands still
        t[f] = mb - R[f] @ R[f - 1].T @ (ma - t[f - 1])
    return R, t


def motion_between(R: np.ndarray, t: np.ndarray, a: int, b: int) -> np.ndarray:
    """T_a_b (4, 4): camera b coordinates -> camera a, from :func:`object_poses`."""
    Rab = R[a] @ R[b].T
    T = np.eye(4)
    T[:3, :3] = Rab
    T[:3, 3] = t[a] - Rab @ t[b]
    return T


def pair_flow(prev: Cloud, cur: Cloud, T_a_b: np.ndarray, dt: float) -> SceneFlow:
    """``(T_a_b X_b - X_a) / dt`` on the track ids the two (checked) clouds share."""
    a_X, a_ids = prev
    b_X, b_ids = cur
    if a_ids.shape == b_ids.shape and np.array_equal(a_ids, b_ids) and \
            bool((a_ids[1:] > a_ids[:-1]).all()):
        common, a, b = a_ids, a_X, b_X      # one ascending track set: no gathers
    else:
        common, ip, ic = _shared(a_ids, b_ids)
        a, b = a_X[ip], b_X[ic]
    moved = b @ T_a_b[:3, :3].T + T_a_b[:3, 3]
    return SceneFlow(points=b, velocity=(moved - a) / dt, ids=common.astype(np.uint32),
                     T_prev_cur=T_a_b)


def jitter_variance(clouds: Sequence[Cloud], R: np.ndarray, t: np.ndarray,
                    times: Sequence[float] | None = None, min_points: int = 3,
                    max_points: int = 2000) -> float | None:
    """Per-coordinate variance of the clouds' jitter about a smooth motion (module doc):
    the pooled residual of a per-track quadratic in time (linear on 3 clouds) fitted to the
    object-frame positions ``R_f^T (X_f - t_f)`` of the tracks seen in every cloud.
    ``clouds`` checked (X, ids) with unique ids, poses from :func:`object_poses`, ``times``
    (default 0, 1, ..) their time stamps; on at most ``max_points`` of the common tracks (an
    even subset of the ids; 0: all).  None with fewer than 3 clouds or ``min_points`` common
    tracks."""
    w = len(clouds)
    if w < 3:
        return None
    # unique ids (checked clouds): no np.unique pass per cloud
    common = _common(clouds[0][1], [i for _, i in clouds[1:]])
    if common.size > max_points > 0:          # an even subset of the ids: plenty of samples
        common = common[::-(-common.size // max_points)]
    n = common.size
    if n < min_points:
        return None
    Y = np.empty((w, n, 3))
    for f, (X, i) in enumerate(clouds):
        order = np.argsort(i, kind='stable')
        Y[f] = (X[order[np.searchsorted(i, common, sorter=order)]] - t[f]) @ R[f]
    tau = np.arange(w, dtype=np.float64) if times is None else np.asarray(times, np.float64)
    if tau.shape != (w,) or not np.all(np.isfinite(tau)) or np.unique(tau).size != w:
        raise ValueError(f'times: expected {w} distinct finite stamps, got {tau}')
    tau = (tau - tau[-1]) / max(float(np.ptp(tau)), 1e-300)
    degree = 2 if w >= 4 else 1
    A = np.vander(tau, degree + 1, increasing=True)
    Q, _ = np.linalg.qr(A)
    flat = Y.reshape(w, -1)
    resid = flat - Q @ (Q.T @ flat)
    return float((resid ** 2).sum() / ((w - degree - 1) * flat.shape[1]))


def neighbour_index(points: np.ndarray, neighbours: int = NEIGHBOURS) -> np.ndarray:
    """(N, k) indices of the ``neighbours`` nearest points of each of ``points`` (N, 3), itself
    included (k = min(neighbours, N))."""
    from scipy.spatial import cKDTree
    pts = np.asarray(points, np.float64)
    k = min(max(int(neighbours), 1), len(pts))
    if k == 0:                                       # no points: no neighbourhoods
        return np.zeros((0, 0), np.intp)
    _, nb = cKDTree(pts).query(pts, k, workers=-1)
    return nb.reshape(len(pts), k)


def shrink_factor(displacement: np.ndarray, sigma2: float | None,
                  points: np.ndarray | None = None, neighbours: int = NEIGHBOURS,
                  index: np.ndarray | None = None, gain: np.ndarray | None = None
                  ) -> float | np.ndarray:
    """Positive-part James-Stein factor ``max(0, 1 - 6 sigma2 / mean |d|^2)`` of raw
    displacements ``d`` (N, 3) whose per-coordinate position jitter has variance ``sigma2``
    (None: unknown -> 0, zero flow).  With ``points`` (N, 3): one factor per point, the mean
    over its ``neighbours`` nearest points (itself included; all if fewer), so that a moving
    part of a still surface keeps its motion; ``index`` (N, k): those neighbours given
    (:func:`neighbour_index`, e.g. kept while a stream's track set stays the same).
    ``gain`` (N,): each displacement's noise power relative to a raw difference's
    (:func:`centred_flow`); the noise then is ``6 sigma2`` times its neighbourhood's mean gain."""
    d2 = np.sum(np.asarray(displacement, np.float64) ** 2, axis=1)
    if points is None and index is None:
        if sigma2 is None or not d2.size or d2.mean() <= 0:
            return 0.0
        return float(max(0.0, 1.0 - 6.0 * sigma2 / d2.mean()))
    if sigma2 is None or not d2.size:
        return np.zeros(d2.size)
    nb = neighbour_index(points, neighbours) if index is None else np.asarray(index)
    if nb.ndim != 2 or nb.shape[0] != d2.size:
        raise ValueError(f'index: expected ({d2.size}, k) neighbour indices, got {nb.shape}')
    if nb.size and not (0 <= nb.min() and nb.max() < d2.size):
        raise ValueError(f'index: expected neighbour indices in 0..{d2.size - 1}')
    nb = np.ascontiguousarray(nb, np.intp)
    power = neighbour_means(d2, nb)
    noise = 6.0 * sigma2
    if gain is not None:
        gain = np.asarray(gain, np.float64)
        if gain.shape != d2.shape or not np.all(gain >= 0):
            raise ValueError(f'gain: expected {d2.size} values >= 0, got shape {gain.shape}')
        noise = noise * neighbour_means(gain, nb)
    with np.errstate(divide='ignore'):
        return np.where(power > 0, np.clip(1.0 - noise / power, 0.0, 1.0), 0.0)


def shrunk(sf: SceneFlow, clouds: Sequence[Cloud], R: np.ndarray, t: np.ndarray, dt: float,
           times: Sequence[float] | None = None, neighbours: int = NEIGHBOURS,
           visibility: np.ndarray | None = None, index: np.ndarray | None = None,
           gain: np.ndarray | None = None) -> SceneFlow:
    """``sf`` (the flow of the last two of ``clouds``, poses R, t) scaled per point by
    :func:`shrink_factor` of its displacements over ``neighbours`` nearest points and
    :func:`jitter_variance` of the window, times ``visibility`` (N,) in [0, 1] where given (the
    smaller of the point's in the two clouds: an occluded point's position is a fill-in, not a
    measurement); ``shrinkage`` the mean factor.  ``index``: the neighbours, if known
    (:func:`shrink_factor`); ``gain``: the displacements' noise gains (:func:`centred_flow`)."""
    s2 = jitter_variance(clouds, R, t, times)
    a = shrink_factor(sf.velocity * dt, s2, sf.points, neighbours, index, gain)
    if visibility is not None:
        w = np.asarray(visibility, np.float64)
        if w.shape != a.shape or not np.all((w >= 0) & (w <= 1)):
            raise ValueError(f'visibility: expected {a.shape[0]} values in [0, 1], got shape '
                             f'{w.shape}')
        a = a * w
    return replace(sf, velocity=sf.velocity * a[:, None],
                   shrinkage=float(a.mean()) if a.size else 0.0,
                   jitter=float('nan') if s2 is None else math.sqrt(s2))


def _check_shrinkage(shrinkage: str, frame: str) -> None:
    if shrinkage not in SHRINKAGE:
        raise ValueError(f'shrinkage={shrinkage!r}: expected one of {list(SHRINKAGE)}')
    if frame not in ('object', 'camera'):
        raise ValueError(f"frame={frame!r}: expected 'object' or 'camera'")


def scene_flow(prev_points: np.ndarray, prev_ids: np.ndarray, points: np.ndarray,
               ids: np.ndarray, dt: float, frame: str = 'object',
               history: Sequence[Cloud] = (), iterations: int = 8,
               softness: float = 0.1, shrinkage: str = 'jitter') -> SceneFlow:
    """Velocity of every current point that also exists in the previous cloud (matched by id).

    ``frame='object'``: the ego-motion is estimated by :func:`object_poses` over ``history``
    (older clouds, oldest first), the previous and the current cloud; with no history and two
    clouds only this is a weighted two-frame fit (weak: prefer a window).  ``shrinkage``
    'jitter' (object frame only): scaled toward zero by the window's jitter (module doc; the
    clouds are taken ``dt`` apart); 'none': the raw difference."""
    _check_shrinkage(shrinkage, frame)
    if not dt > 0:
        raise ValueError(f'dt: expected a positive time step, got {dt}')
    prev = _check_cloud(prev_points, prev_ids, 'prev_points')
    cur = _check_cloud(points, ids, 'points')
    T = np.eye(4)
    if frame == 'object':
        window = [*(_check_cloud(X, i, f'history[{k}]') for k, (X, i) in enumerate(history)),
                  prev, cur]
        R, t = object_poses(window, iterations=iterations, softness=softness)
        T = motion_between(R, t, len(window) - 2, len(window) - 1)
        sf = pair_flow(prev, cur, T, dt)
        return shrunk(sf, window, R, t, dt) if shrinkage == 'jitter' else sf
    return pair_flow(prev, cur, T, dt)


def sequence_flow(clouds: Sequence[Cloud], dts: Sequence[float], frame: str = 'object',
                  window: int = 0, iterations: int = 8, softness: float = 0.1,
                  shrinkage: str = 'jitter') -> list[SceneFlow]:
    """Flow of every consecutive pair (clouds[k-1], clouds[k]), k = 1.. (len - 1 results;
    ``dts[k-1]`` its time step).  ``window`` 0: one pose estimate over all clouds (offline;
    the jitter of ``shrinkage`` over the 5 clouds about each pair); > 1: causal, each pair
    from the ``window`` clouds ending at it (what the node does)."""
    _check_shrinkage(shrinkage, frame)
    checked = [_check_cloud(X, i, f'clouds[{k}]') for k, (X, i) in enumerate(clouds)]
    if len(dts) != max(len(checked) - 1, 0):
        raise ValueError(f'dts: expected {len(checked) - 1} time steps, got {len(dts)}')
    out = []
    if frame == 'object' and window == 0 and len(checked) >= 2:
        R, t = object_poses(checked, iterations=iterations, softness=softness)
        times = np.r_[0.0, np.cumsum(dts)]
        for k in range(1, len(checked)):
            sf = pair_flow(checked[k - 1], checked[k], motion_between(R, t, k - 1, k),
                           dts[k - 1])
            if shrinkage == 'jitter':       # the 5 clouds about the pair (offline)
                lo = min(max(0, k - 3), max(0, len(checked) - 5))
                hi = min(lo + 5, len(checked))
                sf = shrunk(sf, checked[lo:hi], R[lo:hi], t[lo:hi], dts[k - 1], times[lo:hi])
            out.append(sf)
        return out
    for k in range(1, len(checked)):
        hist = checked[max(0, k + 1 - window):k - 1] if window > 1 else []
        out.append(scene_flow(*checked[k - 1], *checked[k], dts[k - 1], frame, hist,
                              iterations, softness, shrinkage))
    return out


def centred_flow(clouds: Sequence[Cloud], R: np.ndarray, t: np.ndarray, k: int,
                 times: Sequence[float] | None = None) -> tuple[SceneFlow, np.ndarray]:
    """The flow of the pair (``clouds[k-1]``, ``clouds[k]``) from a per-track polynomial in
    time over the whole window (poses R, t from :func:`object_poses` / :func:`known_poses`):
    each track seen in every cloud gets ``R_{k-1} (p(t_k) - p(t_{k-1})) / dt``, ``p`` its
    object-frame trajectory ``Y_f = R_f^T (X_f - t_f)`` fitted by a quadratic (linear on 3
    clouds); the rest the raw difference (:func:`pair_flow`).  With clouds after ``k`` in the
    window (look-ahead) the fit is centred on the pair: on the 30 deg sweep renders the
    relative EPE of the noisy cases fell 20-40% (sheet 1.49 -> 0.88 with three clouds each
    side; BENCHMARKS issue 14).  Also returns each point's noise gain ``g``: the variance of
    its displacement per unit position jitter variance per coordinate, over 2 (1 for the raw
    difference, ``Var(Y_b - Y_a) = 2 sigma^2``; below 1 where the fit averages), so that the
    shrinkage can use ``6 g sigma^2``."""
    w = len(clouds)
    if not 1 <= k < w:
        raise ValueError(f'k={k}: expected 1..{w - 1} for a window of {w} clouds')
    tau = np.arange(w, dtype=np.float64) if times is None else np.asarray(times, np.float64)
    if tau.shape != (w,) or not np.all(np.isfinite(tau)) or np.any(np.diff(tau) <= 0):
        raise ValueError(f'times: expected {w} increasing finite stamps, got {tau}')
    dt = float(tau[k] - tau[k - 1])
    sf = pair_flow(clouds[k - 1], clouds[k], motion_between(R, t, k - 1, k), dt)
    gain = np.ones(sf.ids.size)
    if w < 3:
        return sf, gain
    common = _common(sf.ids.astype(np.int64),
                     [i for f, (_, i) in enumerate(clouds) if f not in (k - 1, k)])
    if not common.size:
        return sf, gain
    s = (tau - tau[k - 1]) / max(float(np.ptp(tau)), 1e-300)   # conditioning
    degree = 2 if w >= 4 else 1
    A = np.vander(s, degree + 1, increasing=True)
    g = A[k] - A[k - 1]                                   # p(t_k) - p(t_{k-1}) = g . coef
    h = np.linalg.lstsq(A, np.eye(w), rcond=None)[0].T @ g   # displacement = h . Y (w,)
    # d_obj = sum_f h_f Y_f, the clouds' rows of the common ids weighted in one pass each
    d_obj = np.zeros((common.size, 3))                       # (n, 3) object axes
    none = np.zeros(0, np.intp)
    for f, (X, i) in enumerate(clouds):
        if i.shape == common.shape and np.array_equal(i, common):   # already in that order
            rows = none
        else:
            order = np.argsort(i, kind='stable')
            rows = order[np.searchsorted(i, common, sorter=order)]
        add_object_displacement(d_obj, np.ascontiguousarray(X, np.float64), rows,
                                np.asarray(t[f], np.float64), np.asarray(R[f], np.float64),
                                float(h[f]))
    velocity = sf.velocity.copy()
    if sf.ids.shape == common.shape and np.array_equal(sf.ids, common):
        where: slice | np.ndarray = slice(None)
    else:
        where = np.searchsorted(sf.ids.astype(np.int64), common)   # sf.ids sorted
    velocity[where] = d_obj @ R[k - 1].T / dt
    gain[where] = float(h @ h) / 2.0
    return replace(sf, velocity=velocity), gain
