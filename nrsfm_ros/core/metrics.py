"""Accuracy metrics shared by tests, benchmarks and the demo summary.

Two e3D conventions exist in the NRSfM literature (see ../shared/data/README.md); every report
says which one it uses:

* **A** (:func:`e3d_normalized`): Akhter / Dai et al. normalised mean 3D error, one global
  orthogonal alignment, mean Euclidean point distance divided by the ground-truth spread.
* **B** (:func:`e3d_frobenius`): mean over frames of ||S_f - S_f^gt||_F / ||S_f^gt||_F after
  centring, aligned globally or per frame (orthogonal, reflection allowed; optional scale).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _check_shapes(S: np.ndarray, S_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    S = np.asarray(S, dtype=np.float64)
    S_gt = np.asarray(S_gt, dtype=np.float64)
    if S.shape != S_gt.shape or S.ndim != 3 or S.shape[2] != 3:
        raise ValueError(f'S: expected shape (F, P, 3) equal to S_gt {S_gt.shape}, got {S.shape}')
    return S, S_gt


def orthogonal_procrustes(A: np.ndarray, B: np.ndarray, reflection: bool = True) -> np.ndarray:
    """R (d x d) minimising ||A R - B||_F for row-vector point sets A, B (N x d)."""
    U, _, Vt = np.linalg.svd(A.T @ B)
    R = U @ Vt
    if not reflection and np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return R


def batched_procrustes(A: np.ndarray, B: np.ndarray, reflection: bool = True,
                       scale: bool = False) -> np.ndarray:
    """Align each A[f] (P x 3) onto B[f]; returns the aligned stack.  Inputs must be centred."""
    U, sig, Vt = np.linalg.svd(np.einsum('fpi,fpj->fij', A, B))
    R = U @ Vt
    if not reflection:
        d = np.sign(np.linalg.det(R))
        U[:, :, -1] *= d[:, None]
        sig[:, -1] *= d
        R = U @ Vt
    out = A @ R
    if scale:
        denom = np.einsum('fpi,fpi->f', A, A)
        s = sig.sum(axis=1) / np.maximum(denom, 1e-300)
        out = out * s[:, None, None]
    return out


def e3d_frobenius(S: np.ndarray, S_gt: np.ndarray, align: str = 'frame',
                  scale: bool = False) -> float:
    """Metric B: mean_f ||S_f - S_f^gt||_F / ||S_f^gt||_F after centring and alignment.

    ``align``: 'frame' (per-frame orthogonal Procrustes), 'global' (one rotation for the whole
    sequence) or 'none'.  ``scale=True`` also fits a per-frame (or global) scale, which is the
    fair choice when the reconstruction's metric scale is unknown.
    """
    S, S_gt = _check_shapes(S, S_gt)
    A = S - S.mean(axis=1, keepdims=True)
    B = S_gt - S_gt.mean(axis=1, keepdims=True)
    if align == 'frame':
        A = batched_procrustes(A, B, scale=scale)
    elif align == 'global':
        R = orthogonal_procrustes(A.reshape(-1, 3), B.reshape(-1, 3))
        A = A @ R
        if scale:
            A *= np.sum(A * B) / max(np.sum(A * A), 1e-300)
    elif align != 'none':
        raise ValueError(f"align={align!r}: expected 'frame', 'global' or 'none'")
    num = np.linalg.norm((A - B).reshape(A.shape[0], -1), axis=1)
    den = np.linalg.norm(B.reshape(B.shape[0], -1), axis=1)
    return float(np.mean(num / np.maximum(den, 1e-300)))


def e3d_normalized(S: np.ndarray, S_gt: np.ndarray) -> float:
    """Metric A (Akhter et al.): one global orthogonal alignment; mean point distance / spread.

    The scale s is the mean over frames and axes of the ground truth's per-axis standard
    deviation; each frame is centred; one 3x3 orthogonal matrix (reflection allowed) is fitted
    over the whole sequence by least squares.
    """
    S, S_gt = _check_shapes(S, S_gt)
    s = float(np.mean(np.std(S_gt, axis=1)))
    A = (S - S.mean(axis=1, keepdims=True)) / s
    B = (S_gt - S_gt.mean(axis=1, keepdims=True)) / s
    R = orthogonal_procrustes(A.reshape(-1, 3), B.reshape(-1, 3))
    A = A @ R
    return float(np.mean(np.linalg.norm(A - B, axis=2)))


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a 3x3 rotation in degrees."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def rotation_range_deg(R: np.ndarray) -> float:
    """The largest rotation (degrees) of a sequence of cameras R (F, 3, 3; a reflected camera,
    det -1, counts as its proper partner) away from the first one's."""
    R = np.array(R, dtype=np.float64)
    R[np.linalg.det(R) < 0, 2] *= -1.0
    rel = np.einsum('fji,jk->fik', R, R[0])
    c = (np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))).max())


def rotation_error_deg(R_est: np.ndarray, R_true: np.ndarray) -> float:
    return rotation_angle_deg(np.asarray(R_est).T @ np.asarray(R_true))


def relative_epe(v: np.ndarray, v_gt: np.ndarray) -> float:
    """Scene flow: mean ||v - v_gt|| / mean ||v_gt|| (scale-normalised end-point error)."""
    v = np.asarray(v, dtype=np.float64)
    v_gt = np.asarray(v_gt, dtype=np.float64)
    if v.shape != v_gt.shape:
        raise ValueError(f'v: shape {v.shape} differs from v_gt {v_gt.shape}')
    return float(np.mean(np.linalg.norm(v - v_gt, axis=-1))
                 / max(np.mean(np.linalg.norm(v_gt, axis=-1)), 1e-300))


def track_error_px(W: np.ndarray, W_gt: np.ndarray, V: np.ndarray | None = None) -> float:
    """Mean 2D end-point error of tracks W (2F x P) against W_gt, over visible entries."""
    W = np.asarray(W, dtype=np.float64)
    W_gt = np.asarray(W_gt, dtype=np.float64)
    if W.shape != W_gt.shape:
        raise ValueError(f'W: shape {W.shape} differs from W_gt {W_gt.shape}')
    d = np.hypot(W[0::2] - W_gt[0::2], W[1::2] - W_gt[1::2])
    if V is not None:
        m = np.asarray(V) > 0.5
        return float(d[m].mean()) if m.any() else float('nan')
    return float(d.mean())


def frame_e3d(X: np.ndarray, X_gt: np.ndarray, scale: bool = True) -> float:
    """Metric B of one frame: ||X - X_gt||_F / ||X_gt||_F after centring and orthogonal
    Procrustes (reflection allowed; ``scale`` also fits a scale).  X, X_gt (P, 3)."""
    X = np.asarray(X, dtype=np.float64)
    X_gt = np.asarray(X_gt, dtype=np.float64)
    if X.shape != X_gt.shape or X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f'X: expected shape (P, 3) equal to X_gt {X_gt.shape}, got {X.shape}')
    return e3d_frobenius(X[None], X_gt[None], 'frame', scale=scale)


@dataclass(frozen=True)
class FrameAlignment:
    """The similarity metric B fits for one frame (``frame_e3d``): ``apply(Y)`` maps points of
    the reconstruction's frame into the ground truth's, ``(Y - mean) @ R * s + mean_gt``
    (R orthogonal, reflection allowed; s = 1 without scale)."""

    R: np.ndarray
    s: float
    mean: np.ndarray
    mean_gt: np.ndarray

    def apply(self, Y: np.ndarray) -> np.ndarray:
        return (np.asarray(Y, dtype=np.float64) - self.mean) @ self.R * self.s + self.mean_gt


def frame_alignment(X: np.ndarray, X_gt: np.ndarray, scale: bool = True) -> FrameAlignment:
    """The alignment of X (P, 3) onto X_gt (P, 3) that ``frame_e3d`` scores after: centring,
    orthogonal Procrustes (reflection allowed) and, with ``scale``, the least-squares scale."""
    X = np.asarray(X, dtype=np.float64)
    X_gt = np.asarray(X_gt, dtype=np.float64)
    if X.shape != X_gt.shape or X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f'X: expected shape (P, 3) equal to X_gt {X_gt.shape}, got {X.shape}')
    mean, mean_gt = X.mean(axis=0), X_gt.mean(axis=0)
    A, B = X - mean, X_gt - mean_gt
    U, sig, Vt = np.linalg.svd(A.T @ B)
    s = float(sig.sum() / max(np.sum(A * A), 1e-300)) if scale else 1.0
    return FrameAlignment(U @ Vt, s, mean, mean_gt)


def point_errors(X: np.ndarray, X_gt: np.ndarray, scale: bool = True) -> np.ndarray:
    """Per-point error (P,) of X against X_gt (P, 3) after ``frame_alignment``: the distance
    divided by the RMS radius of X_gt about its centroid, so that the RMS of the errors is the
    frame's metric B (``frame_e3d(X, X_gt, scale)``)."""
    X_gt = np.asarray(X_gt, dtype=np.float64)
    d = np.linalg.norm(frame_alignment(X, X_gt, scale).apply(X) - X_gt, axis=1)
    rms = np.sqrt(np.mean(np.sum((X_gt - X_gt.mean(axis=0)) ** 2, axis=1)))
    return d / max(float(rms), 1e-300)


def match_ids(ids: np.ndarray, gt_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points matched by track id: ``ok`` (n,) True where ``ids`` is one of ``gt_ids`` (P,),
    and ``cols`` (ok.sum(),) the ground-truth column of each matched point."""
    gt_ids = np.asarray(gt_ids).astype(np.int64)
    ids = np.asarray(ids).astype(np.int64)
    order = np.argsort(gt_ids)
    sorted_ids = gt_ids[order]
    if sorted_ids.size == 0:
        return np.zeros(ids.shape, bool), np.zeros(0, np.int64)
    pos = np.clip(np.searchsorted(sorted_ids, ids), 0, sorted_ids.size - 1)
    ok = sorted_ids[pos] == ids
    return ok, order[pos[ok]]


def flat_shape(X: np.ndarray) -> np.ndarray:
    """The points X (P, 3) projected onto their least-squares plane (the flat baseline)."""
    X = np.asarray(X, dtype=np.float64)
    c = X.mean(axis=0)
    n = np.linalg.svd(X - c, full_matrices=False)[2][2]
    return X - np.outer((X - c) @ n, n)


@dataclass(frozen=True)
class StreamScore:
    """Per-frame metric B of a published stream against ground truth, with the baselines
    scored on exactly the same frames and points.

    ``e3d``, ``static``, ``flat`` (F,): NaN for frames that were not scored; ``unscored``: the
    frames without a cloud or with fewer than ``min_points`` points matched to ground truth
    (they are listed, never scored as 0)."""

    e3d: np.ndarray
    static: np.ndarray
    flat: np.ndarray
    matched: np.ndarray
    unscored: list[int]

    def summary(self) -> dict[str, float | int | list[int]]:
        ok = np.isfinite(self.e3d)

        def mean(a: np.ndarray) -> float:
            return float(np.mean(a[ok])) if ok.any() else float('nan')
        return {'frames': int(self.e3d.size), 'frames_scored': int(ok.sum()),
                'unscored': list(self.unscored), 'e3d': mean(self.e3d),
                'static': mean(self.static), 'flat': mean(self.flat),
                'ratio_static': mean(self.e3d) / max(mean(self.static), 1e-300),
                'points_matched_mean': float(self.matched[ok].mean()) if ok.any() else 0.0}


def score_stream(clouds: dict[int, tuple[np.ndarray, np.ndarray]], gt_ids: np.ndarray,
                 S_gt: np.ndarray, min_points: int = 10, scale: bool = True) -> StreamScore:
    """Score clouds ``{frame: (X (n, 3), ids (n,))}`` against ground truth ``S_gt`` (F, P, 3)
    whose columns carry the track ids ``gt_ids`` (P,).  Points are matched by id; non-finite
    points and ids absent from the ground truth are left out; a frame with fewer than
    ``min_points`` matches is unscored.  Baselines on the same points: the static oracle (the
    ground truth of frame 0 repeated) and the flat plane (frame 0 flattened onto its plane)."""
    S_gt = np.asarray(S_gt, dtype=np.float64)
    F = S_gt.shape[0]
    gt_ids = np.asarray(gt_ids).astype(np.int64)
    if gt_ids.shape != (S_gt.shape[1],):
        raise ValueError(f'gt_ids: expected shape ({S_gt.shape[1]},), got {gt_ids.shape}')
    flat0 = flat_shape(S_gt[0])
    e3d, static, flat = (np.full(F, np.nan) for _ in range(3))
    matched = np.zeros(F, np.int64)
    unscored = []
    for f in range(F):
        if f not in clouds:
            unscored.append(f)
            continue
        X, ids = clouds[f]
        ok, cols = match_ids(ids, gt_ids)
        X = np.asarray(X)[ok]
        finite = np.isfinite(X).all(axis=1)
        X, cols = X[finite], cols[finite]
        matched[f] = cols.size
        if cols.size < min_points:
            unscored.append(f)
            continue
        e3d[f] = frame_e3d(X, S_gt[f, cols], scale)
        static[f] = frame_e3d(S_gt[0, cols], S_gt[f, cols], scale)
        flat[f] = frame_e3d(flat0[cols], S_gt[f, cols], scale)
    return StreamScore(e3d, static, flat, matched, unscored)
