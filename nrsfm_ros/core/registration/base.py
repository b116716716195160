"""What every registration method shares: the result type, the input and parameter checks, Kabsch,
the normalisation of a pair of sets, and one meaning of ``fitness`` / ``inlier_rmse``.

Fitness and inlier RMSE are computed here, the same way for every method, from the aligned source
and one distance threshold ``inlier_threshold`` (input units; 0 picks 2% of the target's
bounding-box diagonal): a source point is an inlier when its nearest target point is within the
threshold; ``fitness`` is the inlier fraction of the source, ``inlier_rmse`` the RMS distance of
the inliers (NaN when there are none).  The iterations of a method may use their own thresholds
(ICP's ``max_correspondence_distance``, CPD's variance); the reported numbers do not.

``PARAM_RULES`` holds the checks of the parameters several methods (and the registrar node) take;
each is a function of the value returning None or the reason it is invalid.
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

DEFAULT_INLIER_FRACTION = 0.02       # of the target's bounding-box diagonal
MIN_POINT_BUDGET = 10                # fewest source points a method may iterate on


@dataclass(frozen=True)
class RegistrationResult:
    """T_target_source (4x4) maps source points into the target frame (identity for non-rigid
    methods); ``aligned`` (N, 3) the source after registration; ``displacement`` aligned -
    source; ``correspondences`` (N,) nearest target index per source point, -1 beyond
    ``inlier_threshold``; ``fitness`` inlier fraction of the source; ``inlier_rmse`` RMS distance
    of the inliers; ``converged`` False also when a global start found no unambiguous pose."""

    T_target_source: np.ndarray
    aligned: np.ndarray
    displacement: np.ndarray
    correspondences: np.ndarray
    iterations: int
    converged: bool
    fitness: float
    inlier_rmse: float
    inlier_threshold: float
    seconds: float
    method: str

    @property
    def residual(self) -> float:
        """The inlier RMSE (the name earlier versions used)."""
        return self.inlier_rmse


# ---------------------------------------------------------------- parameter and input checks

Rule = Callable[[Any], 'str | None']


def _finite(v: Any) -> bool:
    return isinstance(v, (int, float, np.floating, np.integer)) and not isinstance(v, bool) \
        and math.isfinite(float(v))


def _positive(v: Any) -> str | None:
    return None if _finite(v) and v > 0 else 'must be a finite number > 0'


def _non_negative(v: Any) -> str | None:
    return None if _finite(v) and v >= 0 else 'must be a finite number >= 0'


PARAM_RULES: dict[str, Rule] = {
    'trim': lambda v: None if _finite(v) and 0.1 <= v <= 1 else 'must be in [0.1, 1]',
    'polish_trim': lambda v: None if _finite(v) and (v == 0 or 0.1 <= v <= 1)
    else 'must be 0 (off) or in [0.1, 1]',
    'w': lambda v: None if _finite(v) and 0 <= v < 1 else 'must be in [0, 1)',
    'voxel': _non_negative,
    'tolerance': _positive,
    'max_iterations': lambda v: None if _finite(v) and v >= 1 else 'must be >= 1',
    'beta': _positive,
    'lam': _positive,
    'inlier_threshold': lambda v: None if _finite(v) and v >= 0
    else 'must be >= 0 (0: 2% of the target diagonal)',
    'depth_weight': lambda v: None if _finite(v) and 0 <= v <= 1 else 'must be in [0, 1]',
    'max_points': lambda v: None if _finite(v) and v == int(v) and (
        v == 0 or v >= MIN_POINT_BUDGET) else f'must be 0 (all) or >= {MIN_POINT_BUDGET}',
}


def check_param(name: str, value: Any) -> None:
    """Raise ValueError naming the field and the value when ``PARAM_RULES[name]`` rejects it."""
    reason = PARAM_RULES[name](value)
    if reason:
        raise ValueError(f'{name}={value!r}: {reason}')


def check_points(name: str, X: np.ndarray, min_points: int = 3) -> np.ndarray:
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f'{name}: expected shape (N, 3), got {X.shape}')
    if X.shape[0] < min_points:
        raise ValueError(f'{name}: need at least {min_points} points, got {X.shape[0]}')
    if not np.isfinite(X).all():
        raise ValueError(f'{name}: contains NaN or inf; drop invalid points first')
    if not (X.max(axis=0) > X.min(axis=0)).any():
        raise ValueError(f'{name}: all {X.shape[0]} points coincide; a cloud needs extent to be '
                         f'registered')
    return X


def check_priors(priors: np.ndarray | None, n_source: int, n_target: int) -> np.ndarray | None:
    """Prior matches as (K, 2) integer (source index, target index) pairs, or None if empty."""
    if priors is None or len(priors) == 0:
        return None
    priors = np.asarray(priors)
    if priors.ndim != 2 or priors.shape[1] != 2 or not np.issubdtype(priors.dtype, np.integer):
        raise ValueError(f'priors: expected (K, 2) integer (source, target) index pairs, got '
                         f'{priors.dtype} {priors.shape}')
    if priors.min() < 0 or priors[:, 0].max() >= n_source or priors[:, 1].max() >= n_target:
        raise ValueError(f'priors: an index is out of range of the {n_source} source and '
                         f'{n_target} target points')
    return priors


# ---------------------------------------------------------------- geometry

def normalise_pair(X: np.ndarray, Y: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """Target X and source Y each centred on its centroid and both scaled by one factor (the
    larger RMS radius): (Xn, Yn, cx, cy, sc)."""
    cx, cy = X.mean(0), Y.mean(0)
    sc = max(float(np.sqrt(((X - cx) ** 2).sum(1).mean())),
             float(np.sqrt(((Y - cy) ** 2).sum(1).mean())), 1e-12)
    return (X - cx) / sc, (Y - cy) / sc, cx, cy, sc


def denormalise(T: np.ndarray, cx: np.ndarray, cy: np.ndarray, sc: float) -> np.ndarray:
    """T between normalised sets (y_n = (y - cy) / sc, x_n = (x - cx) / sc) in input units."""
    out = np.eye(4)
    out[:3, :3] = T[:3, :3]
    out[:3, 3] = cx + sc * T[:3, 3] - T[:3, :3] @ cy
    return out


def kabsch(A: np.ndarray, B: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """4x4 rigid T minimising sum w ||T A - B||^2 (rows are points)."""
    w = np.ones(A.shape[0]) if w is None else w
    ws = w / max(w.sum(), 1e-300)
    ca, cb = ws @ A, ws @ B
    H = (A - ca).T @ ((B - cb) * ws[:, None])
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = cb - R @ ca
    return T


def apply(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    return X @ T[:3, :3].T + T[:3, 3]


def diagonal(X: np.ndarray) -> float:
    return float(np.linalg.norm(X.max(0) - X.min(0)))


# ---------------------------------------------------------------- one meaning of fitness

def resolve_threshold(target: np.ndarray, inlier_threshold: float) -> float:
    """The inlier distance in input units: ``inlier_threshold`` when > 0, else 2% of the
    target's bounding-box diagonal."""
    check_param('inlier_threshold', inlier_threshold)
    if inlier_threshold > 0:
        return float(inlier_threshold)
    return max(DEFAULT_INLIER_FRACTION * diagonal(target), 1e-12)


def inlier_stats(aligned: np.ndarray, tree: cKDTree, threshold: float,
                 index: np.ndarray | None = None) -> tuple[np.ndarray, float, float]:
    """(correspondences, fitness, inlier_rmse) of ``aligned`` against the target points of
    ``tree`` (``index`` maps tree rows to target indices).  The query stops at ``threshold``
    (exact for every inlier; an outlier's distance is not needed), 4-6x faster at 100k points
    where much of the cloud is off the target."""
    dist, corr = tree.query(aligned, workers=-1, distance_upper_bound=threshold)
    ok = dist <= threshold
    corr = np.where(ok, corr, 0)
    if index is not None:
        corr = index[corr]
    rmse = float(np.sqrt(np.mean(dist[ok] ** 2))) if ok.any() else float('nan')
    return np.where(ok, corr, -1), float(ok.mean()), rmse


def robust_residual(aligned: np.ndarray, tree: cKDTree, threshold: float) -> float:
    """Mean of min(d^2, threshold^2) over the source: low when many points sit close, so it
    ranks two results on one scale (outliers count as the threshold, not as their distance).
    The query stops at ``threshold``: exact, since farther distances are clipped to it."""
    dist = tree.query(aligned, workers=-1, distance_upper_bound=threshold)[0]
    return float(np.mean(np.minimum(dist, threshold) ** 2))


def make_result(source: np.ndarray, aligned: np.ndarray, T: np.ndarray, tree: cKDTree,
                threshold: float, method: str, iterations: int, converged: bool, t0: float,
                index: np.ndarray | None = None) -> RegistrationResult:
    """The result of any method: its aligned points scored by ``inlier_stats``."""
    corr, fitness, rmse = inlier_stats(aligned, tree, threshold, index)
    return RegistrationResult(T_target_source=T, aligned=aligned, displacement=aligned - source,
                              correspondences=corr, iterations=int(iterations),
                              converged=bool(converged), fitness=fitness, inlier_rmse=rmse,
                              inlier_threshold=float(threshold),
                              seconds=time.perf_counter() - t0, method=method)


def rigid_result(source: np.ndarray, T: np.ndarray, tree: cKDTree, threshold: float,
                 method: str, iterations: int, converged: bool, t0: float,
                 index: np.ndarray | None = None) -> RegistrationResult:
    return make_result(source, apply(T, source), T, tree, threshold, method, iterations,
                       converged, t0, index)
