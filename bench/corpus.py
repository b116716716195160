"""Shape corpus for the registration benchmark (issue 15): real scans from
../shared/data/registration, procedural shapes (superquadrics, tori, smooth blobs, thin sheets,
near-symmetric objects) and partial views of some of them cut by a z-buffer from random
viewpoints.  Every shape is a dense point set centred and scaled to bounding-box diagonal 1;
``sample`` draws the points of one registration case from it."""
from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from nrsfm_ros.io.export import read_ply  # noqa: E402

DATA = ROOT.parent / 'shared' / 'data' / 'registration'
DENSE = 60_000


def unit(X: np.ndarray) -> np.ndarray:
    X = X - X.mean(0)
    return X / np.linalg.norm(X.max(0) - X.min(0))


def _area_sample(f: Callable[[np.ndarray, np.ndarray], np.ndarray], u_range, v_range,
                 n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points of the parametric surface f(u, v) spread by area (rejection on the
    Jacobian of a dense random draw)."""
    m = 8 * n
    u = rng.uniform(*u_range, m)
    v = rng.uniform(*v_range, m)
    h = 1e-4
    P = f(u, v)
    J = np.linalg.norm(np.cross(f(u + h, v) - P, f(u, v + h) - P), axis=1)
    J = np.minimum(np.nan_to_num(J), np.quantile(np.nan_to_num(J), 0.9))  # edge spikes
    keep = rng.uniform(0, J.max(), m) < J
    return P[keep][:n]


def _spow(x: np.ndarray, e: float) -> np.ndarray:
    return np.sign(x) * np.abs(x) ** e


def superquadric(a, e1: float, e2: float, rng) -> np.ndarray:
    def f(u, v):                       # u: latitude, v: longitude
        cu, su, cv, sv = np.cos(u), np.sin(u), np.cos(v), np.sin(v)
        return np.stack([a[0] * _spow(cu, e1) * _spow(cv, e2),
                         a[1] * _spow(cu, e1) * _spow(sv, e2), a[2] * _spow(su, e1)], 1)
    return _area_sample(f, (-np.pi / 2, np.pi / 2), (-np.pi, np.pi), DENSE, rng)


def torus(R: float, r: float, squash: float, rng) -> np.ndarray:
    def f(u, v):
        return np.stack([(R + r * np.cos(v)) * np.cos(u), squash * (R + r * np.cos(v))
                         * np.sin(u), r * np.sin(v)], 1)
    return _area_sample(f, (0, 2 * np.pi), (0, 2 * np.pi), DENSE, rng)


def blob(seed: int, rng) -> np.ndarray:
    """A sphere with a smooth random radial bump field (low-order terms)."""
    g = np.random.default_rng(seed)
    C = g.normal(size=(6, 3))
    C /= np.linalg.norm(C, axis=1, keepdims=True)
    amp = g.uniform(0.15, 0.4, 6)

    def f(u, v):
        d = np.stack([np.cos(u) * np.cos(v), np.cos(u) * np.sin(v), np.sin(u)], 1)
        r = 1 + (amp * np.exp(-(1 - d @ C.T) / 0.25)).sum(1)
        return d * r[:, None] * [1.0, 0.8, 0.7]
    return _area_sample(f, (-np.pi / 2, np.pi / 2), (-np.pi, np.pi), DENSE, rng)


def sheet(kind: int, rng) -> np.ndarray:
    def f(u, v):
        if kind == 0:
            z = 0.4 * np.sin(2 * u) * np.cos(1.5 * v) + 0.2 * u * v
        else:
            z = 0.3 * (u ** 2 - 0.6 * v ** 2) + 0.4 * np.exp(-((u - 0.4) ** 2 + (v + 0.3) ** 2)
                                                             / 0.08)
        return np.stack([u, 0.8 * v, z], 1)
    return _area_sample(f, (-1, 1), (-1, 1), DENSE, rng)


def near_symmetric(kind: int, rng) -> np.ndarray:
    """Symmetric solids with one small feature that breaks the symmetry."""
    if kind == 0:        # ellipsoid with a bump
        def f(u, v):
            d = np.stack([np.cos(u) * np.cos(v), np.cos(u) * np.sin(v), np.sin(u)], 1)
            bump = 0.12 * np.exp(-((d - [0.6, 0.6, 0.53]) ** 2).sum(1) / 0.05)
            return d * (1 + bump)[:, None] * [1.0, 0.75, 0.55]
        return _area_sample(f, (-np.pi / 2, np.pi / 2), (-np.pi, np.pi), DENSE, rng)
    # a capped cylinder with a knob on its side

    def f(u, v):
        x, y = 0.5 * np.cos(u), 0.5 * np.sin(u)
        knob = 0.15 * np.exp(-((u - 1.0) ** 2 + (v - 0.5) ** 2) / 0.03)
        return np.stack([x * (1 + knob), y * (1 + knob), v], 1)
    side = _area_sample(f, (-np.pi, np.pi), (-1, 1), DENSE, rng)
    r = 0.5 * np.sqrt(rng.uniform(0, 1, (2, DENSE // 6)))
    a = rng.uniform(0, 2 * np.pi, (2, DENSE // 6))
    caps = [np.stack([r[i] * np.cos(a[i]), r[i] * np.sin(a[i]), np.full(DENSE // 6, z)], 1)
            for i, z in enumerate((-1.0, 1.0))]
    return np.vstack([side, *caps])


def zbuffer_view(X: np.ndarray, seed: int, pixels: int = 160, depth_tol: float = 0.01
                 ) -> np.ndarray:
    """The part of X visible from a random viewpoint: orthographic z-buffer of ``pixels`` per
    side; a point is kept when it lies within ``depth_tol`` of its pixel's nearest depth."""
    R = Rotation.random(random_state=seed).as_matrix()
    V = X @ R.T
    lo, hi = V[:, :2].min(0), V[:, :2].max(0)
    ij = np.floor((V[:, :2] - lo) / (hi - lo).max() * (pixels - 1)).astype(np.int64)
    pix = ij[:, 0] * pixels + ij[:, 1]
    front = np.full(pixels * pixels, -np.inf)
    np.maximum.at(front, pix, V[:, 2])
    return X[V[:, 2] >= front[pix] - depth_tol]


def scan(name: str) -> np.ndarray:
    p = DATA / name
    return read_ply(p) if p.suffix == '.ply' else np.loadtxt(p)


def corpus() -> dict[str, np.ndarray]:
    """name -> dense shape (diagonal 1)."""
    rng = np.random.default_rng(0)
    shapes = {
        'scan bunny': scan('stanford_bunny_34834.ply'),
        'scan horse': scan('probreg_horse.ply'),
        'scan monkey': scan('bcpd_monkey-x.txt'),
        'scan face': scan('probreg_face-x.txt'),
        'superquadric box': superquadric((1.0, 0.7, 0.5), 0.3, 0.3, rng),
        'superquadric cylinder': superquadric((0.6, 0.5, 1.0), 0.3, 1.0, rng),
        'superquadric lens': superquadric((1.0, 0.8, 0.4), 1.0, 0.3, rng),
        'superquadric star': superquadric((1.0, 0.9, 0.8), 1.8, 1.8, rng),
        'torus': torus(1.0, 0.3, 1.0, rng),
        'torus elliptic': torus(1.0, 0.4, 0.7, rng),
        'blob 1': blob(1, rng), 'blob 2': blob(2, rng), 'blob 3': blob(3, rng),
        'sheet wave': sheet(0, rng), 'sheet saddle': sheet(1, rng),
        'near-symmetric ellipsoid': near_symmetric(0, rng),
        'near-symmetric cylinder': near_symmetric(1, rng),
    }
    for name, seed in (('scan bunny', 11), ('scan horse', 12), ('scan monkey', 13),
                       ('blob 1', 14), ('torus elliptic', 15)):
        shapes[f'view of {name.removeprefix("scan ")}'] = zbuffer_view(unit(shapes[name]), seed)
    return {k: unit(v) for k, v in shapes.items()}


def sample(S: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points of S (with replacement when S has fewer)."""
    return S[rng.choice(len(S), n, replace=len(S) < n)]


if __name__ == '__main__':
    for k, v in corpus().items():
        print(f'{k:28s} {len(v):7d}')
