"""The depth sign of a batch from rigid shapes fitted to the pinhole image (bundle adjustment).

An orthographic (weak-perspective) solve cannot tell a shape from its depth reflection: ``S``
with cameras ``R`` and ``D S`` with ``D R D`` (``D = diag(1, 1, -1)``) image the same.  The
pinhole camera can, but judging each reflection by the weak solution *imaged* through the
pinhole camera (``perspective.frame_errors``) asks a shape fitted to the wrong camera: where the
surface deforms (a breathing cap) the model's residual outweighs the sign's perspective
signature and the wrong reflection can look better (the cap at 60 deg, amplitude 2: published
reflected in every frame).

Here the question is asked after fitting (:func:`batch_sign`): over short runs of frames (a
surface deforms little within one), a rigid shape and a pinhole pose per frame are adjusted to
the pixels from each of the two Necker starts (:func:`fit_rigid_pinhole`: Levenberg-Marquardt
on a soft-L1 cost, the points eliminated by their Schur complement), on a spread subset of the
tracks; the wrong start cannot reach the same fit, its foreshortening runs the other way.  The
per-track errors of the two fits are compared as a paired test over the tracks, and only a
clear verdict (``SIGN_Z`` standard errors) decides: a deforming surface seen over little camera
motion can favour either reflection by a fraction of a pixel.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.spatial.transform import Rotation

from .extend import spread_subset
from .result import NRSfMResult

SIGN_TRACKS = 300           # tracks of the subset the two fits are run on
ITERATIONS = 12             # Levenberg-Marquardt iterations per fit, at most
SIGN_WINDOW = 12            # frames per run of one rigid fit
SIGN_Z = 4.0                # the paired evidence (standard errors) a sign needs
LOSS_SCALE_PX = 2.0         # soft-L1 scale: beyond it a residual counts linearly
_D = np.diag([1.0, 1.0, -1.0])


@dataclass(frozen=True)
class PinholeFit:
    """A rigid shape fitted to the pinhole image: ``S`` (F, P, 3) camera-frame points (units of
    the start's object frame, depth from the camera), ``track_px`` (P,) each track's mean
    reprojection error, ``median_px`` / ``mean_px`` over the observations used (V >= 0.5),
    ``iterations`` taken."""

    S: np.ndarray
    track_px: np.ndarray
    median_px: float
    mean_px: float
    iterations: int


def _proper(R: np.ndarray) -> np.ndarray:
    """(F, 3, 3) rotations with det +1 (an improper camera's third row negated)."""
    R = np.array(R, dtype=np.float64)
    R[np.linalg.det(R) < 0, 2] *= -1.0
    return R


def _gram(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n, i, j) products a_n^T b_n of (n, 2, i) and (n, 2, j) (two image rows)."""
    return a[:, 0, :, None] * b[:, 0, None, :] + a[:, 1, :, None] * b[:, 1, None, :]


def _robust_cost(r: np.ndarray) -> float:
    """The soft-L1 cost of residual vectors r (n, 2) px."""
    s2 = LOSS_SCALE_PX ** 2
    return float(2.0 * s2 * (np.sqrt(1.0 + (r * r).sum(1) / s2) - 1.0).sum())


def fit_rigid_pinhole(W: np.ndarray, V: np.ndarray, R: np.ndarray, X: np.ndarray,
                      T: np.ndarray, focal: float, principal: np.ndarray,
                      iterations: int = ITERATIONS) -> PinholeFit:
    """One rigid shape ``X`` (P, 3) and per-frame poses ``R`` (F, 3, 3, proper), ``T`` (F, 3)
    adjusted so that ``focal * (R X + T)_xy / (R X + T)_z + principal`` meets the tracks ``W``
    (2F, P) where ``V`` (F, P) >= 0.5: Levenberg-Marquardt on the soft-L1 cost (iteratively
    reweighted), the points eliminated by their Schur complement (the reduced system is the
    6F pose parameters), rotations updated on the left by ``exp([w]x)``."""
    F, P = V.shape
    fi, pi = np.nonzero(V >= 0.5)
    if fi.size < 6 * F + 3 * P:
        raise ValueError(f'V: {fi.size} observations cannot fix {F} poses and {P} points')
    uv = np.stack([W[2 * fi, pi], W[2 * fi + 1, pi]], axis=1)
    c = np.asarray(principal, dtype=np.float64)
    R, T, X = np.array(R, dtype=np.float64), np.array(T, dtype=np.float64), \
        np.array(X, dtype=np.float64)

    def residuals(R: np.ndarray, T: np.ndarray, X: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        RX = np.einsum('nij,nj->ni', R[fi], X[pi])
        Y = RX + T[fi]
        z = np.maximum(Y[:, 2], 1e-9)
        return focal * Y[:, :2] / z[:, None] + c - uv, Y, RX

    ones = np.ones(fi.size)
    starts = np.searchsorted(fi, np.arange(F + 1))      # each frame's observations
    by_frame = csr_matrix((ones, (fi, np.arange(fi.size))), shape=(F, fi.size))
    by_point = csr_matrix((ones, (pi, np.arange(fi.size))), shape=(P, fi.size))
    E = np.zeros((P, F, 6, 3))      # the pose-point blocks of the normal equations
    r, Y, RX = residuals(R, T, X)
    cost, lam, done = _robust_cost(r), 1e-3, 0
    for done in range(1, iterations + 1):
        z = np.maximum(Y[:, 2], 1e-9)
        Jy = np.zeros((fi.size, 2, 3))
        Jy[:, 0, 0] = Jy[:, 1, 1] = focal / z
        Jy[:, :, 2] = -focal * Y[:, :2] / (z * z)[:, None]
        # d(Y)/d(w) for R <- exp([w]x) R is -[R X]x: a row a of Jy gives (R X) x a
        Jc = np.concatenate([np.cross(RX[:, None, :], Jy), Jy], axis=2)     # (n, 2, 6)
        Jx = Jy @ R[fi]                                                     # (n, 2, 3)
        w = 1.0 / np.sqrt(1.0 + (r * r).sum(1) / LOSS_SCALE_PX ** 2)        # soft-L1 IRLS
        wJc, wJx = Jc * w[:, None, None], Jx * w[:, None, None]
        A = np.stack([wJc[a:b].reshape(-1, 6).T @ Jc[a:b].reshape(-1, 6)   # fi is sorted
                      for a, b in zip(starts[:-1], starts[1:])])
        B = (by_point @ _gram(wJx, Jx).reshape(-1, 9)).reshape(P, 3, 3)
        gc = by_frame @ (wJc[:, 0] * r[:, :1] + wJc[:, 1] * r[:, 1:])
        gx = by_point @ (wJx[:, 0] * r[:, :1] + wJx[:, 1] * r[:, 1:])
        C = _gram(wJc, Jx)                                                  # (n, 6, 3)
        E[pi, fi] = C
        Et = E.reshape(P, 6 * F, 3)
        while True:
            Ad = A + lam * (np.einsum('fii->fi', A)[:, :, None] * np.eye(6) + 1e-9 * np.eye(6))
            Bd = B + lam * (np.einsum('pii->pi', B)[:, :, None] * np.eye(3) + 1e-9 * np.eye(3))
            Binv = np.linalg.inv(Bd)
            EB = Et @ Binv                                                  # (P, 6F, 3)
            Sred = -(EB.transpose(1, 0, 2).reshape(6 * F, 3 * P)
                     @ Et.transpose(1, 0, 2).reshape(6 * F, 3 * P).T)
            for f in range(F):
                Sred[6 * f:6 * f + 6, 6 * f:6 * f + 6] += Ad[f]
            rhs = gc.ravel() - EB.transpose(1, 0, 2).reshape(6 * F, 3 * P) @ gx.ravel()
            try:
                dc = -np.linalg.solve(Sred, rhs).reshape(F, 6)
            except np.linalg.LinAlgError:
                lam *= 10.0
                if lam > 1e8:
                    break
                continue
            dx = -np.einsum('pij,pj->pi', Binv,
                            gx + by_point @ (C * dc[fi][:, :, None]).sum(1))
            Rn = Rotation.from_rotvec(dc[:, :3]).as_matrix() @ R
            Tn, Xn = T + dc[:, 3:], X + dx
            rn, Yn, RXn = residuals(Rn, Tn, Xn)
            cn = _robust_cost(rn)
            if np.isfinite(cn) and cn < cost:
                R, T, X, r, Y, RX = Rn, Tn, Xn, rn, Yn, RXn
                improved = cost - cn
                cost, lam = cn, max(lam / 3.0, 1e-7)
                break
            lam *= 4.0
            if lam > 1e8:
                improved = 0.0
                break
        if lam > 1e8 or improved < 1e-6 * cost:
            break
    e = np.linalg.norm(r, axis=1)
    n_obs = np.bincount(pi, minlength=P)
    track_px = np.bincount(pi, weights=e, minlength=P) / np.maximum(n_obs, 1)
    return PinholeFit(np.einsum('fij,pj->fpi', R, X) + T[:, None, :], track_px,
                      float(np.median(e)), float(e.mean()), done)


def necker_fits(rig: NRSfMResult, W: np.ndarray, V: np.ndarray, focal: float,
                principal: np.ndarray) -> tuple[PinholeFit, PinholeFit]:
    """The rigid result ``rig`` of (W, V) adjusted to the pinhole image as it is and from its
    Necker reflection (object shape ``D X``, cameras ``D R D``).  ``rig``'s shape in the object
    frame is its frames' shapes rotated back and averaged; each frame's depth from the camera is
    ``focal / scale`` (weak perspective: scale = focal / depth)."""
    R = _proper(rig.R)
    F = R.shape[0]
    X = np.einsum('fji,fpj->pi', R, _frame_depths_proper(rig)) / F
    Tz = focal / np.maximum(rig.scale, 1e-12)
    T = np.column_stack([(rig.t - principal) * (Tz / focal)[:, None], Tz])
    return (fit_rigid_pinhole(W, V, R, X, T, focal, principal),
            fit_rigid_pinhole(W, V, _D @ R @ _D, X @ _D, T, focal, principal))


def _frame_depths_proper(rig: NRSfMResult) -> np.ndarray:
    """``rig.S`` with the depths of frames whose camera is improper negated (S_f = R_f X with
    R_f made proper)."""
    S = np.array(rig.S, dtype=np.float64)
    S[np.linalg.det(rig.R) < 0, :, 2] *= -1.0
    return S


def batch_sign(res: NRSfMResult, W: np.ndarray, V: np.ndarray, focal: float,
               principal: np.ndarray, tracks: int = SIGN_TRACKS,
               window: int = SIGN_WINDOW) -> tuple[float, float]:
    """The depth sign (+1 keep, -1 reflect every frame, 0 undecided) of the batch result
    ``res`` of (W, V) that the pinhole image prefers, and the evidence ``z``.

    On a spread subset of ``tracks`` tracks, the frames are cut into runs of about ``window``
    (a surface deforms little within one, so a rigid shape fits it); each run's rigid
    factorisation is fitted to the pinhole image from both Necker starts, and each fit is
    labelled by whether its depths agree with ``res``'s on the run.  Per track, the error of
    the disagreeing fit minus that of the agreeing one, summed over the runs; ``z`` is their
    mean over its standard error (a paired test over the tracks).  ``res`` keeps its sign where
    ``z >= SIGN_Z``, is reflected where ``z <= -SIGN_Z``, else the fits do not decide."""
    from .planar import safe_rigid
    principal = np.asarray(principal, dtype=np.float64)
    F = V.shape[0]
    idx = spread_subset(V.shape[1], tracks)
    Ws, Vs = W[:, idx], V[:, idx]
    z_res = res.S[:, idx, 2] - res.S[:, idx, 2].mean(1, keepdims=True)
    diff = np.zeros(idx.size)
    runs = 0
    for fr in np.array_split(np.arange(F), max(1, F // window)):
        rows = np.ravel(np.column_stack([2 * fr, 2 * fr + 1]))
        keep = np.flatnonzero((Vs[fr] >= 0.5).sum(0) >= min(3, fr.size))
        if fr.size < 3 or keep.size < 8:
            continue
        Wr, Vr = Ws[rows][:, keep], Vs[fr][:, keep]
        rig = safe_rigid(Wr, Vr)
        if rig is None or not np.isfinite(rig.S).all():
            continue
        try:
            fits = necker_fits(rig, Wr, Vr, focal, principal)
        except (ValueError, np.linalg.LinAlgError, FloatingPointError):
            continue
        agree = [float(((f.S[:, :, 2] - f.S[:, :, 2].mean(1, keepdims=True))
                        * z_res[fr][:, keep]).sum()) for f in fits]
        if not all(np.isfinite(agree)) or agree[0] * agree[1] >= 0:
            continue                # the two fits are not each other's reflections here
        a, b = (0, 1) if agree[0] > 0 else (1, 0)
        diff[keep] += fits[b].track_px - fits[a].track_px
        runs += 1
    if runs == 0 or not np.isfinite(diff).all():
        return 0.0, 0.0
    spread = diff.std() / np.sqrt(diff.size)
    z = float(diff.mean() / spread) if spread > 0 else 0.0
    if z >= SIGN_Z:
        return 1.0, z
    return (-1.0, z) if z <= -SIGN_Z else (0.0, z)
