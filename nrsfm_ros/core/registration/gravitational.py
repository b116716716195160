"""GA: rigid gravitational point set registration (Golyanik, Ali, Stricker; METHODS §10.1).

The source is a swarm of particles moving through a viscous medium under the softened gravity of
the target: f_i = sum_j m_j (x_j - y_i) / (|x_j - y_i|^2 + eps^2)^(3/2).  Each iteration
integrates the damped second-order dynamics one semi-implicit Euler step (velocity, then
position) and projects the displaced swarm onto the rigid motions of the source (Kabsch); the
velocities follow the projected motion.  Forces are summed exactly over all pairs of the
(sub)sampled sets in float32 chunks (O(M N) per step).  Masses: uniform, with the prior-matched
points weighted ``prior_mass`` times (the alignment cues of the paper).  Inputs are centred and
scaled to unit RMS radius; the result is returned in input units.
"""
from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from .base import (RegistrationResult, check_param, check_points, check_priors, denormalise,
                   kabsch, normalise_pair, resolve_threshold, rigid_result)
from .refine import polish


def forces(Y: np.ndarray, X: np.ndarray, m: np.ndarray, eps: float, chunk: int = 1024
           ) -> np.ndarray:
    """Softened gravitational acceleration (M, 3) on the points Y from masses m at X."""
    out = np.empty_like(Y)
    X32, m32 = X.astype(np.float32), m.astype(np.float32)
    for a in range(0, len(Y), chunk):
        d = X32[None] - Y[a:a + chunk, None, :].astype(np.float32)      # (c, N, 3)
        r2 = (d * d).sum(-1) + eps * eps
        wgt = m32[None] / (r2 * np.sqrt(r2))
        out[a:a + chunk] = np.einsum('cn,cnk->ck', wgt, d)
    return out


def ga(source: np.ndarray, target: np.ndarray, max_iterations: int = 300,
       tolerance: float = 1e-6, eps: float = 0.15, dt: float = 0.3, damping: float = 0.3,
       max_points: int = 1000, priors: np.ndarray | None = None, prior_mass: float = 50.0,
       seed: int = 0, polish_trim: float = 0.7, inlier_threshold: float = 0.0
       ) -> RegistrationResult:
    """Rigid gravitational registration of ``source`` onto ``target``.

    ``eps`` softening, ``dt`` time step, ``damping`` viscosity (fraction of velocity lost per
    step), all in units of the normalised data; ``priors`` (K, 2) (source, target) index pairs
    get ``prior_mass`` times the mass and attract their partner only; ``max_points`` (0: all)
    random points of each set take part.  The softened potential
    biases the optimum slightly, so the pose is polished by trimmed ICP (``polish_trim`` of the
    closest pairs kept; 0 to skip) from the gravitational solution."""
    t0 = time.perf_counter()
    Y0 = check_points('source', source)
    X0 = check_points('target', target)
    for name, v in (('eps', eps), ('dt', dt), ('prior_mass', prior_mass)):
        if v <= 0:
            raise ValueError(f'{name}={v}: expected > 0')
    check_param('polish_trim', polish_trim)
    check_param('max_iterations', max_iterations)
    check_param('max_points', max_points)
    threshold = resolve_threshold(X0, inlier_threshold)
    if not 0 <= damping < 1:
        raise ValueError(f'damping={damping}: expected 0 <= damping < 1')
    rng = np.random.default_rng(seed)
    Xn, Yn, cx, cy, sc = normalise_pair(X0, Y0)
    xi = rng.choice(len(Xn), max_points, replace=False) if 0 < max_points < len(Xn) else \
        np.arange(len(Xn))
    yi = rng.choice(len(Yn), max_points, replace=False) if 0 < max_points < len(Yn) else \
        np.arange(len(Yn))
    X, Y = Xn[xi], Yn[yi]
    m = np.full(len(X), 1.0 / len(X))
    pairs = None
    priors = check_priors(priors, len(Y0), len(X0))
    if priors is not None:
        pairs = (Yn[priors[:, 0]], Xn[priors[:, 1]])
    T = np.eye(4)                        # normalised source -> normalised target
    vel = np.zeros_like(Y)
    it, converged = 0, False
    for it in range(1, max_iterations + 1):
        cur = Y @ T[:3, :3].T + T[:3, 3]
        acc = forces(cur, X, m, eps)
        # keep the step scale independent of the absolute force magnitude
        acc /= max(float(np.sqrt((acc ** 2).sum(1).mean())), 1e-12)
        vel = (1.0 - damping) * vel + dt * acc
        moved = cur + dt * vel
        src_pts, dst_pts, w = Y, moved, np.ones(len(Y))
        if pairs is not None:
            py = pairs[0] @ T[:3, :3].T + T[:3, 3]
            pull = pairs[1] - py
            src_pts = np.vstack([Y, pairs[0]])
            dst_pts = np.vstack([moved, py + dt * pull])
            w = np.concatenate([w, np.full(len(pull), prior_mass * len(Y) / max(len(X), 1))])
        Tn = kabsch(src_pts, dst_pts, w)
        new = Y @ Tn[:3, :3].T + Tn[:3, 3]
        vel = (new - cur) / dt
        change = float(np.sqrt(((new - cur) ** 2).sum(1).mean()))
        T = Tn
        if change < tolerance:
            converged = True
            break
    # back to input units: y_n = (y - cy) / sc, x = sc * (R y_n + t) + cx
    Tout = denormalise(T, cx, cy, sc)
    tree = cKDTree(X0)
    if polish_trim > 0:
        Tout = polish(Y0, X0, Tout, polish_trim, tree=tree)
    return rigid_result(Y0, Tout, tree, threshold, 'ga', it, converged, t0)
