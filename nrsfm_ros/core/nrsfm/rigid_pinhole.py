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
from scipy.spatial.transform import Rotation

from ._pinhole_kernels import (bundle_normal_equations, bundle_point_gradient,
                               bundle_residuals, bundle_schur_rows)
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
    fi, pi = fi.astype(np.int64), pi.astype(np.int64)
    c = np.array(principal, dtype=np.float64)      # the kernels' one type: C order
    R, T, X = np.array(R, dtype=np.float64), np.array(T, dtype=np.float64), \
        np.array(X, dtype=np.float64)

    def residuals(R: np.ndarray, T: np.ndarray, X: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return bundle_residuals(fi, pi, uv, R, T, X, focal, c)

    # the pose-point blocks of the normal equations, laid out as the rows (6F, 3P) of the
    # Schur complement's product
    E = np.zeros((F, 6, P, 3))
    Et = E.reshape(6 * F, 3 * P)
    diag = np.arange(F)
    r, Y, RX = residuals(R, T, X)
    cost, lam, done = _robust_cost(r), 1e-3, 0
    for done in range(1, iterations + 1):
        A, B, gc, gx, C = bundle_normal_equations(fi, pi, r, Y, RX, R, focal,
                                                  LOSS_SCALE_PX ** 2, E)
        while True:
            Ad = A + lam * (np.einsum('fii->fi', A)[:, :, None] * np.eye(6) + 1e-9 * np.eye(6))
            Bd = B + lam * (np.einsum('pii->pi', B)[:, :, None] * np.eye(3) + 1e-9 * np.eye(3))
            Binv = np.linalg.inv(Bd)
            EB = bundle_schur_rows(E, Binv)
            Sred = -(EB @ Et.T)
            Sred.reshape(F, 6, F, 6)[diag, :, diag, :] += Ad
            rhs = gc.ravel() - EB @ gx.ravel()
            try:
                dc = -np.linalg.solve(Sred, rhs).reshape(F, 6)
            except np.linalg.LinAlgError:
                lam *= 10.0
                if lam > 1e8:
                    break
                continue
            dx = -np.einsum('pij,pj->pi', Binv, bundle_point_gradient(fi, pi, C, dc, gx))
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
