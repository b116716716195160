"""Rigid ICP, point-to-point and point-to-plane, with a KD-tree (SciPy cKDTree); the iterations
are ``refine.icp_iterate``; ``init='global'`` starts them from ``globalsearch.global_pose``."""
from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from .base import (RegistrationResult, apply, check_param, check_points, diagonal,  # noqa: F401
                   kabsch, resolve_threshold, rigid_result)
from .globalsearch import global_pose
from .refine import (estimate_normals, fine_levels, icp_iterate, icp_levels,  # noqa: F401
                     surface_pass, voxel_downsample)

FINE_VOXEL = 0.01      # init='global', voxel 0: the fine pass's cell edge, of the target diagonal
FINE_FACTORS = (4.0, 2.0, 1.0)   # init='global': the fine passes' grids, x the cell edge
SURFACE_FACTORS = (4.0, 2.0)   # point-to-plane, voxel > 0: the grids before refine.surface_pass
ICP_METHODS = {'icp': 'point_to_point', 'icp-point-to-point': 'point_to_point',
               'icp-point-to-plane': 'point_to_plane'}


def icp(source: np.ndarray, target: np.ndarray, method: str = 'point_to_point',
        max_iterations: int = 50, tolerance: float = 1e-6,
        max_correspondence_distance: float = np.inf, init: str | np.ndarray = 'centroid',
        trim: float = 0.9, max_points: int = 5000, target_tree: cKDTree | None = None,
        voxel: float = 0.0, inlier_threshold: float = 0.0) -> RegistrationResult:
    """Align ``source`` (N, 3) to ``target`` (M, 3).

    ``init``: 'centroid' (translate centroids together), 'identity', 'global' (a search over
    all rotations, robust to outliers and missing parts: ``globalsearch.global_pose``; the
    iterations then use the target points its density filter keeps; ``converged`` is False
    when its best poses are ambiguous; the pose is then finished by ``refine.fine_levels``,
    robust symmetric point-to-plane on grids of 4, 2, 1 x ``voxel`` (1% of the target diagonal
    when voxel is 0) whatever ``method``, ``trim`` serving only the search), or a 4x4
    T_target_source.
    ``trim``: fraction of closest pairs kept each iteration (robust to partial overlap).
    ``max_correspondence_distance``: pairs further apart are not used by the iterations.
    ``target_tree``: a cKDTree of ``target`` to reuse across calls (a fixed reference).
    ``max_points``: the iterations use an evenly strided subset of at most this many source
    points (the transform is then applied to all of them); 0 uses every point.
    ``voxel``: when > 0, both sets are reduced to voxel-grid centroids of this edge (input
    units) for the iterations -- faster, and the centroids average the sensor noise out of the
    pairs and the normals (``target_tree`` then only serves the final correspondences);
    grids of 4, 2, 1 x ``voxel``, except point-to-plane: grids of 4 and 2 x ``voxel``, then
    ``refine.surface_pass`` on local planes of the raw points (no grid bias; robust weights
    in place of ``trim``).
    ``inlier_threshold``: the distance of the reported fitness and inlier RMSE (``base``).
    """
    t0 = time.perf_counter()
    if method not in ('point_to_point', 'point_to_plane'):
        raise ValueError(f"method={method!r}: expected 'point_to_point' or 'point_to_plane'")
    for name, value in (('trim', trim), ('voxel', voxel), ('tolerance', tolerance),
                        ('max_iterations', max_iterations), ('max_points', max_points)):
        check_param(name, value)
    src = check_points('source', source)
    dst = check_points('target', target)
    threshold = resolve_threshold(dst, inlier_threshold)
    full_dst = dst
    ambiguous = False
    if isinstance(init, str):
        T = np.eye(4)
        if init == 'centroid':
            T[:3, 3] = dst.mean(axis=0) - src.mean(axis=0)
        elif init == 'global':
            g = global_pose(src, dst, trim=min(trim, 0.6))
            T, dst, ambiguous = g.T_target_source, dst[g.target_inliers], g.ambiguous
        elif init != 'identity':
            raise ValueError(f"init={init!r}: expected 'centroid', 'identity', 'global' or a "
                             '4x4 array')
    else:
        T = np.asarray(init, dtype=np.float64)
        if T.shape != (4, 4):
            raise ValueError(f'init: expected a 4x4 transform, got shape {T.shape}')
    if isinstance(init, str) and init == 'global':
        # finish the start with the robust symmetric passes, coarse to fine (refine.fine_levels)
        fv = voxel if voxel > 0 else FINE_VOXEL * diagonal(dst)
        T, it, converged = fine_levels(src, dst, T, fv, FINE_FACTORS,
                                       min(max_iterations, 15))
        T, more, _ = surface_pass(src, dst, T, fv)
        it += more
        tree = cKDTree(full_dst) if target_tree is None else target_tree
        return rigid_result(src, T, tree, threshold, f'icp-{method}', it,
                            converged and not ambiguous, t0)
    # the iterations reuse target_tree only when they run on the whole target itself
    surface = method == 'point_to_plane' and voxel > 0
    levels = icp_levels(src, dst, method, voxel, max_points,
                        target_tree if voxel == 0 and dst is full_dst else None,
                        SURFACE_FACTORS if surface else (4.0, 2.0, 1.0))
    T, it, converged, _ = icp_iterate(levels, T, method, max_iterations, tolerance,
                                      max_correspondence_distance, trim, voxel,
                                      finish=not surface)
    if voxel > 0 or dst is not full_dst:
        tree = cKDTree(full_dst) if target_tree is None else target_tree
    else:
        tree = levels[0].tree
    if surface:     # the finest grid's place: local planes of the raw points (refine)
        T, more, converged = surface_pass(src, full_dst, T, min(voxel,
                                          max_correspondence_distance / 3), target_tree=tree)
        it += more
    return rigid_result(src, T, tree, threshold, f'icp-{method}', it,
                        converged and not ambiguous, t0)
