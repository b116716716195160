"""A ``planar`` result refined under the pinhole camera (a close camera's field of view).

``perspective.perspective_solve`` corrects the tracks by the depth ratios of a weak-perspective
solve and re-solves; for the planar model at a ~45 deg field of view that leaves errors 2-4x
those of the same surface solved on tracks corrected by the *true* depths (BENCHMARKS, "Field
of view").  Here the planar model itself is fitted to the pinhole image:

- model: object-frame points ``(x_p, y_p, h_fp)`` -- rest coordinates in the plane and a height
  along its normal in every frame -- with heights of rank ``rank`` over the frames,
  ``h = C B`` (C (F, K), B (K, P)), seen by cameras ``(R_f, T_f)``: ``X_fp = R_f (x_p e1 +
  y_p e2 + h_fp e3) + T_f``;
- per round: (from the second on) each track's weight in each frame from its reprojection
  error, Cauchy at ``robust_px`` (``ROBUST_PX``: the tracker's gross errors); every frame's
  pose by ``POSE_STEPS`` Gauss-Newton steps on the reprojection error (all frames at once);
  C and B by ``ALTERNATIONS`` alternations of linear least squares on the algebraic error
  ``m_fp x X_fp`` (m the track's ray ``K^-1 [u, v, 1]``); then the rest coordinates (a 2 x 2
  system per point);
- start: the planar result in the camera frame (depth ``1 + z / f`` about each frame's centroid),
  the object frame from frame 0's principal axes, C and B from the rank-K SVD of the first
  heights along the rays.

The refinement is kept only when it lowers the pinhole reprojection error of the start (its
mean Cauchy loss at ``robust_px``) by ``MIN_GAIN`` and every point stays in front of the
camera; otherwise the input comes back unchanged.  Output in
the stream's convention: per frame, shapes centred on the visible points in image units with
the frame's centroid depth as the weak-perspective scale, so ``processing.to_metric`` back-
projects them exactly (up to the stream's one global scale).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from ..arrays import contiguous64
from ._pinhole_kernels import (cauchy_weights, height_terms, pose_normal_equations,
                               reprojection_loss, rest_coordinates)
from ._planar_kernels import final_passes
from .extend import spread_subset
from .perspective import check_intrinsics
from .result import NRSfMResult

ROUNDS = 12        # measured on ground-truth tracks (bench/study_planar_perspective.py): the
#   error falls for ~10 rounds and then holds
HEIGHT_RANK = 2    # rank of the heights over the frames
POSE_STEPS = 3
ALTERNATIONS = 3
ROBUST_PX = 5.0    # Cauchy scale (px) of the reprojection weights from the second round on: the
#   tracker's gross errors (5-7% of its visible tracks over 2 px on the sheet at 60 deg,
#   some tens of px) otherwise pull the fit.  Measured through the tracker at a 45 deg field of
#   view (e3D, 0 / 5 / 8 / 12 px): sheet 30 deg 0.059 / 0.030 / 0.031 / 0.032, sheet 60 deg
#   0.100 / 0.061 / 0.058 / -, flag 30 deg 0.030 at every scale (ground-truth tracks: no change)
MAX_TRACKS = 1500  # the rounds on at most this many spread tracks (then every track from
#   them): ground-truth tracks at 45 deg, 6k tracks, e3D all / 3000 / 1500 / 800: flag 30 deg
#   0.0291 / 0.0292 / 0.0292 / 0.0294, sheet 60 deg 0.0132 / 0.0133 / 0.0133 / 0.0133, flag
#   30 deg amplitude 2 0.0575 / 0.0573 / 0.0574 / 0.0578, sheet 12 deg 0.0394 / 0.0410 /
#   0.0411 / 0.0409
FINAL_PASSES = 6   # per-point passes giving every track its rest coordinates and heights
#   (bending sheet, a quarter of the tracks in the rounds: e3D 0.024 / 0.0097 / 0.0058 /
#   0.0056 after 1 / 3 / 6 / 12 passes; all tracks in the rounds 0.0045)
MIN_GAIN = 0.02    # kept when it cuts the start's pinhole reprojection error by this much
MIN_DEPTH = 0.05   # every refined point's depth over its frame's centroid depth at least this


def pose_steps(O: np.ndarray, m: np.ndarray, w: np.ndarray, R: np.ndarray, T: np.ndarray,
               steps: int) -> tuple[np.ndarray, np.ndarray]:
    """``steps`` Gauss-Newton steps on the reprojection error of object points O (F, P, 3)
    posed as ``R_f O + T_f`` against normalised image points m (F, P, 2) with weights
    w (F, P), all frames (or, for ``dspr``, all candidate shapes) at once: (R, T).  The normal
    equations in one pass over each frame's points (``_pinhole_kernels``)."""
    O, m, w = contiguous64(O, m, w)
    for _ in range(steps):
        JtJ, Jtr = pose_normal_equations(O, m, w, np.ascontiguousarray(R, np.float64),
                                         np.ascontiguousarray(T, np.float64))
        d = np.linalg.solve(JtJ + 1e-12 * np.eye(6), -Jtr[..., None])[..., 0]
        R = Rotation.from_rotvec(d[:, :3]).as_matrix() @ R
        T = T + d[:, 3:]
    return R, T


def _reprojection(X: np.ndarray, m: np.ndarray, w: np.ndarray, robust: float = 0.0
                 ) -> float:
    """Visibility-weighted mean distance (normalised image units) of X's image from m;
    ``robust`` > 0: the mean Cauchy loss of that distance at that scale (the same units), which
    a few gross track errors do not dominate; inf where a point is not in front."""
    return reprojection_loss(*contiguous64(X, m, w), float(robust))

def _start_pose(X0: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Object frame from frame 0's principal axes; per frame the rotation aligning frame 0's
    centred points with the frame's (Kabsch) and its centroid: (R (F, 3, 3), T (F, 3), object
    points (F, P, 3))."""
    T = (X0 * w[..., None]).sum(1) / np.maximum(w.sum(1), 1e-12)[:, None]
    C0 = X0 - T[:, None]
    axes = np.linalg.svd(C0[0] - C0[0].mean(0), full_matrices=False)[2]
    if np.linalg.det(axes) < 0:
        axes[2] *= -1
    H = C0.transpose(0, 2, 1) @ C0[0]
    u, _, vt = np.linalg.svd(H)
    sign = np.sign(np.linalg.det(u @ vt))
    D = np.zeros((X0.shape[0], 3, 3))
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = np.where(sign == 0, 1.0, sign)
    R = u @ D @ vt @ axes.T
    return R, T, C0 @ R


def _cauchy(rest: np.ndarray, h: np.ndarray, R: np.ndarray, T: np.ndarray, m: np.ndarray,
            w0: np.ndarray, robust: float) -> np.ndarray:
    """Weights w0 x the Cauchy weight at scale ``robust`` (normalised units) of each point's
    reprojection error, the points (rest, h) posed by R, T."""
    return cauchy_weights(*contiguous64(rest, h, R, T, m, w0), float(robust))

def _height_terms(rays: np.ndarray, R: np.ndarray, T: np.ndarray, rest: np.ndarray,
                  w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The algebraic error of X = A + h n (A the rest point posed, n the normal) is
    |m x A + h m x n|^2 = gg h^2 + 2 ga h + const: (gg, ga), each (F, P), weighted.  By
    (m x a) . (m x b) = |m|^2 a . b - (m . a)(m . b): no cross products."""
    return height_terms(*contiguous64(rays, R, T, rest, w))

def _solve_B(gg: np.ndarray, ga: np.ndarray, Cf: np.ndarray, ridge: float) -> np.ndarray:
    """Point basis B (K, P) of the heights h = C B minimising sum gg h^2 + 2 ga h, C given."""
    F, K = Cf.shape
    CC = (Cf[:, :, None] * Cf[:, None, :]).reshape(F, K * K)
    return np.linalg.solve((gg.T @ CC).reshape(-1, K, K) + ridge * np.eye(K),
                           -(ga.T @ Cf)[..., None])[..., 0].T


def _solve_C(gg: np.ndarray, ga: np.ndarray, Bp: np.ndarray, ridge: float) -> np.ndarray:
    """Frame coefficients C (F, K) of the heights, B given (matmul: einsum's 3-operand sums
    were 4 s of the 9)."""
    K = Bp.shape[0]
    BB = (Bp[:, None, :] * Bp[None]).reshape(K * K, -1)
    return np.linalg.solve((gg @ BB.T).reshape(-1, K, K) + ridge * np.eye(K),
                           -(ga @ Bp.T)[..., None])[..., 0]


def _solve_rest(rays: np.ndarray, R: np.ndarray, T: np.ndarray, h: np.ndarray, w: np.ndarray,
                rest: np.ndarray) -> np.ndarray:
    """Rest coordinates (P, 2) minimising the algebraic error over the frames, the heights
    given (a 2 x 2 system per point; a point without enough views keeps ``rest``).  The error
    is |m x (x e1 + y e2 + c)|^2 with e1, e2 the plane's axes in the camera and c = h n + T;
    its normal equations by the same identity as in ``_height_terms``."""
    return rest_coordinates(*contiguous64(rays, R, T, h, w, rest))

def _posed(rest: np.ndarray, h: np.ndarray) -> np.ndarray:
    F, P = h.shape
    return np.concatenate([np.broadcast_to(rest, (F, P, 2)), h[..., None]], 2)


def _fit(rays: np.ndarray, w0: np.ndarray, R: np.ndarray, T: np.ndarray, rest: np.ndarray,
         h: np.ndarray, rounds: int, rank: int, robust: float
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The rounds of the module docstring on the points given: (R, T, C, B, rest)."""
    m = np.ascontiguousarray(rays[..., :2])     # (the kernels take contiguous arrays)
    w, Cf = w0, None
    for rnd in range(rounds):
        pts = _posed(rest, h)
        if robust > 0 and rnd > 0:
            w = _cauchy(rest, h, R, T, m, w0, robust)
        R, T = pose_steps(pts, m, w, R, T, POSE_STEPS)
        gg, ga = _height_terms(rays, R, T, rest, w)
        if Cf is None:
            U, s, Vt = np.linalg.svd(np.where(w > 0, -ga / np.maximum(gg, 1e-15), h),
                                     full_matrices=False)
            Cf, Bp = U[:, :rank] * s[:rank], Vt[:rank].copy()
        ridge = 1e-9 * float(gg.sum()) / max(float(w.sum()), 1.0)
        for _ in range(ALTERNATIONS):
            Cf = _solve_C(gg, ga, Bp, ridge)
            Bp = _solve_B(gg, ga, Cf, ridge)
        h = Cf @ Bp
        rest = _solve_rest(rays, R, T, h, w, rest)
    return R, T, Cf, Bp, rest


@dataclass(frozen=True)
class PinholeImage:
    """The tracks' pinhole image as every refinement start reads it (:func:`pinhole_image`):
    visible weights ``w0`` (F, P), normalised image points ``m`` (F, P, 2), their rays
    (F, P, 3), the same per point for the final passes (P, F, 3) and (P, F), and the rounds'
    spread subset ``idx`` with its rays and weights.  Built once for the 2-4 starts of a batch
    (each built its own: ~64 MB of fresh memory a start at 80 frames x 10k tracks)."""
    w0: np.ndarray
    m: np.ndarray
    rays: np.ndarray
    rays_points: np.ndarray
    w0_points: np.ndarray
    idx: np.ndarray
    rays_sub: np.ndarray
    w0_sub: np.ndarray


def pinhole_image(W: np.ndarray, V: np.ndarray, focal: float, principal: np.ndarray,
                  max_tracks: int = MAX_TRACKS) -> PinholeImage:
    """The :class:`PinholeImage` of tracks W (2F, P), V (F, P) for refinements with these
    intrinsics and ``max_tracks``."""
    focal, principal = check_intrinsics(focal, principal)
    if max_tracks < 4:
        raise ValueError(f'max_tracks: expected >= 4, got {max_tracks}')
    F, P = V.shape
    w0 = np.ascontiguousarray(V >= 0.5, np.float64)
    m = np.ascontiguousarray((W.reshape(F, 2, P).transpose(0, 2, 1) - principal) / focal)
    rays = np.concatenate([m, np.ones((F, P, 1))], 2)
    idx = spread_subset(P, max_tracks)
    full = idx.size == P
    return PinholeImage(
        w0=w0, m=m, rays=rays,
        rays_points=rays if full else np.ascontiguousarray(rays.transpose(1, 0, 2)),
        w0_points=w0 if full else np.ascontiguousarray(w0.T), idx=idx,
        rays_sub=rays if full else np.ascontiguousarray(rays[:, idx]),
        w0_sub=w0 if full else np.ascontiguousarray(w0[:, idx]))


@dataclass(frozen=True)
class PlanarFit:
    """A refinement's rounds on the spread subset (:func:`fit_planar_pinhole`), waiting for
    :func:`finish_planar_pinhole` to give every track its rest coordinates and heights:
    the ``start`` it came from, the poses R (F, 3, 3), T (F, 3), the heights' frame
    coefficients ``Cf`` (F, K) and point basis ``Bp`` (K, subset), the rest coordinates and
    heights every track starts the final passes from (``rest`` (P, 2), ``h`` (F, P)), the
    subset's ``rest_sub`` and its pinhole reprojection error ``subset_px`` (mean, px): what
    several starts of one batch are ranked by before only the best is finished."""
    start: NRSfMResult
    R: np.ndarray
    T: np.ndarray
    Cf: np.ndarray
    Bp: np.ndarray
    rest: np.ndarray
    h: np.ndarray
    rest_sub: np.ndarray
    subset_px: float
    t0: float


def refine_planar_pinhole(res: NRSfMResult, W: np.ndarray, V: np.ndarray, focal: float,
                          principal: np.ndarray, rounds: int = ROUNDS,
                          rank: int = HEIGHT_RANK, robust_px: float = ROBUST_PX,
                          max_tracks: int = MAX_TRACKS, image: PinholeImage | None = None
                          ) -> NRSfMResult:
    """``res`` (a weak-perspective or ``perspective_solve`` result of W (2F, P), V (F, P) in
    image units) refined under the pinhole camera (focal px, principal point); see the module
    docstring.  ``res`` itself when the refinement does not explain the image better.
    ``max_tracks``: the rounds run on at most this many tracks spread over the set; the poses
    and the heights' frame coefficients found there then give every track its rest
    coordinates and height basis (per-point closed forms, ``FINAL_PASSES`` times).
    ``image``: :func:`pinhole_image` of the same tracks, intrinsics and ``max_tracks``, shared
    by several starts (built here when None).  :func:`fit_planar_pinhole` then
    :func:`finish_planar_pinhole`."""
    img = pinhole_image(W, V, focal, principal, max_tracks) if image is None else image
    fit = fit_planar_pinhole(res, W, V, focal, principal, rounds, rank, robust_px, max_tracks,
                             img)
    return res if fit is None else finish_planar_pinhole(fit, focal, principal, robust_px, img)


def fit_planar_pinhole(res: NRSfMResult, W: np.ndarray, V: np.ndarray, focal: float,
                       principal: np.ndarray, rounds: int = ROUNDS, rank: int = HEIGHT_RANK,
                       robust_px: float = ROBUST_PX, max_tracks: int = MAX_TRACKS,
                       image: PinholeImage | None = None) -> PlanarFit | None:
    """The rounds of :func:`refine_planar_pinhole` on its spread subset (arguments the same);
    None where ``res`` cannot start one (non-finite, fewer than 3 frames)."""
    focal, principal = check_intrinsics(focal, principal)
    if rounds < 1:
        raise ValueError(f'rounds: expected >= 1, got {rounds}')
    if rank < 1:
        raise ValueError(f'rank: expected >= 1, got {rank}')
    if not (np.isfinite(robust_px) and robust_px >= 0):
        raise ValueError(f'robust_px: expected a finite value >= 0 (0: least squares), got '
                         f'{robust_px}')
    if max_tracks < 4:
        raise ValueError(f'max_tracks: expected >= 4, got {max_tracks}')
    t0 = time.perf_counter()
    F, P = V.shape
    if not (np.isfinite(res.S).all() and np.isfinite(res.t).all()) or F < 3:
        return None
    img = pinhole_image(W, V, focal, principal, max_tracks) if image is None else image
    if img.w0.shape != (F, P):
        raise ValueError(f'image: for {img.w0.shape} tracks, the solve has {(F, P)}')
    w0 = img.w0
    X0 = _start_shapes(res, focal, principal)
    R, T, O = _start_pose(X0, w0)
    wr = w0 + 1e-9                    # a point never seen at V >= 0.5 keeps its mean position
    rest, h = (O[..., :2] * wr[..., None]).sum(0) / wr.sum(0)[:, None], O[..., 2]
    rank = min(rank, F, P)
    idx = img.idx
    R, T, Cf, Bp, rest_sub = _fit(img.rays_sub, img.w0_sub, R, T, rest[idx], h[:, idx], rounds,
                                  rank, robust_px / focal)
    Xs = _posed(rest_sub, Cf @ Bp) @ R.transpose(0, 2, 1) + T[:, None]
    err = _reprojection(Xs, img.rays_sub[..., :2], img.w0_sub) * focal
    return PlanarFit(res, R, T, Cf, Bp, rest, h, rest_sub,
                     err if np.isfinite(err) else np.inf, t0)


def _start_shapes(res: NRSfMResult, focal: float, principal: np.ndarray) -> np.ndarray:
    """``res``'s shapes in the camera frame relative to depth (F, P, 3)."""
    X = res.S * res.scale[:, None, None] / focal
    return np.stack([X[..., 0] + (res.t[:, None, 0] - principal[0]) / focal,
                     X[..., 1] + (res.t[:, None, 1] - principal[1]) / focal,
                     1.0 + X[..., 2]], 2)


def finish_planar_pinhole(fit: PlanarFit, focal: float, principal: np.ndarray,
                          robust_px: float, image: PinholeImage) -> NRSfMResult:
    """Every track of ``fit`` from its subset's poses and heights' frame coefficients
    (``FINAL_PASSES``), kept when it explains the image better than its start (``MIN_GAIN``)
    with every point in front: the refined result, else ``fit.start`` itself."""
    focal, principal = check_intrinsics(focal, principal)
    res, img = fit.start, image
    w0, m = img.w0, img.m
    robust = robust_px / focal
    err0 = _reprojection(_start_shapes(res, focal, principal), m, w0, robust)
    R, T = fit.R, fit.T
    if img.idx.size < w0.shape[1]:     # every track from the subset's poses and C
        rest, hT = final_passes(img.rays_points, img.w0_points, R, T,
                                np.ascontiguousarray(fit.Cf), fit.rest,
                                np.ascontiguousarray(fit.h.T), robust, FINAL_PASSES, 1e-9)
        h = hT.T
    else:
        rest, h = fit.rest_sub, fit.Cf @ fit.Bp
    Xr = _posed(rest, h) @ R.transpose(0, 2, 1) + T[:, None]
    if not (np.isfinite(Xr).all() and _reprojection(Xr, m, w0, robust) < (1.0 - MIN_GAIN) * err0):
        return res
    mean = (Xr * w0[..., None]).sum(1) / np.maximum(w0.sum(1), 1e-12)[:, None]   # (F, 3)
    if not (mean[:, 2] > 0).all() or (Xr[..., 2] < MIN_DEPTH * mean[:, None, 2]).any():
        return res
    S, scale, t = stream_convention(Xr, w0, focal, principal)
    return replace(res, S=S, R=R, scale=scale, t=t,
                   residual_px=_reprojection(Xr, m, w0) * focal,
                   seconds=res.seconds + time.perf_counter() - fit.t0)


def stream_convention(X: np.ndarray, w: np.ndarray, focal: float, principal: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera-frame points X (F, P, 3) (any one unit) in the stream's convention: per frame
    the shape centred on its w-weighted centroid (w (F, P)) in that unit, the scale
    focal / the centroid's depth (so ``S * scale`` is in image units) and the centroid's image
    position t (F, 2): ``processing.to_metric`` back-projects them exactly."""
    mean = (X * w[..., None]).sum(1) / np.maximum(w.sum(1), 1e-12)[:, None]
    scale = focal / mean[:, 2]
    return X - mean[:, None], scale, principal + mean[:, :2] * scale[:, None]
