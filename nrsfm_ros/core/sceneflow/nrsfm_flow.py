"""NRSfM-Flow style scene flow (METHODS §11.1): 3D motion per point between consecutive
reconstructions, expressed in one frame (the current camera frame).

``frame='object'`` removes the rigid part (camera ego-motion) by a Kabsch fit between the two
clouds on their shared track ids, leaving the non-rigid motion; ``frame='camera'`` keeps the raw
difference in the current camera frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SceneFlow:
    """points (N, 3) current positions; velocity (N, 3) in units/s; ids (N,) track ids."""

    points: np.ndarray
    velocity: np.ndarray
    ids: np.ndarray
    T_cur_prev: np.ndarray


def scene_flow(prev_points: np.ndarray, prev_ids: np.ndarray, points: np.ndarray,
               ids: np.ndarray, dt: float, frame: str = 'object') -> SceneFlow:
    """Velocity of every current point that also exists in the previous cloud (matched by id)."""
    if frame not in ('object', 'camera'):
        raise ValueError(f"frame={frame!r}: expected 'object' or 'camera'")
    if not dt > 0:
        raise ValueError(f'dt: expected a positive time step, got {dt}')
    prev_points = np.asarray(prev_points, np.float64)
    points = np.asarray(points, np.float64)
    if prev_points.shape != (len(prev_ids), 3) or points.shape != (len(ids), 3):
        raise ValueError('points/ids: expected (N, 3) points and N ids')
    for name, v in (('prev_ids', prev_ids), ('ids', ids)):
        if np.unique(v).size != len(v):
            raise ValueError(f'{name}: {len(v) - np.unique(v).size} duplicated track id(s); '
                             'ids must be unique')
    common, ip, ic = np.intersect1d(prev_ids, ids, assume_unique=True, return_indices=True)
    a, b = prev_points[ip], points[ic]
    T = np.eye(4)
    if frame == 'object' and common.size >= 3:
        from ..registration.icp import kabsch   # lazily: MSF needs no registration code
        T = kabsch(a, b)
        a = a @ T[:3, :3].T + T[:3, 3]
    return SceneFlow(points=b, velocity=(b - a) / dt, ids=common.astype(np.uint32), T_cur_prev=T)
