"""Rigid pose of a camera-frame cloud from matched points, trusting its viewing rays more than
its depth (the registrar's ``match: track_id``).

A monocular reconstruction in a camera's optical frame (the reconstructor's nrsfm/points) knows
where each point lies in the image far better than how far away it is: its rays come from the
tracks, its depth from the factorisation, which at small camera motion barely observes it.  So
the residual of a target point p mapped into the source camera, ``y = G p``, against its matched
source point x splits into the part across x's viewing ray (weight 1) and the part along it
(weight ``depth_weight``^2):

    r^2 = |(I - d d^T)(y - x)|^2 + depth_weight^2 (d^T (y - x))^2,   d = x / |x|.

``depth_weight`` 1 is the point-to-point (Kabsch) residual; 0 the object-space collinearity of
PnP (Lu, Hager and Mjolsness' orthogonal iteration), where the cloud's depth is not used at all.
It is minimised by Gauss-Newton on the rotation vector and translation of G, re-weighted each
iteration by Cauchy weights 1 / (1 + (r / threshold)^2) against the points that deform.  The
depth reflection of a monocular reconstruction (orthographic NRSfM cannot tell it) is the
source mirrored along its rays about its mean depth: ``mirror_along_rays``.
"""
from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from ._rays_kernel import ray_normal_equations, ray_residual_lengths
from .base import RegistrationResult, apply, check_param, make_result

MIN_MATCHES = 6          # fewest matched points a pose is solved from
# below this fraction of the matches within the threshold of the pose, the matches do not name
# the same points (track ids from an unrelated source): the pipeline's reconstructions keep
# >= 0.16 (flag 60 deg amplitude 2), shuffled ids of the same clouds <= 0.01
MIN_INLIER_FRACTION = 0.05


def _rodrigues(w: np.ndarray) -> np.ndarray:
    a = float(np.linalg.norm(w))
    if a < 1e-12:
        return np.eye(3)
    k = w / a
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def invert(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def mirror_along_rays(X: np.ndarray) -> np.ndarray:
    """``X`` (N, 3, camera frame, z > 0) with its depth reflected about the mean depth, every
    point kept on its viewing ray (the other depth reflection of the same image tracks)."""
    z = X[:, 2]
    zm = float(z.mean())
    scale = np.maximum(2 * zm - z, 1e-3 * zm) / z
    return X * scale[:, None]


def check_rays(X: np.ndarray) -> None:
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f'source shape {X.shape}: expected (N, 3)')
    if X.shape[0] < MIN_MATCHES:
        raise ValueError(f'source has {X.shape[0]} matched points: needs >= {MIN_MATCHES}')
    if not np.isfinite(X).all() or not (X[:, 2] > 0).all():
        raise ValueError('source: every point must be finite and in front of the camera '
                         '(z > 0): it is a cloud in a camera optical frame')


def ray_residuals(G: np.ndarray, target: np.ndarray, source: np.ndarray, d: np.ndarray,
                  depth_weight: float) -> np.ndarray:
    """r (N,) of the target mapped into the source camera by G (see the module); one numba
    pass (the array form's five passes were ~0.5 ms at 30k points, three calls a cloud)."""
    G, target, source, d = (np.ascontiguousarray(a, np.float64) for a in (G, target, source, d))
    return ray_residual_lengths(G, target, source, d, float(depth_weight))


def ray_cost(r: np.ndarray, threshold: float) -> float:
    """Mean of min(r, threshold)^2 (``base.robust_residual``'s form, on the ray residual)."""
    return float(np.mean(np.minimum(r, threshold) ** 2))


def ray_pose(source: np.ndarray, target: np.ndarray, threshold: float,
             depth_weight: float = 0.1, init: np.ndarray | None = None,
             max_iterations: int = 30, tolerance: float = 1e-6, max_points: int = 1000,
             tree: cKDTree | None = None, seed: int = 0, score: bool = True
             ) -> tuple[RegistrationResult, float]:
    """(result, ray cost) of the rigid T_target_source mapping ``source`` (N, 3, a camera
    optical frame) onto ``target`` (N, 3): row i of each is one matched point.  ``init``: a
    start T_target_source (None: identity); ``threshold``: the Cauchy scale and the cost's cap
    (input units); ``max_points`` (0: all) evenly spread points iterate, all are scored;
    ``tree``: a cKDTree of the whole reference for the reported fitness (default: ``target``);
    ``score=False`` skips that fitness (a nearest-neighbour query of every point: ~65 ms at
    100k points, seconds for a far-off mirrored solve) for a caller that scores the moved
    cloud itself: correspondences all -1, fitness and inlier_rmse NaN.
    """
    t0 = time.perf_counter()
    source = np.asarray(source, np.float64)
    target = np.asarray(target, np.float64)
    check_rays(source)
    if target.shape != source.shape or not np.isfinite(target).all():
        raise ValueError(f'target shape {target.shape}: expected {source.shape}, finite')
    for name, v in (('max_iterations', max_iterations), ('tolerance', tolerance),
                    ('max_points', max_points), ('depth_weight', depth_weight)):
        check_param(name, v)
    if not (np.isfinite(threshold) and threshold > 0):
        raise ValueError(f'threshold={threshold}: must be > 0')
    n = source.shape[0]
    idx = np.arange(n) if not max_points or n <= max_points else \
        np.random.default_rng(seed).choice(n, int(max_points), replace=False)
    x, p = source[idx], target[idx]
    d = x / np.linalg.norm(x, axis=1, keepdims=True)
    # W = (I - d d^T) + depth_weight d d^T weighs a 3-vector error (W^T W: the residual's form);
    # applied as v - c d (d . v), never formed (n, 3, 3)
    c = 1.0 - depth_weight
    G = np.eye(4) if init is None else invert(np.asarray(init, np.float64))
    it, prev = 0, np.inf
    x, p, d = (np.ascontiguousarray(a) for a in (x, p, d))
    for it in range(1, int(max_iterations) + 1):
        # Gauss-Newton on (rotation vector, translation), left-multiplied update of G, with
        # Cauchy IRLS weights: J = W [-skew(y) | I] (one pass over the points, numba)
        H, g, r = ray_normal_equations(G, p, x, d, c, float(threshold))
        cost = ray_cost(r, threshold)
        try:
            step = -np.linalg.solve(H + (1e-9 * np.trace(H) + 1e-300) * np.eye(6), g)
        except np.linalg.LinAlgError:
            break
        if not np.isfinite(step).all():          # degenerate matches (e.g. all one point)
            break
        U = np.eye(4)
        U[:3, :3] = _rodrigues(step[:3])
        U[:3, 3] = step[3:]
        G = U @ G
        if abs(prev - cost) <= tolerance * max(prev, 1e-300) and \
                np.linalg.norm(step) < 1e-9 + tolerance:
            break
        prev = cost
    T = invert(G)
    d_all = source / np.linalg.norm(source, axis=1, keepdims=True)
    cost = ray_cost(ray_residuals(G, target, source, d_all, depth_weight), threshold)
    aligned = apply(T, source)
    if not score:
        return RegistrationResult(
            T_target_source=T, aligned=aligned, displacement=aligned - source,
            correspondences=np.full(n, -1, np.intp), iterations=int(it),
            converged=bool(it < max_iterations), fitness=float('nan'),
            inlier_rmse=float('nan'), inlier_threshold=float(threshold),
            seconds=time.perf_counter() - t0, method='rays'), cost
    tree = tree if tree is not None else cKDTree(target)
    res = make_result(source, aligned, T, tree, threshold, 'rays', it,
                      it < max_iterations, t0)
    return res, cost
