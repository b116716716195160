"""Result type and input checks shared by the NRSfM methods."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class NRSfMResult:
    """Per-frame shapes and orthographic cameras recovered from tracks.

    S: (F, P, 3) shapes in each frame's camera frame (orthographic, image units, centred on the
       frame's visible points; z towards the scene up to the usual depth reflection).
    R: (F, 3, 3) rotations object -> camera (rows 0, 1 are the orthographic camera).
    scale: (F,) weak-perspective scale per frame; t: (F, 2) image translation per frame, so
       W_f ~= scale_f * S_f[:, :2].T + t_f.
    compression: numbers of the full sequence (3FP) over those the method's model stores
       (``hdsm``); 1.0 for methods that store every shape.
    camera_model: 'orbit' where the cameras were replaced by their constant-rate orbit fit
       (``bmm``/``cdf`` with ``camera_model`` 'auto' or 'orbit'), else 'free' (per frame).
    """

    S: np.ndarray
    R: np.ndarray
    scale: np.ndarray
    t: np.ndarray
    method: str
    rank: int
    residual_px: float
    iterations: int
    converged: bool
    seconds: float
    compression: float = 1.0
    camera_model: str = 'free'


def check_tracks(W: np.ndarray, V: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Validate W (2F, P) and V (F, P); returns float64 W and float64 V in [0, 1]."""
    W = np.asarray(W, dtype=np.float64)
    if W.ndim != 2 or W.shape[0] % 2 or W.shape[0] < 4:
        raise ValueError(f'W: expected shape (2F, P) with F >= 2, got {W.shape}')
    F, P = W.shape[0] // 2, W.shape[1]
    if P < 4:
        raise ValueError(f'W: need at least 4 points, got P={P}')
    if V is None:
        V = np.ones((F, P))
    V = np.asarray(V, dtype=np.float64)
    if V.shape != (F, P):
        raise ValueError(f'V: expected shape (F, P) = {(F, P)}, got {V.shape}')
    if np.any(V < 0) or np.any(V > 1) or np.isnan(V).any():
        raise ValueError('V: values must lie in [0, 1]')
    bad = ~np.isfinite(W)
    if bad.any():
        # Non-finite measurements are treated as missing, never silently used.
        V = V.copy()
        V[(bad[0::2] | bad[1::2])] = 0.0
        W = np.where(bad, 0.0, W)
    if (V.sum(axis=0) == 0).any():
        raise ValueError('V: some points are never visible; drop them before reconstruction')
    return W, V
