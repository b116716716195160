"""An occluder over ground-truth tracks, as a flow tracker sees it (SPVA tests and benchmark).

A disc covering ``area`` of the tracks' bounding box in frame 0 crosses the view diagonally
during ``frames`` (first, end).  Tracks it covers stick to it (their positions move with the
disc from where it caught them, as a flow tracker's tracks follow the occluder's texture) and
get visibility ``soft`` (the tracker's occlusion tensor is soft; 0: hard occlusion)."""
from __future__ import annotations

import numpy as np


def occlude_tracks(W: np.ndarray, frames: tuple[int, int], area: float = 0.3,
                   soft: float = 0.25) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tracks W (2F, P) -> the occluded tracks W (2F, P), visibility V (F, P) and the
    occluded mask (F, P) bool."""
    W = np.asarray(W, dtype=np.float64)
    if W.ndim != 2 or W.shape[0] % 2:
        raise ValueError(f'W: expected shape (2F, P), got {W.shape}')
    F, P = W.shape[0] // 2, W.shape[1]
    first, end = (int(f) for f in frames)
    if not 0 <= first < end <= F:
        raise ValueError(f'frames: expected 0 <= first < end <= {F}, got {frames}')
    if not 0 < area < 1 or not 0 <= soft <= 1:
        raise ValueError(f'area={area}, soft={soft}: expected 0 < area < 1, 0 <= soft <= 1')
    Wf = W.reshape(F, 2, P)
    out = Wf.copy()
    lo, hi = Wf[0].min(1), Wf[0].max(1)
    r = np.sqrt(area * (hi - lo).prod() / np.pi)
    occ = np.zeros((F, P), bool)
    anchor = np.zeros((2, P))
    was = np.zeros(P, bool)
    for f in range(first, end):
        s = (f - first + 0.5) / (end - first)
        c = np.array([lo[0] + s * (hi[0] - lo[0]), lo[1] + (0.3 + 0.4 * s) * (hi[1] - lo[1])])
        occ[f] = ((Wf[f].T - c) ** 2).sum(1) <= r * r
        new = occ[f] & ~was
        anchor[:, new] = Wf[f][:, new] - c[:, None]
        out[f][:, occ[f]] = anchor[:, occ[f]] + c[:, None]
        was = occ[f]
    return out.reshape(2 * F, P), np.where(occ, soft, 1.0), occ
