"""NRGA: non-rigid gravitational registration (Ali, Golyanik, Stricker; METHODS §10.3).

Every source particle moves under the softened gravity of its ``k`` nearest target points (a
cKDTree, so the cost stays O(N log M) per step): the force is
sum_j m_j (x_j - y_i) / (|x_j - y_i|^2 + eps^2)^(3/2), taken as the force-weighted mean offset so
the step does not depend on the absolute force scale.  Damped semi-implicit Euler dynamics move
the particles; after every step the displacement field is projected onto coherent collective
motions -- the ridge fit of a Gaussian-kernel field (width ``beta``, weight ``lam``) in the
Nystrom features of the source -- so neighbours move together and the swarm cannot collapse onto
the nearest target points.  The softening eps is annealed from ``eps_start`` to ``eps_end``.
The iterations run on at most ``max_points`` source points; the same features extend the field
to every source point.  Inputs are centred and scaled to unit RMS radius (one scale for both
sets); parameters are in those units.

What differs from the paper's code: the local as-rigid-as-possible blending of kNN
neighbourhoods is replaced by the global Gaussian-kernel coherence used by CPD (the motion
coherence the thesis adopts for CDF), which keeps one smooth field for the whole swarm.
"""
from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from .base import (RegistrationResult, check_param, check_points, make_result, normalise_pair,
                   resolve_threshold)
from .kernels import Nystrom


def nrga(source: np.ndarray, target: np.ndarray, k: int = 8, iterations: int = 150,
         dt: float = 0.5, damping: float = 0.3, beta: float = 2.0, lam: float = 3e-3,
         eps_start: float = 0.2, eps_end: float = 0.02, max_points: int = 4000,
         landmarks: int = 300, seed: int = 0, inlier_threshold: float = 0.0
         ) -> RegistrationResult:
    """Non-rigid gravitational registration of ``source`` (N, 3) onto ``target`` (M, 3)."""
    t0 = time.perf_counter()
    Y0 = check_points('source', source)
    X0 = check_points('target', target)
    check_param('beta', beta)
    check_param('lam', lam)
    for name, v in (('dt', dt), ('eps_start', eps_start), ('eps_end', eps_end)):
        if not v > 0:
            raise ValueError(f'{name}={v}: expected > 0')
    if not 0 <= damping < 1:
        raise ValueError(f'damping={damping}: expected 0 <= damping < 1')
    if k < 1 or iterations < 1 or max_points < 10 or landmarks < 1:
        raise ValueError(f'k={k}, iterations={iterations}, max_points={max_points}, '
                         f'landmarks={landmarks}: expected >= 1, >= 1, >= 10, >= 1')
    threshold = resolve_threshold(X0, inlier_threshold)
    rng = np.random.default_rng(seed)
    Xn, Yn, cx, cy, sc = normalise_pair(X0, Y0)
    yi = rng.choice(len(Yn), max_points, replace=False) if len(Yn) > max_points \
        else np.arange(len(Yn))
    Y = Yn[yi]
    tree = cKDTree(Xn)
    k = min(k, len(Xn))
    nys = Nystrom(Y, beta, landmarks, rng)
    Phi = nys.features(Y)                                        # (n, L)
    L = Phi.shape[1]
    fit = np.linalg.solve(Phi.T @ Phi + lam * np.eye(L), Phi.T)  # displacement -> coefficients
    a = np.zeros((L, 3))
    vel = np.zeros_like(Y)
    epss = np.geomspace(eps_start, eps_end, iterations)
    for eps in epss:
        cur = Y + Phi @ a
        _, idx = tree.query(cur, k=k, workers=-1)
        d = Xn[idx.reshape(len(Y), k)] - cur[:, None, :]
        r2 = (d * d).sum(-1) + eps * eps
        w = 1.0 / (r2 * np.sqrt(r2))
        force = (w[:, :, None] * d).sum(1) / w.sum(1, keepdims=True)
        vel = (1.0 - damping) * vel + dt * force
        a = fit @ (cur + vel - Y)                                # coherent projection
        vel = Y + Phi @ a - cur
    aligned = (Yn + nys.features(Yn) @ a) * sc + cx
    return make_result(Y0, aligned, np.eye(4), cKDTree(X0), threshold, 'nrga', iterations, True,
                       t0)
