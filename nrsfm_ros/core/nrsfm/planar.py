"""PLANAR: NRSfM of a planar rest shape deforming out of its plane (cloth, paper, a flag).

Such a surface is S_f(p) = (x_p, y_p, h_f(p)) in an object frame whose z axis is the rest
plane's normal: fixed in-plane positions and a per-frame height field.  Its tracks are
W_f = A_f s_p + v_f h_f(p), with A_f = R_f[:2, :2] (the plane's axes in the image) and
v_f = R_f[:2, 2] (the normal's image).  The general metric upgrade (``bmm``) is ill-conditioned
here: the rigid part has rank 2, not 3, and its cameras err by ~30 degrees on the generated
flag.  Instead:

1. Cameras: the rank-2 factorisation W ~= M s (the plane's rows, the dominant part of W) is
   corrected by one 2 x 2 lower-triangular L (the in-plane affine ambiguity) so that every
   A_f = M_f L extends to a 2 x 3 block with orthonormal rows, [A_f | c_f]; eliminating c_f
   leaves per frame (a1 . a2)^2 = (1 - |a1|^2)(1 - |a2|^2) with |a_i| <= 1, solved for L by
   Levenberg-Marquardt (three starts).  c_f follows up to its sign: the sign between its two
   entries from a1 . a2 + c1 c2 = 0, the sign of the pair (the plane seen from the front or the
   back: the per-frame depth reversal of orthographic views of a plane) from temporal
   continuity with the previous frame.
2. Shapes: the rest positions s_p by visibility-weighted least squares over all frames
   (a 2 x 2 system per point), then the height of every point in every frame from the part of
   its track the plane does not explain, projected on the normal's image:
   h_f(p) = v_f . (w_fp - A_f s_p) / |v_f|^2.
Hidden tracks are first filled by ``cdf``'s coherent motion fields.  Everything is closed form
after the 3-parameter fit: linear in P.

Not for surfaces that are not planar at rest (a face: use ``bmm``/``cdf``); the result reports
``residual_px``, and ``converged`` says whether the planar model holds: the rest shape came out
flat (the RMS of the time-mean height field over the RMS in-plane extent, ``rest_height_ratio``,
at most ``PLANAR_REST_RATIO``) and the model explains the tracks not much worse than the rigid
factorisation does (reprojection residual at most ``PLANAR_RIGID_RATIO`` times rigid's: a
curved surface seen over a small camera motion can look flat to the first test, but the flat
rest and the height field along one normal then cannot follow its image).  (The cameras'
orthonormality misfit is no test: it passes any shape when the camera moves little, and fails a
flag seen by a wide camera motion through perspective and tracking noise.)  Frames must be in
temporal order.
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from .bmm import _finish
from .cdf import coherent_fill
from .factorization import _centre, rigid
from .result import NRSfMResult, check_tracks

PLANAR_REST_RATIO = 0.08  # rest_height_ratio above which the rest shape is not flat.  Measured
#   at 12 / 30 / 60 deg of camera motion, on ground-truth tracks of the 256x192 renders and on
#   the tracker's tracks (192x144): flag 0.010-0.021 / 0.010-0.063, sheet 0.008-0.049 /
#   0.007-0.060, face 0.135-0.168 / 0.161 at 30-60 deg, sphere cap 0.091-0.206 / 0.121-0.127 at
#   30-60 deg; at 12 deg the face (0.011-0.021) and the cap (0.046-0.058) look flat: their depth
#   is barely observable there.  Orthographic dense face: 0.165 over 60 frames.
PLANAR_REST_RATIO_PERSPECTIVE = 0.14  # the same bound where the camera's intrinsics are known
#   (stream.auto_solve), which then also applies PLANAR_PERSPECTIVE_RATIO: a weak-perspective
#   fit reads a close camera's perspective as rest relief (45 deg field of view, 1.6 m in
#   `synth`, 60 deg of camera motion, the tracker's tracks: sheet 0.082, flag at amplitude 2
#   0.085, taken rigid / bmm at e3D 0.23-0.32 against planar's 0.05-0.10 on the ground
#   truth), while the perspective test rejects the face and the cap at most camera motions
#   (planar over rigid 1.05-2.07 below).  0.16 until session 41: the face at 60 deg amplitude 2
#   before a textured wall through `roi_mask` read 0.149-0.157 and passed the perspective test
#   too (planar 0.115 against rigid's 0.075); 0.12 changed no case of the 48-case sweep nor of
#   the 24 unoccluded 1.6 m cases, but a 12-frame 96x72 flag at 1.6 m, 60 deg, amplitude 2
#   reads 0.129 on ground-truth tracks (test_core_perspective): 0.14 between them
#   (BENCHMARKS issue 12, session 41).
PLANAR_RIGID_RATIO = 1.5  # planar's reprojection residual over rigid's above which the planar
#   model does not hold.  Measured on ground-truth tracks of the 256x192 renders (12 / 30 / 60
#   deg): flag 0.18-0.87, sheet 0.54-1.13 (1.34 on a 128x96, 30-frame render), face 0.98-1.91
#   (12 deg amplitude 1: 1.35, planar's e3D 0.122 against rigid's 0.026), sphere cap 1.3-2.0;
#   on the tracker's tracks of the cap at 30 deg amplitude 2 1.82 (rest ratio under 0.08:
#   planar's e3D 0.240 there against bmm's 0.125).  1.0 (no worse than one rigid shape, which
#   the per-frame height field can always match on a truly planar surface) would reject the
#   face at 12 deg but also the sheets above 1.0 (30 deg, 40 frames: planar 0.065 against
#   bmm's 0.10).


PLANAR_PERSPECTIVE_RATIO = 1.0  # with the camera's intrinsics (stream.auto_solve): planar's
#   perspective-image error (perspective.reflected_error, each frame in its better reflection)
#   over the rigid shape's above which the planar model does not hold.  Measured on the
#   256x192 renders, ground-truth / tracker tracks: flag 0.35-0.97 / 0.55-0.96 at 12 deg (0.95-
#   0.97 without the occluder), 0.21-0.59 at 30-60 deg; sheet 0.12-0.67 / 0.21-0.77; face at 12
#   deg 1.05-1.66 / 0.95-1.41 (planar 0.12-0.17 there against rigid's 0.026-0.068: the face's
#   relief read as per-frame heights through the little camera motion), 1.46-1.83 at 30 deg;
#   cap 1.18-2.07 / 1.21-1.93.  The weak residual ratio (PLANAR_RIGID_RATIO) cannot separate
#   these: face at 12 deg 0.98-1.73, sheets 0.88-1.16.


def rest_height_ratio(S: np.ndarray) -> float:
    """RMS of the time-mean height (object-frame z) over the RMS in-plane extent, for
    object-frame shapes S (F, 3, P) of the planar model: ~0 for a flat rest shape."""
    inplane = S[:, :2] - S[:, :2].mean(axis=2, keepdims=True)
    h = S[:, 2] - S[:, 2].mean(axis=1, keepdims=True)
    return float(np.sqrt(np.mean(h.mean(axis=0) ** 2) / max(np.mean((inplane ** 2).sum(1)),
                                                               1e-300)))


def planar_cameras(Wc: np.ndarray) -> tuple[np.ndarray, float]:
    """Orthographic cameras (F, 2, 3) of a planar rest shape from centred tracks Wc (2F, P),
    in the object frame whose z axis is the plane's normal; returns them and the RMS of the
    orthonormality residuals (0 on an exactly planar rigid sequence)."""
    from scipy.optimize import least_squares
    F = Wc.shape[0] // 2
    lam, E = np.linalg.eigh(Wc @ Wc.T)
    M = E[:, -2:][:, ::-1] * np.sqrt(np.maximum(lam[-2:][::-1], 0.0))
    M = M / np.sqrt(2 * np.mean(M ** 2))
    a = M.reshape(F, 2, 2)

    def blocks(x: np.ndarray) -> np.ndarray:
        return a @ np.array([[x[0], 0.0], [x[1], x[2]]])

    def resid(x: np.ndarray) -> np.ndarray:
        A = blocks(x)
        n1, n2 = (A[:, 0] ** 2).sum(1), (A[:, 1] ** 2).sum(1)
        m = (A[:, 0] * A[:, 1]).sum(1)
        return np.concatenate([m ** 2 - (1 - n1) * (1 - n2), np.minimum(1 - n1, 0),
                               np.minimum(1 - n2, 0)])

    best = None
    for x0 in ([0.9, 0.0, 0.9], [0.7, 0.1, 0.7], [1.0, -0.2, 0.8]):
        sol = least_squares(resid, np.array(x0), method='lm', xtol=1e-12, ftol=1e-12)
        if best is None or sol.cost < best.cost:
            best = sol
    A = blocks(best.x)
    n1, n2 = (A[:, 0] ** 2).sum(1), (A[:, 1] ** 2).sum(1)
    m = (A[:, 0] * A[:, 1]).sum(1)
    c1 = np.sqrt(np.maximum(1 - n1, 0.0))
    c2 = np.sqrt(np.maximum(1 - n2, 0.0)) * np.where(m > 0, -1.0, 1.0)
    R2 = np.concatenate([A, np.stack([c1, c2], 1)[:, :, None]], axis=2)
    U, _, Vt = np.linalg.svd(R2, full_matrices=False)
    R2 = U @ Vt
    for f in range(1, F):                    # front/back of the plane: temporal continuity
        alt = R2[f] * np.array([1.0, 1.0, -1.0])
        if np.sum((alt - R2[f - 1]) ** 2) < np.sum((R2[f] - R2[f - 1]) ** 2):
            R2[f] = alt
    return R2, float(np.sqrt(2 * best.cost / best.fun.size))


def height_field(Wc: np.ndarray, V: np.ndarray, R2: np.ndarray) -> np.ndarray:
    """Object-frame shapes (F, 3, P): rest positions (visibility-weighted least squares over the
    frames) and per-frame heights along the plane's normal."""
    F, P = V.shape
    Wf = Wc.reshape(F, 2, P)
    A = R2[:, :, :2]
    # the sums over frames as BLAS products (three-operand einsums run unblocked)
    G = np.einsum('fki,fkj->fij', A, A)
    lhs = (V.T @ G.reshape(F, 4)).reshape(P, 2, 2) + 1e-12 * np.eye(2)
    rhs = (V[:, None, :] * Wf).reshape(2 * F, P).T @ A.reshape(2 * F, 2)     # (P, 2)
    s0 = np.linalg.solve(lhs, rhs[:, :, None])[:, :, 0].T           # (2, P)
    v = R2[:, :, 2]
    h = (v[:, :, None] * (Wf - A @ s0)).sum(1) / np.maximum((v ** 2).sum(1), 1e-12)[:, None]
    return np.concatenate([np.broadcast_to(s0, (F, 2, P)), h[:, None]], axis=1)


def planar(W: np.ndarray, V: np.ndarray | None = None, beta: float = 0.5, lam: float = 0.01,
           landmarks: int = 300, seed: int = 0,
           rigid_check: bool | NRSfMResult | None = True,
           rest_ratio: float = PLANAR_REST_RATIO) -> NRSfMResult:
    """Planar rest shape + per-frame height field (see the module docstring).  ``beta``,
    ``lam``, ``landmarks``, ``seed``: the coherent fill of hidden tracks (as in ``cdf``).
    ``rigid_check``: compare the residual with the rigid factorisation's for ``converged``
    (True: solve it, ~10x the cost of the planar one; or the rigid result of the same tracks,
    already solved (None: it failed); False: off, where the model is already chosen).
    ``rest_ratio``: the ``rest_height_ratio`` above which the rest shape is not flat
    (``converged`` False)."""
    t0 = time.perf_counter()
    W, V = check_tracks(W, V)
    for name, v in (('beta', beta), ('lam', lam)):
        if not v > 0:
            raise ValueError(f'{name}: expected > 0, got {v}')
    if landmarks < 1:
        raise ValueError(f'landmarks: expected >= 1, got {landmarks}')
    if not rest_ratio >= 0:
        raise ValueError(f'rest_ratio: expected >= 0, got {rest_ratio}')
    F, P = V.shape
    if F < 3:
        raise ValueError(f'W: planar needs at least 3 frames, got F={F}')
    X = coherent_fill(W, V, beta, lam, landmarks, seed) if (V < 0.5).any() else W
    Xc, t = _centre(X, np.ones_like(V))
    R2, _ = planar_cameras(Xc)
    S = height_field(Xc, V, R2)
    flat = rest_height_ratio(S) <= rest_ratio
    res = _finish(Xc, V, R2, S, t, 'planar', 0, 1, flat, t0)
    if rigid_check is True and flat:
        rigid_check = safe_rigid(W, V)
    if rigid_check is not False and flat and \
            res.residual_px > PLANAR_RIGID_RATIO * rigid_residual(rigid_check):
        res = replace(res, converged=False)
    return replace(res, seconds=time.perf_counter() - t0)


def safe_rigid(W: np.ndarray, V: np.ndarray) -> NRSfMResult | None:
    """The rigid factorisation, or None where it fails."""
    try:
        return rigid(W, V)
    except (np.linalg.LinAlgError, ValueError, FloatingPointError):
        return None


def rigid_residual(res: NRSfMResult | None) -> float:
    """A rigid factorisation's reprojection residual (px); inf where it failed or is not
    finite, so that a comparison with it then rests on the other tests alone."""
    r = float('inf') if res is None else res.residual_px
    return r if np.isfinite(r) else float('inf')
