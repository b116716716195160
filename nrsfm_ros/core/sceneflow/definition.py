"""The one definition of scene flow used by the estimators, the synthetic ground truth
(:mod:`nrsfm_ros.io.synth_flow`) and the evaluation (:func:`epe`).

Scene flow is defined **per surface point** P between an earlier frame a and a later frame b
(consecutive frames b = a + 1, or the reference frame a and any later b):

* ``frame='camera'``: ``X_b - X_a``, where ``X_f`` is P in camera f's optical frame
  (x right, y down, z forward; metres).  This is the motion relative to the (possibly moving)
  camera, what an RGB-D sensor observes; the camera's ego-motion is included.
* ``frame='object'``: ``T_a_b X_b - X_a`` with ``T_a_b = T_a_world inv(T_b_world)`` the camera
  motion from b to a: both positions in camera a's optical frame, the ego-motion removed.  It
  equals ``R_a (X_world_b - X_world_a)``: the displacement of the point in the world (object)
  frame, expressed in the axes of the earlier camera.  It needs the camera pose (known, as in
  the synthetic sequences, or estimated); the rigid part of the deformation is *kept*.

Both are displacements in metres (divide by the time step for a velocity).  An end-point error
is the same in both frames (they differ by a rotation of the later position); the relative
EPE (mean error / mean true displacement) is reported in the object frame.
"""
from __future__ import annotations

import numpy as np

FRAMES = ('camera', 'object')


def camera_to_object(flow: np.ndarray, X_a: np.ndarray, T_a_b: np.ndarray) -> np.ndarray:
    """Camera-frame flow (..., 3) of points X_a (..., 3) -> object-frame flow, given the camera
    motion ``T_a_b`` (4, 4) that maps camera b coordinates to camera a coordinates."""
    T = np.asarray(T_a_b, np.float64)
    if T.shape != (4, 4):
        raise ValueError(f'T_a_b: expected a 4x4 transform, got shape {T.shape}')
    X_b = np.asarray(X_a, np.float64) + np.asarray(flow, np.float64)
    return X_b @ T[:3, :3].T + T[:3, 3] - X_a


def relative_motion(T_camera_world: np.ndarray, a: int, b: int) -> np.ndarray:
    """``T_a_b`` (camera b -> camera a) from per-frame poses T_camera_world (F, 4, 4)."""
    P = np.asarray(T_camera_world, np.float64)
    return P[a] @ np.linalg.inv(P[b])


def epe(flow: np.ndarray, flow_gt: np.ndarray, valid: np.ndarray | None = None
        ) -> tuple[float, float]:
    """(mean end-point error in metres, relative EPE = mean error / mean |flow_gt|) over the
    entries where ``valid`` (default: where flow_gt is finite).  A NaN estimate counts as zero
    displacement (an estimator that says nothing is scored as one that says 'no motion')."""
    f = np.asarray(flow, np.float64)
    g = np.asarray(flow_gt, np.float64)
    if f.shape != g.shape or f.shape[-1] != 3:
        raise ValueError(f'flow: shape {f.shape} differs from flow_gt {g.shape} (or not ...x3)')
    ok = np.isfinite(g).all(-1)
    if valid is not None:
        ok &= np.asarray(valid, bool)
    if not ok.any():
        raise ValueError('valid: no entry with a finite ground truth to score')
    e = np.linalg.norm(np.nan_to_num(f[ok]) - g[ok], axis=-1)
    return float(e.mean()), float(e.mean() / max(np.linalg.norm(g[ok], axis=-1).mean(), 1e-300))
