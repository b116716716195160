"""BH-RGA: rigid gravitational alignment by direct minimisation of the potential energy with a
Barnes-Hut tree (Golyanik, Theobalt, Stricker, ICCV 2019; METHODS §10.2).

The two sets are particle swarms.  The energy of the source at pose (R, t) in the field of the
target is E = -sum_i sum_j m_i m_j / sqrt(|R y_i + t - x_j|^2 + eps^2) (softened Newtonian
potential), plus, for prior matches (i, j), a pair term with mass ``prior_mass`` times an
ordinary source particle that only its partner attracts (with three or more prior matches the
pose starts from their Procrustes fit).  E is minimised over the six pose
parameters by L-BFGS with the analytic gradient (force and torque), while the softening eps is
annealed from a wide basin (``eps_start``) to a sharp one (``eps_end``).

Barnes-Hut: the target is an implicit octree -- levels of a regular grid over its bounding cube,
each occupied cell holding its mass and centre of mass, built in O(N) with one sort per level.
For every source particle the tree is walked from the coarse levels down; a cell whose edge is
below ``theta`` times its distance is taken whole (its centre of mass), otherwise it is opened,
down to the leaf level whose cell edge follows eps (structure below the softening length does not
change the field).  The interaction lists are rebuilt at every softening stage and held fixed
inside it, so each L-BFGS stage minimises one smooth function.  The source, being rigid, is
clustered the same way (a cell of the source moves as one particle with its summed mass), so the
cost per energy evaluation depends on the number of occupied cells, not on the number of points:
one million points cost one grid pass per level plus a fixed number of cell interactions.

After the last stage the pose is polished by trimmed point-to-point ICP on subsamples (the
softened potential biases the optimum by a fraction of eps).  Inputs are centred and scaled to
unit RMS radius; the result is in input units.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from .base import (RegistrationResult, check_param, check_points, check_priors, denormalise,
                   kabsch, normalise_pair, resolve_threshold, rigid_result)
from .refine import polish


@dataclass(frozen=True)
class CellLevel:
    edge: float             # cell edge length
    com: np.ndarray         # (C, 3) centre of mass per occupied cell
    mass: np.ndarray        # (C,)
    child_start: np.ndarray  # (C,) first child (index into the next level's cells)
    child_count: np.ndarray  # (C,) number of occupied children


def morton(ijk: np.ndarray, bits: int) -> np.ndarray:
    """Z-order keys of integer cell coordinates (N, 3): a parent's key is its child's >> 3."""
    key = np.zeros(len(ijk), np.int64)
    for b in range(bits):
        for a in range(3):
            key |= ((ijk[:, a] >> b) & 1) << (3 * b + 2 - a)
    return key


class CellTree:
    """Implicit octree: occupied cells of grids with 2^l cells per axis, l = 0..levels."""

    def __init__(self, X: np.ndarray, m: np.ndarray, levels: int, lo: np.ndarray,
                 size: float) -> None:
        n = 2 ** levels
        ijk = np.clip(((X - lo) / size * n).astype(np.int64), 0, n - 1)
        keys, inv = np.unique(morton(ijk, levels), return_inverse=True)
        mass = np.bincount(inv, m)
        com = np.stack([np.bincount(inv, m * X[:, k]) for k in range(3)], 1) / mass[:, None]
        # finest first; Morton order keeps each parent's children contiguous
        coms, masses, parents = [com], [mass], []
        for _ in range(levels):
            keys, pinv = np.unique(keys >> 3, return_inverse=True)
            pmass = np.bincount(pinv, mass)
            com = np.stack([np.bincount(pinv, mass * com[:, d]) for d in range(3)], 1) \
                / pmass[:, None]
            mass = pmass
            coms.append(com)
            masses.append(mass)
            parents.append(pinv)
        coms.reverse()
        masses.reverse()
        parents.reverse()                    # parents[l]: parent (level l) of level l+1 cells
        self.levels: list[CellLevel] = []
        for lev in range(levels + 1):
            if lev < levels:
                count = np.bincount(parents[lev], minlength=len(masses[lev]))
                start = np.concatenate([[0], np.cumsum(count)[:-1]])
            else:
                count = start = np.zeros(len(masses[lev]), np.int64)
            self.levels.append(CellLevel(size / 2 ** lev, coms[lev], masses[lev], start, count))

    def level_for(self, edge: float) -> int:
        """The coarsest level whose cell edge is at most ``edge`` (or the leaf level)."""
        for lev, L in enumerate(self.levels):
            if L.edge <= edge:
                return lev
        return len(self.levels) - 1


def interaction_lists(tree: CellTree, Q: np.ndarray, theta: float, leaf: int, top: int = 2
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Barnes-Hut walk for the particles Q: (particle index, cell centre, cell mass) per
    interaction, cells taken whole when edge < theta * distance, opened down to level ``leaf``."""
    top = min(top, leaf)
    L = tree.levels[top]
    pi = np.repeat(np.arange(len(Q)), len(L.mass))
    ci = np.tile(np.arange(len(L.mass)), len(Q))
    out_p, out_c, out_m = [], [], []
    for lev in range(top, leaf + 1):
        L = tree.levels[lev]
        d = np.sqrt(((Q[pi] - L.com[ci]) ** 2).sum(1))
        take = (L.edge < theta * d) if lev < leaf else np.ones(len(pi), bool)
        out_p.append(pi[take])
        out_c.append(L.com[ci[take]])
        out_m.append(L.mass[ci[take]])
        if lev == leaf:
            break
        pi, ci = pi[~take], ci[~take]
        cnt = L.child_count[ci]
        first = L.child_start[ci]
        pi = np.repeat(pi, cnt)
        # child indices: first + 0..cnt-1 for each opened pair
        offs = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        ci = np.repeat(first, cnt) + offs
    return np.concatenate(out_p), np.concatenate(out_c), np.concatenate(out_m)


def _right_jacobian(w: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(w))
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-8:
        return np.eye(3) - 0.5 * K
    return (np.eye(3) - (1 - np.cos(th)) / th ** 2 * K
            + (th - np.sin(th)) / th ** 3 * K @ K)


def _stage(Q: np.ndarray, qm: np.ndarray, pi: np.ndarray, xc: np.ndarray, xm: np.ndarray,
           eps: float, prior_q: np.ndarray | None, prior_x: np.ndarray | None, prior_w: float,
           iterations: int) -> np.ndarray:
    """Minimise the fixed-list energy over (w, t); Q are the particles at the current pose.
    Returns the 4x4 increment."""
    wpair = qm[pi] * xm
    e2 = eps * eps

    def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
        R = Rotation.from_rotvec(x[:3]).as_matrix()
        P = Q @ R.T + x[3:]
        d = P[pi] - xc
        r2 = np.einsum('ij,ij->i', d, d) + e2
        inv = 1.0 / np.sqrt(r2)
        E = -float(wpair @ inv)
        c = wpair * inv / r2
        g = np.stack([np.bincount(pi, c * d[:, k], minlength=len(Q)) for k in range(3)], 1)
        if prior_q is not None:
            pd = prior_q @ R.T + x[3:] - prior_x
            pr2 = (pd * pd).sum(1) + e2
            pinv = 1.0 / np.sqrt(pr2)
            E -= prior_w * float(pinv.sum())
            gp = (prior_w * pinv / pr2)[:, None] * pd
            gt = g.sum(0) + gp.sum(0)
            tor = np.cross(Q, g @ R).sum(0) + np.cross(prior_q, gp @ R).sum(0)
        else:
            gt = g.sum(0)
            tor = np.cross(Q, g @ R).sum(0)
        gw = _right_jacobian(x[:3]).T @ tor
        return E, np.concatenate([gw, gt])

    res = minimize(fun, np.zeros(6), jac=True, method='L-BFGS-B',
                   options={'maxiter': iterations, 'gtol': 1e-12, 'ftol': 1e-12})
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(res.x[:3]).as_matrix()
    T[:3, 3] = res.x[3:]
    return T


def bhrga(source: np.ndarray, target: np.ndarray, eps_start: float = 0.5,
          eps_end: float = 0.04, stages: int = 6, theta: float = 0.7,
          max_particles: int = 1500, iterations: int = 40, priors: np.ndarray | None = None,
          prior_mass: float = 50.0, polish_trim: float = 0.7, polish_points: int = 5000,
          seed: int = 0, inlier_threshold: float = 0.0) -> RegistrationResult:
    """Rigid Barnes-Hut gravitational registration of ``source`` onto ``target``.

    ``eps_start`` -> ``eps_end``: softening annealed geometrically over ``stages`` (units of the
    normalised data, RMS radius 1); ``theta``: Barnes-Hut opening criterion (cell edge /
    distance); ``max_particles``: cap on the source cells (the particles); ``iterations``: L-BFGS
    iterations per stage; ``priors`` (K, 2) (source index, target index) matches, each pair
    weighing ``prior_mass`` ordinary source particles; ``polish_trim``: trimmed ICP polish (0 to
    skip) on ``polish_points`` source points against 20x as many target points."""
    t0 = time.perf_counter()
    Y0 = check_points('source', source)
    X0 = check_points('target', target)
    for name, v in (('eps_start', eps_start), ('eps_end', eps_end), ('theta', theta),
                    ('prior_mass', prior_mass)):
        if not v > 0:
            raise ValueError(f'{name}={v}: expected > 0')
    if eps_end > eps_start:
        raise ValueError(f'eps_end={eps_end} > eps_start={eps_start}: expected annealing down')
    if stages < 1 or iterations < 1 or max_particles < 8:
        raise ValueError(f'stages={stages}, iterations={iterations}, max_particles='
                         f'{max_particles}: expected >= 1, >= 1, >= 8')
    check_param('polish_trim', polish_trim)
    threshold = resolve_threshold(X0, inlier_threshold)
    Xn, Yn, cx, cy, sc = normalise_pair(X0, Y0)
    prior_y = prior_x = None
    priors = check_priors(priors, len(Y0), len(X0))
    if priors is not None:
        prior_y, prior_x = Yn[priors[:, 0]], Xn[priors[:, 1]]

    def build(P: np.ndarray) -> CellTree:
        lo = P.min(0)
        size = float((P.max(0) - lo).max()) * (1 + 1e-9) + 1e-12
        levels = int(np.clip(np.ceil(np.log2(size / (0.5 * eps_end))), 1, 10))
        return CellTree(P, np.full(len(P), 1.0 / len(P)), levels, lo, size)

    xt, yt = build(Xn), build(Yn)
    T = np.eye(4)                                    # normalised source -> normalised target
    if prior_y is not None and len(prior_y) >= 3:    # the cues also give the starting pose
        T = kabsch(prior_y, prior_x)
    # source particles: the finest source level with at most max_particles cells
    Ls = yt.levels[max([lev for lev, L in enumerate(yt.levels) if len(L.mass) <= max_particles],
                       default=0)]
    for eps in np.geomspace(eps_start, eps_end, stages):
        Q = Ls.com @ T[:3, :3].T + T[:3, 3]
        leaf = xt.level_for(0.5 * eps)
        pi, xc, xm = interaction_lists(xt, Q, theta, leaf)
        pq = None if prior_y is None else prior_y @ T[:3, :3].T + T[:3, 3]
        dT = _stage(Q, Ls.mass, pi, xc, xm, float(eps), pq, prior_x,
                    prior_mass / len(Yn), iterations)
        T = dT @ T
    Tout = denormalise(T, cx, cy, sc)
    rng = np.random.default_rng(seed)
    nx = 20 * polish_points          # a dense target subsample: ICP's pairs need close neighbours
    xi = rng.choice(len(X0), nx, replace=False) if len(X0) > nx else np.arange(len(X0))
    tree = cKDTree(X0[xi])
    if polish_trim > 0:
        yi = rng.choice(len(Y0), polish_points, replace=False) if len(Y0) > polish_points \
            else np.arange(len(Y0))
        Tout = polish(Y0[yi], X0[xi], Tout, polish_trim, tree=tree, max_points=0)
    full = tree if len(xi) == len(X0) else cKDTree(X0)
    return rigid_result(Y0, Tout, full, threshold, 'bhrga', stages, True, t0)
