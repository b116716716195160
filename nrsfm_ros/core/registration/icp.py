"""Rigid ICP, point-to-point and point-to-plane, with a KD-tree (SciPy cKDTree)."""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class RegistrationResult:
    """T_target_source (4x4) maps source points into the target frame; ``aligned`` (N, 3) is the
    source after the transform; ``displacement`` (N, 3) aligned - source; ``correspondences``
    (N,) target index per source point (-1 where rejected); ``residual`` RMSE of accepted pairs;
    ``fitness`` fraction of source points with an accepted pair."""

    T_target_source: np.ndarray
    aligned: np.ndarray
    displacement: np.ndarray
    correspondences: np.ndarray
    iterations: int
    converged: bool
    residual: float
    fitness: float
    seconds: float
    method: str


def check_points(name: str, X: np.ndarray, min_points: int = 3) -> np.ndarray:
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f'{name}: expected shape (N, 3), got {X.shape}')
    if X.shape[0] < min_points:
        raise ValueError(f'{name}: need at least {min_points} points, got {X.shape[0]}')
    if not np.isfinite(X).all():
        raise ValueError(f'{name}: contains NaN or inf; drop invalid points first')
    return X


def check_priors(priors: np.ndarray | None, n_source: int, n_target: int) -> np.ndarray | None:
    """Prior matches as (K, 2) integer (source index, target index) pairs, or None if empty."""
    if priors is None or len(priors) == 0:
        return None
    priors = np.asarray(priors)
    if priors.ndim != 2 or priors.shape[1] != 2 or not np.issubdtype(priors.dtype, np.integer) \
            or priors.min() < 0 or priors[:, 0].max() >= n_source \
            or priors[:, 1].max() >= n_target:
        raise ValueError(f'priors: expected (K, 2) in-range integer (source, target) index pairs '
                         f'for {n_source} source and {n_target} target points')
    return priors


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


def rigid_result(source: np.ndarray, T: np.ndarray, tree: cKDTree, index: np.ndarray | None,
                 method: str, iterations: int, converged: bool, t0: float
                 ) -> RegistrationResult:
    """The result of a rigid T: correspondences to the target points of ``tree`` (``index``
    maps them to target indices) within 3x the median distance, their RMSE and fraction."""
    aligned = source @ T[:3, :3].T + T[:3, 3]
    dist, corr = tree.query(aligned, workers=-1)
    ok = dist <= max(3 * float(np.median(dist)), 1e-12)
    if index is not None:
        corr = index[corr]
    return RegistrationResult(T_target_source=T, aligned=aligned, displacement=aligned - source,
                              correspondences=np.where(ok, corr, -1), iterations=iterations,
                              converged=converged,
                              residual=float(np.sqrt(np.mean(dist[ok] ** 2))),
                              fitness=float(ok.mean()), seconds=time.perf_counter() - t0,
                              method=method)


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


def estimate_normals(X: np.ndarray, k: int = 10, tree: cKDTree | None = None,
                     at: np.ndarray | None = None) -> np.ndarray:
    """Unit normals by PCA of each point's k nearest neighbours (batched eigh); ``at``: only
    for these point indices."""
    tree = cKDTree(X) if tree is None else tree
    k = min(k, X.shape[0])
    _, idx = tree.query(X if at is None else X[at], k=k, workers=-1)
    nb = X[idx] - X[idx].mean(axis=1, keepdims=True)
    cov = np.einsum('nki,nkj->nij', nb, nb)
    return np.linalg.eigh(cov)[1][:, :, 0]


def voxel_downsample(X: np.ndarray, voxel: float) -> np.ndarray:
    """Centroid of the points in each occupied cell of a grid with edge ``voxel``."""
    ijk = np.floor((X - X.min(0)) / voxel).astype(np.int64)
    dims = ijk.max(0) + 1
    _, inv, cnt = np.unique((ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2],
                            return_inverse=True, return_counts=True)
    return np.stack([np.bincount(inv, X[:, k]) for k in range(3)], 1) / cnt[:, None]


def _apply(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    return X @ T[:3, :3].T + T[:3, 3]


def icp(source: np.ndarray, target: np.ndarray, method: str = 'point_to_point',
        max_iterations: int = 50, tolerance: float = 1e-6,
        max_correspondence_distance: float = np.inf, init: str | np.ndarray = 'centroid',
        trim: float = 0.9, max_points: int = 5000, target_tree: cKDTree | None = None,
        voxel: float = 0.0) -> RegistrationResult:
    """Align ``source`` (N, 3) to ``target`` (M, 3).

    ``init``: 'centroid' (translate centroids together), 'identity', 'global' (a search over
    all rotations, robust to outliers and missing parts: ``globalsearch.global_pose``; the
    iterations then use the target points its density filter keeps), or a 4x4 T_target_source.
    ``trim``: fraction of closest pairs kept each iteration (robust to partial overlap).
    ``target_tree``: a cKDTree of ``target`` to reuse across calls (a fixed reference).
    ``max_points``: the iterations use an evenly strided subset of at most this many source
    points (the transform is then applied to all of them); 0 uses every point.
    ``voxel``: when > 0, both sets are reduced to voxel-grid centroids of this edge (input
    units) for the iterations -- faster, and the centroids average the sensor noise out of the
    pairs and the normals (``target_tree`` then only serves the final correspondences).
    """
    t0 = time.perf_counter()
    if method not in ('point_to_point', 'point_to_plane'):
        raise ValueError(f"method={method!r}: expected 'point_to_point' or 'point_to_plane'")
    if not 0.1 <= trim <= 1.0:
        raise ValueError(f'trim: expected in [0.1, 1], got {trim}')
    src = check_points('source', source)
    dst = check_points('target', target)
    full_src, full_dst = src, dst
    if isinstance(init, str):
        T = np.eye(4)
        if init == 'centroid':
            T[:3, 3] = dst.mean(axis=0) - src.mean(axis=0)
        elif init == 'global':
            from .globalsearch import global_pose       # it builds on this module
            g = global_pose(src, dst, trim=min(trim, 0.6))
            T, dst = g.T_target_source, dst[g.target_inliers]
        elif init != 'identity':
            raise ValueError(f"init={init!r}: expected 'centroid', 'identity', 'global' or a "
                             '4x4 array')
    else:
        T = np.asarray(init, dtype=np.float64)
        if T.shape != (4, 4):
            raise ValueError(f'init: expected a 4x4 transform, got shape {T.shape}')
    if voxel < 0 or not np.isfinite(voxel):
        raise ValueError(f'voxel={voxel}: expected >= 0')
    # the iterations reuse target_tree only when they run on the whole target itself
    levels = icp_levels(src, dst, method, voxel, max_points,
                        target_tree if voxel == 0 and dst is full_dst else None)
    T, it, converged, rmse = icp_iterate(levels, T, method, max_iterations, tolerance,
                                         max_correspondence_distance, trim, voxel)
    if voxel > 0 or dst is not full_dst:
        tree = cKDTree(full_dst) if target_tree is None else target_tree
    else:
        tree = levels[0].tree
    aligned = _apply(T, full_src)
    dist, idx = tree.query(aligned, workers=-1)
    keep = dist <= max_correspondence_distance
    corr = np.where(keep, idx, -1)
    return RegistrationResult(T_target_source=T, aligned=aligned,
                              displacement=aligned - full_src,
                              correspondences=corr, iterations=it, converged=converged,
                              residual=rmse, fitness=float(keep.mean()),
                              seconds=time.perf_counter() - t0, method=f'icp-{method}')


@dataclass
class IcpLevel:
    """One level of the coarse-to-fine iterations: (strided) source points, target points, their
    KD-tree, target normals computed when first paired (NaN until then), the cell-edge factor."""

    src: np.ndarray
    dst: np.ndarray
    tree: cKDTree
    normals: np.ndarray | None
    factor: float


def icp_levels(src: np.ndarray, dst: np.ndarray, method: str, voxel: float, max_points: int,
               target_tree: cKDTree | None = None) -> list[IcpLevel]:
    """voxel > 0: grids of 4, 2, 1 x voxel (a wide basin and few points first); otherwise one
    level on the points themselves.  Reusable across starts (see ``icp_iterate``)."""
    levels = []
    for f in ((4.0, 2.0, 1.0) if voxel > 0 else (0.0,)):
        s, d = (voxel_downsample(src, f * voxel), voxel_downsample(dst, f * voxel)) \
            if f > 0 else (src, dst)
        if max_points and s.shape[0] > max_points:
            s = s[np.linspace(0, s.shape[0] - 1, max_points).astype(np.intp)]
        tree = target_tree if (f == 0 and target_tree is not None) else cKDTree(d)
        normals = np.full(d.shape, np.nan) if method == 'point_to_plane' else None
        levels.append(IcpLevel(s, d, tree, normals, f))
    return levels


def icp_iterate(levels: list[IcpLevel], T: np.ndarray, method: str, max_iterations: int,
                tolerance: float, max_correspondence_distance: float, trim: float, voxel: float
                ) -> tuple[np.ndarray, int, bool, float]:
    """Trimmed ICP from ``T`` through ``levels``: (T, iterations, converged, RMSE)."""
    total = 0
    converged = False
    rmse = np.inf
    for level, lv in enumerate(levels):
        src, dst, tree, normals, f = lv.src, lv.dst, lv.tree, lv.normals, lv.factor
        workers = -1 if src.shape[0] > 4000 else 1      # threads cost more than small queries
        last = level == len(levels) - 1
        prev = np.inf
        converged = False
        it = 0
        for it in range(1, max_iterations + 1):
            moved = _apply(T, src)
            dist, idx = tree.query(moved, workers=workers)
            keep = dist <= max_correspondence_distance
            if trim < 1.0 and keep.sum() > 10:
                cutoff = np.quantile(dist[keep], trim)
                keep &= dist <= cutoff
            if keep.sum() < 3:
                break
            rmse = float(np.sqrt(np.mean(dist[keep] ** 2)))
            if method == 'point_to_point':
                dT = kabsch(moved[keep], dst[idx[keep]])
            else:
                assert normals is not None
                pairs = idx[keep]
                todo = np.unique(pairs[np.isnan(normals[pairs, 0])])
                if todo.size:
                    normals[todo] = estimate_normals(dst, k=20 if f > 0 else 10, tree=tree,
                                                     at=todo)
                dT = _point_to_plane_step(moved[keep], dst[idx[keep]], normals[idx[keep]])
            T = dT @ T
            # converged: the RMSE settles, or (voxel levels) the step is below 1e-4 rad (1e-3
            # on the coarse levels) and a hundredth of the cell edge
            small = f > 0 and np.abs(dT[:3, :3] - np.eye(3)).max() < (1e-4 if last else 1e-3) \
                and np.abs(dT[:3, 3]).max() < 1e-2 * f * voxel
            if abs(prev - rmse) <= tolerance * max(rmse, 1e-12) or small:
                converged = True
                break
            prev = rmse
        total += it
    return T, total, converged, rmse


def _point_to_plane_step(A: np.ndarray, B: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Linearised point-to-plane least squares (small-angle), one Gauss-Newton step."""
    J = np.hstack([np.cross(A, n), n])
    r = np.einsum('ij,ij->i', B - A, n)
    JtJ = J.T @ J                        # normal equations: 6x6, far cheaper than lstsq
    x = np.linalg.solve(JtJ + 1e-12 * np.trace(JtJ) * np.eye(6), J.T @ r)
    wx, wy, wz = x[:3]
    Rm = np.array([[1, -wz, wy], [wz, 1, -wx], [-wy, wx, 1]])
    U, _, Vt = np.linalg.svd(Rm)
    T = np.eye(4)
    T[:3, :3] = U @ Vt
    T[:3, 3] = x[3:]
    return T


ICP_METHODS = {'icp': 'point_to_point', 'icp-point-to-point': 'point_to_point',
               'icp-point-to-plane': 'point_to_plane'}
