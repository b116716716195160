"""Perspective NRSfM from any weak-perspective solver by affine iterations.

With intrinsics (focal length ``f`` in px, principal point ``c``) a point at depth Z of a frame
whose tracked centroid lies at depth Zbar projects to ``u = c + f X / Z``; a weak-perspective
camera would have seen ``c + (u - c) Z / Zbar``.  The solver's shapes give, per frame and point,
the relative depth ``z`` in image units, so ``Z / Zbar = 1 + z / f``: the measurements are
corrected by that ratio and re-solved, a few times (Christy and Horaud's iteration; it converges
in one or two steps when the depth relief is small against the distance).  The result is in the
corrected (weak-perspective equivalent) image coordinates, so the usual back-projection with the
stream's mean depth gives metric camera-frame shapes.

Perspective also tells the two depth reflections of a weak-perspective solution apart: both
are iterated from the first solution (one with its depth flipped) and the one whose *perspective*
reprojection error in the original pixels is lower wins; where the first solution imaged
through its own and through its flipped depths already differs by ``PROXY_MARGIN``, only the
better reflection is iterated.  When it does not cut the
weak-perspective solution's own error by ``MIN_GAIN`` (depth relief unobservable, e.g. a far or
flat scene), the weak-perspective solution is returned unchanged.

Its depth sign is then still the weak solver's coin toss, so the stream also asks every frame
(``frame_errors``: the result imaged with its own and with its reflected depths) and gives the
batch the sign with the lower total log error (``frame_reflections``); a model whose frames each
carry their own reflection (``planar``: a plane's Necker reversal, each frame's sign taken from
the previous one's) may also have runs of frames reflected, where the evidence over the run
exceeds ``FRAME_FLIP_SWITCH`` per change of sign.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from ..threads import map_threads
from .result import NRSfMResult

RATIO_RANGE = (0.5, 1.5)      # Z / Zbar kept in this range (a wild depth never explodes u)
FLIP = np.diag([1.0, 1.0, -1.0])
MIN_GAIN = 0.05               # perspective is kept when it cuts the pixel error by this much
PROXY_MARGIN = 1.05           # reflections told apart without a solve when their perspective
#   errors (the weak solution imaged through its own / its flipped depths) differ by this
#   factor.  Measured on eight batches of the 256x192 renders (face, cap; ground-truth and
#   tracker tracks): margins 1.06-1.19 on seven, each choosing the reflection the two solves
#   choose; one tie (cap 60 deg, 1.0001), left to the solves


def depth_ratio(res: NRSfMResult, focal: float) -> np.ndarray:
    """(F, P) Z / Zbar of each point from a weak-perspective result (image units)."""
    z = res.S[:, :, 2] * res.scale[:, None]
    return np.clip(1.0 + z / focal, *RATIO_RANGE)


def corrected_tracks(W: np.ndarray, ratio: np.ndarray, principal: np.ndarray) -> np.ndarray:
    """Tracks W (2F, P) as a weak-perspective camera would have seen them: every point moved
    about the principal point by its depth ratio ``ratio`` (F, P) = Z / Zbar."""
    F, P = ratio.shape
    c = np.asarray(principal, dtype=np.float64)[None, :, None]
    return ((W.reshape(F, 2, P) - c) * ratio[:, None, :] + c).reshape(2 * F, P)


def perspective_error(res: NRSfMResult, W: np.ndarray, V: np.ndarray, focal: float,
                      principal: np.ndarray, ratio: np.ndarray | float = 1.0) -> float:
    """Visibility-weighted mean pixel distance between ``W`` and ``res`` imaged by a camera that
    divides its weak-perspective projection by the depth ratio ``ratio`` (F, P) about the
    principal point: the pixel error of a solve of measurements corrected by ``ratio`` (1: the
    weak-perspective camera)."""
    from ..arrays import contiguous64
    from ._pinhole_kernels import weak_image_error
    c = np.asarray(principal, dtype=np.float64)
    # one pass over the points (numba): the array form's ten passes over (F, P) arrays were
    # 37 ms a call at 80 frames x 30k tracks
    per_point = np.ndim(ratio) > 0
    r = np.zeros((0, 0))
    if per_point:
        r = np.array(np.broadcast_to(ratio, V.shape), dtype=np.float64, order='C') \
            if np.shape(ratio) != V.shape else contiguous64(ratio)[0]
    S, scale, t, W, V = contiguous64(res.S, res.scale, res.t, W, V)
    return float(weak_image_error(S, scale, t, W, V, float(c[0]), float(c[1]), r,
                                  float(ratio) if not per_point else 1.0))


def reflect_frames(res: NRSfMResult, signs: np.ndarray) -> NRSfMResult:
    """``res`` with the depths of the frames where ``signs`` (F,) is negative reflected about
    their centroid (S's z and the camera's third row, FLIP @ R); the others unchanged."""
    flip = np.where(np.asarray(signs)[:, None] < 0, -1.0, 1.0)
    S = np.array(res.S, dtype=np.float64)
    S[:, :, 2] *= flip
    R = np.array(res.R, dtype=np.float64)
    R[:, 2] *= flip
    return replace(res, S=S, R=R)


def _flipped(res: NRSfMResult) -> NRSfMResult:
    return reflect_frames(res, -np.ones(res.S.shape[0]))


def _aligned(res: NRSfMResult, z_prev: np.ndarray) -> NRSfMResult:
    """``res`` in the depth reflection that agrees with the previous iterate's depths."""
    z = res.S[:, :, 2] * res.scale[:, None]
    return _flipped(res) if float((z * z_prev).sum()) < 0 else res


def check_intrinsics(focal: float, principal: np.ndarray) -> tuple[float, np.ndarray]:
    """Validated focal length (px) and principal point (cx, cy)."""
    principal = np.asarray(principal, dtype=np.float64).reshape(-1)
    if not (np.isfinite(focal) and focal > 0):
        raise ValueError(f'focal: expected a finite focal length > 0 px, got {focal}')
    if principal.shape != (2,) or not np.isfinite(principal).all():
        raise ValueError(f'principal: expected a finite (cx, cy), got {principal}')
    return float(focal), principal


def perspective_solve(solve: Callable[[np.ndarray, np.ndarray], NRSfMResult], W: np.ndarray,
                      V: np.ndarray, focal: float, principal: np.ndarray,
                      iterations: int = 1, weak: NRSfMResult | None = None,
                      warm: Callable[[np.ndarray, np.ndarray, NRSfMResult], NRSfMResult]
                      | None = None,
                      staged: Callable[[np.ndarray, np.ndarray, NRSfMResult],
                                       tuple[NRSfMResult, Callable[[], NRSfMResult]]]
                      | None = None) -> NRSfMResult:
    """``solve(W, V)`` (any weak-perspective NRSfM) refined for a perspective camera; see the
    module docstring.  ``iterations`` corrections after the reflection is chosen (>= 1, each one
    solve; the choice costs two); ``weak``: ``solve(W, V)`` if already computed; ``warm(W, V,
    start)``: the same solver started from ``start`` (the iterate being corrected, in its
    reflection), used for the corrected solves instead of ``solve``.  ``staged(W, V, start)``:
    ``warm`` in two stages (an early solution, and the function completing it into ``warm``'s
    result, e.g. ``bmm.bmm_warm_staged``): where both reflections are solved, their early
    solutions choose, and only the chosen one is completed.  Returns ``weak`` itself when the
    perspective model does not explain the tracks better."""
    focal, principal = check_intrinsics(focal, principal)
    if iterations < 1:
        raise ValueError(f'iterations: expected >= 1, got {iterations}')

    def depths(res: NRSfMResult) -> np.ndarray:
        return res.S[:, :, 2] * res.scale[:, None]

    weak = solve(W, V) if weak is None else weak
    if not (np.isfinite(weak.S).all() and np.isfinite(weak.t).all()):
        return weak
    weak_err = perspective_error(weak, W, V, focal, principal)

    def corrected(prev: NRSfMResult) -> tuple[np.ndarray, np.ndarray]:
        ratio = depth_ratio(prev, focal)
        return ratio, corrected_tracks(W, ratio, principal)

    def step(prev: NRSfMResult) -> tuple[float, NRSfMResult]:
        ratio, Wk = corrected(prev)
        res = warm(Wk, V, prev) if warm is not None else solve(Wk, V)
        res = _aligned(res, depths(prev))
        return perspective_error(res, W, V, focal, principal, ratio), res

    # one corrected solve from each reflection, then only the better one goes on; where the
    # weak solution imaged through its own depths already tells the reflections apart by
    # PROXY_MARGIN, only that one is solved (one solve less: a full bmm at 8k tracks)
    starts = (weak, _flipped(weak))
    proxy = [perspective_error(s, W, V, focal, principal, depth_ratio(s, focal))
             for s in starts]
    if max(proxy) > PROXY_MARGIN * min(proxy):
        starts = (starts[int(np.argmin(proxy))],)
    if len(starts) == 2 and staged is not None:
        # both re-solves judged at their early stage (the same choice as the complete
        # re-solves on 10 of 10 measured batches, BENCHMARKS issue 17): one completion less
        trials = []
        for start in starts:
            ratio, Wk = corrected(start)
            early, finish = staged(Wk, V, start)
            early = _aligned(early, depths(start))
            trials.append((perspective_error(early, W, V, focal, principal, ratio), start,
                           ratio, finish))
        _, start, ratio, finish = min(trials, key=lambda trial: trial[0])
        res = _aligned(finish(), depths(start))
        err = perspective_error(res, W, V, focal, principal, ratio)
    else:
        err, res = min(map_threads(step, starts), key=lambda e: e[0])
    for _ in range(iterations - 1):
        nxt_err, nxt = step(res)
        if not nxt_err < err:
            break
        err, res = nxt_err, nxt
    if err < (1.0 - MIN_GAIN) * weak_err and np.isfinite(res.S).all():
        return replace(res, residual_px=err)
    return weak


FRAME_FLIP_SWITCH = 1.0       # frame_reflections: the log-error evidence a run of frames needs
#   to leave (or re-enter) the batch's depth sign


def frame_errors(res: NRSfMResult, W: np.ndarray, V: np.ndarray, focal: float,
                 principal: np.ndarray) -> np.ndarray:
    """(F, 2) per frame: the visibility-weighted mean pixel error of ``res`` imaged by the
    perspective camera with its own depths and with the frame's depths reflected about its
    centroid (which the orthographic camera cannot tell apart), each with its best image
    translation."""
    from ..arrays import contiguous64
    from ._pinhole_kernels import frame_error_table
    focal, principal = check_intrinsics(focal, principal)
    return frame_error_table(*contiguous64(res.S, res.scale, res.t, W, V), focal,
                             principal[0], principal[1], *RATIO_RANGE)


def frame_reflections(errors: np.ndarray, per_frame: bool = False,
                      switch: float = FRAME_FLIP_SWITCH) -> np.ndarray:
    """(F,) +1 (keep) or -1 (reflect the frame's depths) from ``frame_errors``.  The batch's
    sign: the one with the lower total log error over its frames (an orthographic solve's depth
    sign is arbitrary; the perspective image of all frames together decides it).
    ``per_frame``: then runs of frames may take the other sign, where the sign sequence with the
    least total log error plus ``switch`` per change of sign says so (entering and leaving a run
    each cost ``switch``; one reaching the batch's end only its entry) -- for a model whose
    frames each carry their own reflection (a plane's Necker reversal), not for one shape seen
    in every frame."""
    cost = np.log(np.maximum(errors, 1e-12))
    g = 1 if cost[:, 1].sum() < cost[:, 0].sum() else 0          # the batch's sign
    cost = cost[:, [g, 1 - g]]
    F = cost.shape[0]
    state = np.zeros(F, np.intp)
    if per_frame:
        acc = np.array([cost[0, 0], cost[0, 1] + switch])
        back = np.zeros((F, 2), np.intp)
        for f in range(1, F):
            stay, move = acc, acc[::-1] + switch
            back[f] = np.where(stay <= move, [0, 1], [1, 0])
            acc = np.minimum(stay, move) + cost[f]
        s = int(np.argmin(acc))
        for f in range(F - 1, -1, -1):
            state[f] = s
            s = int(back[f, s])
    flipped = (state == 1) != bool(g)                        # state 1: the other sign than g
    return np.where(flipped, -1.0, 1.0)


def reflected_error(res: NRSfMResult, W: np.ndarray, V: np.ndarray, focal: float,
                    principal: np.ndarray, per_frame: bool = False) -> float:
    """Mean over frames of ``frame_errors`` with each frame in the sign ``frame_reflections``
    gives it: how well a weak-perspective result explains the perspective image, in its best
    depth reflection(s) -- comparable between models (``stream.auto_solve``)."""
    e = frame_errors(res, W, V, focal, principal)
    signs = frame_reflections(e, per_frame=per_frame)
    return float(np.mean(np.where(signs < 0, e[:, 1], e[:, 0])))
