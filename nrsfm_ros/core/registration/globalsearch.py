"""Global rigid pose search: a start for local registration from any rotation, robust to outliers
and partial overlap.

Local methods (ICP, CPD, GA) converge only from poses near the truth; with clustered missing
parts and dense outliers their basins shrink and wrong poses become strong local optima.  This
search needs no features and no correspondences:

1. Outlier filter: a point whose distance to its 8th neighbour exceeds 1.5 x the 30th percentile
   of that distance over its own cloud lies off any sampled surface and is dropped (uniform
   clutter is an order of magnitude sparser than a scanned surface).
2. The filtered target becomes a distance field: a grid over its padded bounding box whose cells
   store their nearest target point (one exact Euclidean distance transform).  Nearest-point
   queries are then one array lookup, vectorised over all hypotheses at once.
3. Rotations: ``rotations`` evenly spread samples of SO(3) (super-Fibonacci spirals, Alexa,
   CVPR 2022).  For each, the translation follows a truncated mean shift of a coarse source
   (4 steps, pairs within 3 delta), and the hypothesis is scored by the truncated quadratic
   sum(max(0, 1 - d^2 / delta^2)) over the source points (delta 3% of the source's diagonal).
4. The ``candidates`` best hypotheses at least ``PICK_DEG`` (30) degrees apart are picked (15
   degrees apart, the 8 best of a near-symmetric sheet all lay in its flipped basin) and each
   is zoomed into: rescored at 29 rotations around it (4 and 8 degrees about 14 axes) and
   replaced by the best of them.
5. Multi-start refinement in tiers of trimmed point-to-plane ICP: every pick on a grid of 8% of
   the diagonal, the ``MID_CANDIDATES`` best on 4%, then the best and the best at another pose
   (> ``AMBIGUOUS_DEG`` away) on 2%; each scored by the soft inlier fraction at a fine delta
   (1% of the diagonal) against the 1% target grid.  The best wins; it is ``ambiguous`` when
   the other scores at least ``AMBIGUOUS_RATIO`` of it (a symmetry of the shape: distinct
   rotations that the data do not tell apart; ``icp`` then reports ``converged`` False).

Cost at 35k points a side: about 1.1 s CPU (kNN filter of each cloud 0.15 s, the rotation
scores 0.35 s, the candidate ICPs 0.4 s).  ``icp(..., init='global')`` runs it and then
``refine.fine_levels`` on the filtered target.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from .refine import icp_iterate, icp_levels, voxel_downsample


@dataclass(frozen=True)
class GlobalPose:
    """Best pose T_target_source, its fine score (the soft fraction of source points
    explained), the score of each candidate after its last refinement tier, the target's inlier
    mask from the density filter, and ``ambiguous``: the best candidate at another pose
    (> ``AMBIGUOUS_DEG`` away) scores at least ``AMBIGUOUS_RATIO`` of the best (the data do not
    tell the poses apart)."""

    T_target_source: np.ndarray
    score: float
    candidate_scores: np.ndarray
    target_inliers: np.ndarray
    ambiguous: bool = False


AMBIGUOUS_DEG = 10.0
AMBIGUOUS_RATIO = 0.9
COARSE_ITERATIONS = 30
MID_CANDIDATES = 5        # refined on the middle grid (2 x 2% of the diagonal)
PICK_DEG = 30.0          # the coarse picks at least this far apart
SCORE_POINTS = 3000       # source points that score a coarse candidate
FINE_ITERATIONS = 30


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1))))


def so3_samples(n: int) -> np.ndarray:
    """``n`` rotation matrices spread evenly over SO(3) (super-Fibonacci spirals)."""
    if n < 1:
        raise ValueError(f'rotations: expected >= 1, got {n}')
    phi, psi = np.sqrt(2.0), 1.533751168755204288118041
    i = np.arange(n) + 0.5
    s = i / n
    r, rr = np.sqrt(s), np.sqrt(1.0 - s)
    a, b = 2 * np.pi * i / phi, 2 * np.pi * i / psi
    q = np.stack([r * np.sin(a), r * np.cos(a), rr * np.sin(b), rr * np.cos(b)], axis=1)
    return Rotation.from_quat(q).as_matrix()


def density_inliers(X: np.ndarray, k: int = 8, factor: float = 1.5,
                    quantile: float = 0.3) -> np.ndarray:
    """Mask of points whose k-th neighbour distance is below ``factor`` times the
    ``quantile`` of that distance over the cloud (sparse clutter off the surface is False)."""
    if X.shape[0] <= k + 1:
        return np.ones(X.shape[0], bool)
    d = cKDTree(X).query(X, k=k + 1, workers=-1)[0][:, -1]
    return d <= factor * np.quantile(d, quantile)


class DistanceField:
    """Nearest target point for any query, by lookup in a grid (edge ``h``) over the target's
    bounding box padded by ``pad``; outside the box the nearest cell of its border answers."""

    def __init__(self, X: np.ndarray, h: float, pad: float) -> None:
        self.lo = X.min(0) - pad
        self.h = h
        self.dims = np.ceil((X.max(0) + pad - self.lo) / h).astype(np.intp) + 1
        empty = np.ones(tuple(self.dims), bool)
        ijk = np.floor((X - self.lo) / h).astype(np.intp)
        empty[tuple(ijk.T)] = False
        # the representative of each occupied cell: one of its points
        rep = np.zeros(tuple(self.dims) + (3,))
        rep[tuple(ijk.T)] = X
        idx = distance_transform_edt(empty, return_distances=False, return_indices=True)
        self.near = rep[idx[0], idx[1], idx[2]].reshape(-1, 3)

    def nearest(self, Q: np.ndarray) -> np.ndarray:
        g = np.floor((Q - self.lo) / self.h).astype(np.intp)
        np.clip(g, 0, self.dims - 1, out=g)
        flat = (g[..., 0] * self.dims[1] + g[..., 1]) * self.dims[2] + g[..., 2]
        return self.near[flat]


def score_rotations(Rs: np.ndarray, Yc: np.ndarray, t: np.ndarray, field: DistanceField,
                    delta: float) -> tuple[np.ndarray, np.ndarray]:
    """For each rotation of ``Rs`` (R, 3, 3) of the centred coarse source ``Yc``: the
    translation after a truncated mean shift from ``t`` (R, 3) (4 steps, pairs within 3
    ``delta``) and the truncated quadratic score sum(max(0, 1 - d^2 / delta^2))."""
    P = np.einsum('rij,nj->rni', Rs, Yc)                  # (rotations, n, 3)
    t = t.copy()
    for _ in range(4):
        Q = P + t[:, None]
        d = field.nearest(Q) - Q
        w = (d ** 2).sum(-1) < (3 * delta) ** 2
        t += (d * w[..., None]).sum(1) / np.maximum(w.sum(1), 1)[:, None]
    Q = P + t[:, None]
    return t, np.clip(1 - ((field.nearest(Q) - Q) ** 2).sum(-1) / delta ** 2, 0, None).sum(1)


def local_rotations(steps: tuple[float, ...] = (4.0, 8.0)) -> np.ndarray:
    """The identity and rotations by each of ``steps`` degrees about 14 axes (the directions
    to the faces and corners of a cube): a local grid around a sample of SO(3)."""
    ax = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                   if abs(i) + abs(j) + abs(k) in (1, 3)], float)
    ax /= np.linalg.norm(ax, axis=1, keepdims=True)
    vecs = np.vstack([np.zeros((1, 3)), *(np.radians(a) * ax for a in steps)])
    return Rotation.from_rotvec(vecs).as_matrix()


def global_pose(source: np.ndarray, target: np.ndarray, rotations: int = 600,
                candidates: int = 12, trim: float = 0.6) -> GlobalPose:
    """Search SO(3) x R^3 for the pose that best explains ``target`` by ``source`` (both (N, 3),
    input units); see the module docstring.  ``trim``: fraction of pairs kept by the candidate
    refinement (below the expected overlap)."""
    if candidates < 1:
        raise ValueError(f'candidates: expected >= 1, got {candidates}')
    keep_t = density_inliers(target)
    src = source[density_inliers(source)]
    tgt = target[keep_t]
    diag = float(np.linalg.norm(src.max(0) - src.min(0)))
    if tgt.shape[0] < 3 or diag <= 0:
        raise ValueError('target: fewer than 3 points left after the outlier filter')
    delta = 0.03 * diag
    X = voxel_downsample(tgt, 0.02 * diag)
    Y = voxel_downsample(src, 0.05 * diag)
    field = DistanceField(X, 0.01 * diag, 0.12 * diag)   # pad: beyond 3 delta nothing counts
    Rs = so3_samples(rotations)
    cy = Y.mean(0)
    t, score = score_rotations(Rs, Y - cy, np.tile(X.mean(0), (rotations, 1)), field, delta)
    picked: list[int] = []
    for r in np.argsort(-score):                            # best first, 15 deg apart
        if all(np.arccos(np.clip((np.trace(Rs[r].T @ Rs[p]) - 1) / 2, -1, 1))
               > np.radians(PICK_DEG) for p in picked):
            picked.append(int(r))
            if len(picked) == candidates:
                break
    # zoom in: each pick rescored at the rotations around it (a finer SO(3) grid, half the
    # sample spacing) and replaced by the best of its neighbourhood, so that the ICP below
    # starts a few degrees from its basin's bottom rather than up to the full sample gap
    near = local_rotations()
    Rz = np.einsum('kij,cjl->ckil', near, Rs[picked]).reshape(-1, 3, 3)
    tz = np.repeat(t[picked], len(near), axis=0)
    tz, sz = score_rotations(Rz, Y - cy, tz, field, delta)
    bestz = sz.reshape(len(picked), len(near)).argmax(1) + np.arange(len(picked)) * len(near)
    starts = [(Rz[b], tz[b]) for b in bestz]
    # refine each on the two coarse grids (4 and 2 x 2% of the diagonal: few points, cheap
    # iterations, so many of them), rescore at a fine delta (1% of the diagonal) on the 1% grid
    Xf = voxel_downsample(tgt, 0.01 * diag)
    Yf = voxel_downsample(src, 0.01 * diag)
    tree = cKDTree(Xf)
    levels = icp_levels(Yf, Xf, 'point_to_plane', 0.02 * diag, 0)   # shared by the candidates

    Ys = Yf[np.linspace(0, len(Yf) - 1, min(len(Yf), SCORE_POINTS)).astype(np.intp)]

    def score_of(T: np.ndarray, Y: np.ndarray = Ys) -> float:
        """Source points explained (soft count at 1% of the diagonal), per point of ``Y``."""
        d = tree.query(Y @ T[:3, :3].T + T[:3, 3], distance_upper_bound=0.01 * diag)[0]
        return float(np.clip(1 - d ** 2 / (0.01 * diag) ** 2, 0, None).mean())

    scores = np.zeros(len(starts))
    poses = []
    for c, (Rc, tc) in enumerate(starts):
        T0 = np.eye(4)
        T0[:3, :3] = Rc
        T0[:3, 3] = tc - Rc @ cy
        T = icp_iterate(levels[:1], T0, 'point_to_plane', COARSE_ITERATIONS, 1e-6, np.inf,
                        trim, 0.02 * diag)[0]
        poses.append(T)
        scores[c] = score_of(T)
    for c in np.argsort(-scores)[:MID_CANDIDATES]:          # the best few on the middle grid
        poses[c] = icp_iterate(levels[1:2], poses[c], 'point_to_plane', COARSE_ITERATIONS,
                               1e-6, np.inf, trim, 0.02 * diag)[0]
        scores[c] = score_of(poses[c])
    # the best and the best at another pose (> AMBIGUOUS_DEG away) also on the fine grid
    order = np.argsort(-scores)
    top = [int(order[0])]
    top += [int(c) for c in order[1:] if rotation_angle_deg(
        poses[c][:3, :3], poses[top[0]][:3, :3]) > AMBIGUOUS_DEG][:1]
    for c in top:
        poses[c] = icp_iterate(levels[2:], poses[c], 'point_to_plane', FINE_ITERATIONS, 1e-6,
                               np.inf, trim, 0.02 * diag)[0]
        scores[c] = score_of(poses[c], Yf)
    top.sort(key=lambda c: -scores[c])
    best_T, best = poses[top[0]], float(scores[top[0]])
    ambiguous = len(top) > 1 and scores[top[1]] >= AMBIGUOUS_RATIO * best and \
        rotation_angle_deg(poses[top[1]][:3, :3], best_T[:3, :3]) > AMBIGUOUS_DEG
    if ambiguous:       # a (near) symmetry: a feature that breaks it may still decide
        T, sc = symmetry_sweep(Yf, best_T, tree, levels[1:], trim, diag,
                               lambda T: score_of(T, Yf), best)
        if sc > -np.inf:                # a feature was found: the sweep's choice stands
            best_T, best = T, sc
    return GlobalPose(T_target_source=best_T, score=best, candidate_scores=scores,
                      target_inliers=keep_t, ambiguous=bool(ambiguous))



SWEEP_STEP_DEG = 5.0      # symmetry_sweep: turns about the symmetry axis this far apart
SWEEP_FEATURE_TIE = 0.9   # symmetry_sweep: features this close to the best one's tie
SWEEP_FEATURE = 0.05      # symmetry_sweep: at most this share of source points (and at
SWEEP_MIN_FEATURE = 50    #   least these) score the turns: the feature, if it is found
SWEEP_REFINED = 3         # symmetry_sweep: the best turns refined by ICP and rescored
SWEEP_KEPT = 0.8          # symmetry_sweep: turns about an axis keep this share of the fit
SWEEP_POINTS = 8000       # symmetry_sweep: source points searched for the feature


def symmetry_sweep(Y: np.ndarray, T: np.ndarray, tree: cKDTree, levels: list,
                   trim: float, diag: float, score: Callable[[np.ndarray], float],
                   score_T: float | None = None) -> tuple[np.ndarray, float]:
    """Where the best poses are ambiguous, a (near) symmetry of the shape: a feature that
    breaks it (a knob on a cylinder) may still decide, but it is too small a share of the
    points for the search's scores.  The aligned source (``Y`` at pose ``T``, target frame) is
    turned about each of its principal axes through its centroid (the axis of a rotational
    symmetry is one of them) by 45 to 315 degrees; the axis whose turns keep the most points
    explained is the symmetry axis (none where no axis keeps ``SWEEP_KEPT`` of the fit at
    ``T``, e.g. a box's flips: ``T`` is returned with score -inf).  The source points (of
    ``SWEEP_POINTS``) that stay off the source's own surface (3 x the median distance) at most
    of 11 turns about it (at most ``SWEEP_FEATURE`` of them: the feature, where the source is
    not a surface of revolution; on the corpus' cylinder its knob, ~0.2% of the points; taken
    from the source, not the target, so that the target's missing part and clutter are not
    mistaken for it) score turns about it every ``SWEEP_STEP_DEG``, each also flipped end over
    end (180 degrees about another principal axis); the ``SWEEP_REFINED`` best are refined on
    ``levels``.  Among ``T`` and them, those scoring at least ``AMBIGUOUS_RATIO`` of the best
    (``score``) keep the fit alike; of these the feature decides (its soft count on the
    target), and the total score among features within ``SWEEP_FEATURE_TIE`` of the best one.
    Soft counts within 1% of the diagonal against exact nearest target points (``tree``);
    ``score_T``: ``score(T)`` where the caller has it.  Returns (the chosen pose, its score).
    """
    h2 = (0.01 * diag) ** 2

    def soft(Q: np.ndarray) -> np.ndarray:     # zero beyond 1% of the diagonal: stop there
        d = tree.query(Q.reshape(-1, 3), workers=-1, distance_upper_bound=0.01 * diag
                       )[0].reshape(Q.shape[:-1])
        return np.clip(1 - d ** 2 / h2, 0, None)

    def turned(R: np.ndarray, X: np.ndarray) -> np.ndarray:     # R (h, 3, 3) about c
        return np.einsum('hij,nj->hni', R, X - c) + c

    A = Y @ T[:3, :3].T + T[:3, 3]
    c = A.mean(0)
    axes = np.linalg.eigh(np.cov((A - c).T))[1].T
    quarter = np.radians(np.arange(45.0, 360.0, 45.0))
    P = A[np.linspace(0, len(A) - 1, min(len(A), 1500)).astype(np.intp)]
    kept = [soft(turned(Rotation.from_rotvec(np.outer(quarter, ax)).as_matrix(), P)).mean()
            for ax in axes]
    k = int(np.argmax(kept))
    if kept[k] < SWEEP_KEPT * soft(P[None]).mean():
        return T, -np.inf               # no axis of a continuous symmetry (a box's flips)
    axis, other = axes[k], axes[(k + 1) % 3]
    # the feature: points off the source's own surface (3x the median distance) at most of
    # 11 turns about the axis: where the source itself is not a surface of revolution (not
    # where the target is cut or cluttered)
    A_all = A
    A = A[::max(1, len(A) // SWEEP_POINTS)]
    Q = turned(Rotation.from_rotvec(np.outer(np.radians(np.arange(30.0, 360.0, 30.0)), axis)
                                    ).as_matrix(), A)
    d = cKDTree(A_all).query(Q.reshape(-1, 3), workers=-1)[0].reshape(Q.shape[:-1])
    off = (d > 3 * np.median(d)).mean(0)
    pick = np.argsort(-off)[:max(SWEEP_MIN_FEATURE, int(SWEEP_FEATURE * len(A)))]
    pick = pick[off[pick] >= 0.5]
    if pick.size < SWEEP_MIN_FEATURE // 5:
        return T, -np.inf                                # nothing breaks the symmetry
    F = A[pick]
    F_src = Y[::max(1, len(Y) // SWEEP_POINTS)][pick]          # the feature, source frame
    turns = Rotation.from_rotvec(np.outer(np.radians(np.arange(0.0, 360.0, SWEEP_STEP_DEG)),
                                          axis)).as_matrix()
    flip = Rotation.from_rotvec(np.pi * other).as_matrix()
    H = np.concatenate([turns, turns @ flip])
    order = np.argsort(-soft(turned(H, F)).sum(1))
    poses, totals = [T], [score(T) if score_T is None else score_T]
    for h in order[:SWEEP_REFINED]:
        Th = np.eye(4)
        Th[:3, :3] = H[h] @ T[:3, :3]
        Th[:3, 3] = H[h] @ (T[:3, 3] - c) + c
        Th = icp_iterate(levels, Th, 'point_to_plane', FINE_ITERATIONS, 1e-6, np.inf, trim,
                         0.02 * diag)[0]
        poses.append(Th)
        totals.append(score(Th))
    # the turns explain (nearly) all points alike: the feature decides among those that keep
    # the fit, the total score only where a turn loses it
    feature = [float(soft((F_src @ P[:3, :3].T + P[:3, 3])[None]).mean()) for P in poses]
    ok = [i for i, s in enumerate(totals) if s >= AMBIGUOUS_RATIO * max(totals)]
    top = max(feature[i] for i in ok)
    i = max((i for i in ok if feature[i] >= SWEEP_FEATURE_TIE * top), key=lambda i: totals[i])
    return poses[i], totals[i]
