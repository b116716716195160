"""Streaming NRSfM keyed by track id: one shape per input frame, one gauge for the stream.

The tracker's track set changes over a stream (a reference re-selection carries the visible
tracks with their ids and adds new ones), so frames are stored as (ids, uv, visibility) and every
solve runs on the union of the ids of its frames, a track absent from a frame being invisible
there.  Modes (the reconstructor's ``mode``):

* ``window``: low-rank NRSfM over the last ``window`` frames, warm-started when the track set
  did not change; nothing until the first window is full, then every buffered frame, then one
  shape per frame.
* ``online``: the first window as ``window``, then each frame fitted alone to that window's
  rank-K shape basis (O(KP)); the basis is rebuilt from the buffered frames when more than
  ``REBASE_FRACTION`` of a frame's tracks are not in it.
* ``batch``: ``batch_frames`` frames at a time with ``method`` (``auto``: ``planar`` when its
  orthonormality test says the rest shape is planar, else ``bmm``).  With ``projection``
  ``perspective`` and intrinsics (:meth:`StreamNRSfM.set_intrinsics`) every batch solve is
  refined for a perspective camera (:func:`perspective.perspective_solve`: the shapes are then in
  weak-perspective-equivalent image coordinates, which back-project exactly); a ``planar``
  batch is then fitted to the pinhole image itself (:mod:`.planar_pinhole`).  A batch after
  the first is solved with up to ``batch_context`` published frames before it that share its
  tracks (context, not published again).
* ``dspr``: the first ``batch_frames`` frames solved as ``batch`` (published together), their
  shapes clustered into a dynamic shape prior of distinct states (:mod:`.dspr`), then one shape
  per frame at low latency: every state fitted at once by orthographic Procrustes; a frame whose
  residual is under ``dspr_recurrence_px`` (0: 1.5 x the batch's RMS residual, at least
  0.75 px) is a recurrence of that state (stored as camera +
  state index), else a per-frame energy started from the best state gives the shape, which joins
  the prior when farther than ``dspr_distinct`` (0: half the batch's mean shape distance from
  its first shape) from every state.  ``compression_ratio`` =
  frames / states.  Tracks new since the prior get the depth of their nearest prior tracks in
  the image (``dspr_new_tracks`` counts them).
* ``spva``: the first ``batch_frames`` frames solved as ``batch``; the ``spva_prior_frames``
  least occluded of them (total-intensity criterion on the visibility) give a shape prior and the
  batch's shapes a low-rank subspace (:mod:`.spva`); the batch frames are re-solved with the
  prior and published together, then each frame alone: data on the visible tracks, Huber-TV on
  the track grid, the subspace and the prior weighted by the occlusion (``spva_weighting``),
  the prior refreshed at ``spva_refresh``.  New tracks as in ``dspr``.

Gauge: every shape is in its frame's camera frame in image units (x, y the centred pixel
coordinates), so rotation and scale are fixed by the data; the remaining depth reflection is
chosen, for every solve after the first, to agree with the shapes already published on the
frames and tracks they share.  ``flush()`` at the end of a stream returns a shape for every
frame still pending (a stream shorter than the window is solved whole), so no frame is lost.
"""
from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..arrays import duplicates, sorted_unique
from ..metrics import rotation_range_deg
from ..threads import map_threads
from .dspr import DynamicShapePrior, necker_partner, object_shapes, shape_distance
from .factorization import low_rank, rigid
from .perspective import (RATIO_RANGE, check_intrinsics, frame_errors, frame_reflections,
                          perspective_solve, reflect_frames, reflected_error)
from .planar import PLANAR_PERSPECTIVE_RATIO
from .planar_pinhole import (ROBUST_PX, finish_planar_pinhole, fit_planar_pinhole,
                             pinhole_image)
from .result import NRSfMResult
from .rigid_pinhole import batch_sign
from .spva import WEIGHTINGS, ShapePrior

MODES = ('window', 'online', 'batch', 'dspr', 'spva')
# the batch solves' methods (auto, or a name of core.nrsfm.METHODS; spva is a mode)
BATCH_METHODS = ('auto', 'lowrank', 'rigid', 'bmm', 'smsr', 'amp', 'cdf', 'hdsm', 'va',
                 'planar')
PROJECTIONS = ('perspective', 'weak')
REBASE_FRACTION = 0.1     # online: rebuild the basis when more of a frame's tracks are new
MIN_OBSERVED = 2          # a track is reconstructed once seen (visible) in this many frames
MIN_SEEN = 0.7            # a batch's track is solved where seen in this share of its frames
MIN_SEEN_TRACKS = 100     # min_seen applies where it keeps at least this many tracks
SPVA_MIN_SEEN = 0.3       # spva's first batch: min_seen at most this (its prior term fills the
#   tracks an occluder hides part of the time; those seen in fewer frames spoil its solve),
#   except in a fragmented batch (_fragment_share): over the 48 sweep cases through the
#   tracker spva / static median 1.055 -> 1.021, geometric mean 1.243 -> 1.157, the cap at
#   60 deg 0.152 -> 0.078, the held-out tube at 60 deg 0.254 -> ~0.08; 0.5 / 0.7: the occluded
#   face at 12 deg amplitude 2 0.068 -> 0.18 (BENCHMARKS, issue 13, session 48)
FRAGMENTED_SHARE = 0.1    # _fragmented: a batch is halved where fewer of its tracks are seen in
#   min_seen of its frames (the 60 deg occluded cap 0.2%, a tube's far side 0.3-2.4%; the
#   other face / cap batches 100%): the cap 0.297 -> 0.204, the tube at 60 deg
#   0.59-0.74 -> 0.11-0.32 (BENCHMARKS, issue 12, session 47)
MIN_PART_FRAMES = 10      # _fragmented: not halved into parts shorter than this
NEW_TRACK_NEIGHBOURS = 4  # dspr: a track new since the prior takes its neighbours' depth
BATCH_MAX_TRACKS = 10000  # batch solves run on at most this many spread tracks, extended to all
BMM_RIGID_RATIO = 0.5     # auto: bmm's reprojection residual over rigid's above which the rigid
#   factorisation is taken.  Measured on ground-truth tracks of the 256x192 renders: the face
#   (nearly rigid: static 0.026-0.054) 0.19-0.58 without the occluder, 0.69-1.49 with it (bmm's
#   e3D 0.08-0.18 there against rigid's 0.025-0.067); the cap at 12 deg 0.24 (bmm 0.20, rigid
#   0.27); the mocap sets of ../shared/data/nrsfm 0.00-0.26 (face 0.26, the rest <= 0.12).
SMALL_RANGE_DEG = 25.0    # auto: cameras turning less than this over a batch barely observe
#   depth: bmm's nuclear norm flattens it (relief 0.21-0.22 against the truth's 0.32-0.34 on
#   the face at 12 deg, 15 deg of camera rotation, through the tracker) ...
RANGE_AGREEMENT = 0.75    # ... so where the rigid factorisation's cameras turn at least this x
#   as far as bmm's (its depth not stretched by the bas-relief ambiguity, which shrinks its
#   rotation: the breathing cap at 12 deg 8 / 20 deg, relief 0.84 against 0.43) rigid is taken.
#   The 48-case sweep: the face at 12 deg 0.0787 / 0.0954 -> 0.0268 / 0.0602 (static 0.0256 /
#   0.0497), ground-truth tracks 0.0826 -> 0.0248, no other case changed (BENCHMARKS issue 12,
#   session 43, at 0.9).  The tracker's faces there at 0.94-1.06 of bmm's rotation on session
#   43's machine, 0.84 / 0.77 on session 49's (bmm kept at 0.9: 3.19x / 2.00x static; at 0.75
#   0.78x / 0.91x); the caps at 0.42-0.72 there, 0.17-0.63 here (session 49)
BMM_LAM = 4.0            # bmm's lam (its own default) for batches up to BMM_LAM_FRAMES frames
BMM_LAM_FRAMES = 60       # longer batches scale it by sqrt(frames / BMM_LAM_FRAMES): the
#   tracker's errors are smooth in time, low rank as the deformation is, and their singular
#   values grow with sqrt(frames) past a threshold that does not; a 30 frames/s camera's
#   180-frame batch otherwise took bmm on the face (0.041) where rigid gets 0.031 (BENCHMARKS
#   issue 12, "The camera's frame rate")
BMM_ITERATIONS = 40      # ADMM iterations of the stream's bmm solves (bmm's own default: 100):
#   the same e3D to 4 digits on 8 face / cap sweep cases (30 / 60 deg, with and without the
#   occluder; ground-truth stream and through the tracker), `process` on the 320x240 face
#   12.7 -> 9.4 s (BENCHMARKS, issue 17)
DECISION_TRACKS = 2000    # auto decides bmm against rigid on at most this many spread tracks:
#   the ratio on 2000 of ~5k ground-truth tracks of the 256x192 renders is within 3% of the
#   full one (face 30 deg 0.338 / 0.341, 0.699 / 0.691 occluded, 60 deg 0.585 / 0.585; cap
#   0.561 / 0.550, 0.694 / 0.693; flag 0.898 / 0.901; sheet 0.302 / 0.298) at 2-3x less time
DEPTH_RATIO_RANGE = (0.25, 4.0)   # a frame's depth over the stream's reference (_gauge)
SIGN_TRACKS = 400         # spva: the steps' depth sign from this many spread tracks (the
#   flag's and sheet's periodic renders: the same signs as from 1000, 3.5 -> 2.8 ms a frame)
RATE_FRAMES = 4           # a new batch continues the camera's turn over this many frames
SIGN_FIT_FRAMES = 30      # a later batch refined under the pinhole camera over at least this many
#   frames keeps the depth sign of its fit; a shorter or unrefined one takes the last published
#   frame's (_emit).  Continuity alone let a wrong frame at a batch's end (its shape drifting
#   to a reversed relief) reflect the whole next batch: 600-frame 12 deg flag render, 95 of 600
#   frames published reflected, 35 with the fit's sign; 150-frame flag and sheet renders (12
#   / 30 / 60 deg, amplitude 1 / 2) 456 -> 200 frames of 1800, e3D unchanged; the one short
#   batch measured, a 20-frame flush of the sheet at 12 deg, was right by continuity (1 frame
#   reflected) and wrong by its fit (19): BENCHMARKS, issue 12, session 35
RECURRENCE_AUTO = 1.5     # dspr_recurrence_px 0: this x the prior batch's RMS residual (px)
RECURRENCE_MIN_PX = 0.5   # ... but at least this x RECURRENCE_AUTO
BASIS_RECURRENCE = 2.0    # ... and this x more where the batch was auto's rigid basis: it fits
#   about half of the residual rigid leaves (0.32-0.54 of it on the face, through the tracker),
#   the tracks' noise among it, and the test is against that noise (periodic cap: compression
#   10.9 with rigid's prior, 4.3 on the basis at 1.5 x its residual, 10.9 at 2 x 1.5)
DISTINCT_AUTO = 0.5       # dspr_distinct 0: this x the batch's mean shape distance from its
DISTINCT_MIN = 1e-3       # first shape (its deformation range), at least DISTINCT_MIN
CONTEXT_OVERLAP = 0.5     # batch_context: a published frame is context of a later batch while it
#   sees this share of the tracks visible in the batch's first frame (none across a re-selection)
START_FLIP_CORRELATION = 0.5   # _reflected_start: a planar last batch's first frame whose depth
#   correlation with the last published frame is below minus this starts reflected
START_FLIP_FRAMES = 3     # ... against each of the last this many published frames
PLANAR_KEPT_RATIO = 1.1   # auto after a planar batch: planar's perspective test allows this x
#   PLANAR_PERSPECTIVE_RATIO (the same surface; a 90-frame flag batch at 12 deg tested 1.014 and
#   went bmm at e3D 0.088 against planar's 0.035: BENCHMARKS, issue 12, session 36)
CROSSING_TILT = 15.0      # _refine_planar: a frame where the plane faces the camera closer than
CROSSING_PROMINENCE = 5.0  # this (deg), the least tilt of a dip this deep on both sides, is
CROSSING_STARTS = 2       # a crossing; the refinement also starts from the batch reflected after
#   each of the (at most this many) deepest.  84 runs of planar renders (60 / 150 / 300 frames,
#   ground-truth and tracker tracks): frames published reflected 866 -> 647, e3D geometric mean
#   0.983 (the 300-frame sheet at 30 deg 0.047 -> 0.035, 69 -> 18 reflected; the occluded sheet
#   at 12 deg +11%); with the deepest one only 796 and two renders +21% / +49%: BENCHMARKS,
#   issue 12, session 37


def plane_crossings(R: np.ndarray, max_tilt: float = CROSSING_TILT,
                    prominence: float = CROSSING_PROMINENCE, most: int = CROSSING_STARTS
                    ) -> list[int]:
    """Frames (in order) where a planar solve's plane faces the camera most: local minima of
    the tilt (the angle between the plane's normal, the object z axis, and the viewing axis;
    cameras R (F, 3, 3) object -> camera) under ``max_tilt`` degrees whose dip is at least
    ``prominence`` degrees below the highest tilt on each side, the ``most`` deepest.  A plane's
    two depth reflections coincide there, so a Necker slip enters a batch only at such a frame
    (BENCHMARKS, issue 12, session 36)."""
    tilt = np.degrees(np.arccos(np.clip(np.abs(np.asarray(R)[:, 2, 2]), 0.0, 1.0)))
    found = []
    for f in range(1, tilt.size - 1):
        if tilt[f] <= tilt[f - 1] and tilt[f] < tilt[f + 1] and tilt[f] < max_tilt:
            dip = min(tilt[:f].max(), tilt[f + 1:].max()) - tilt[f]
            if dip >= prominence:
                found.append((dip, f))
    return sorted(f for _, f in sorted(found, reverse=True)[:most])


@dataclass(frozen=True)
class StreamShape:
    """One frame's reconstruction: ``X`` (n, 3) camera frame, image units (x, y centred pixel
    coordinates of the frame, z depth relative to the frame's centroid, towards the scene),
    ``t`` (2,) the image position of the centroid, for the tracks ``ids`` (n,).

    ``R`` (3, 3): the rotation object -> this camera (``X ~ R Y`` for the object-frame shape
    ``Y``, proper) in the stream's one object frame (the first frame's camera axes, carried
    across solves: :meth:`StreamNRSfM._gauge`; the per-frame dspr / spva steps' cameras in
    their prior's, the first batch's), None where the frame's solve has no cameras (a flat
    fallback, the online steps).  ``depth_ratio``: the
    centroid's depth over the stream's reference depth (the inverse of the frame's
    weak-perspective scale, in the same carried gauge): a camera closer to the surface sees it
    larger, and the metric cloud is then nearer, not larger (``processing.to_metric``)."""

    index: int
    ids: np.ndarray
    X: np.ndarray
    t: np.ndarray
    residual_px: float
    R: np.ndarray | None = None
    depth_ratio: float | None = None


@dataclass
class _Frame:
    index: int
    ids: np.ndarray
    uv: np.ndarray
    vis: np.ndarray


def _solve_default(W: np.ndarray, V: np.ndarray, method: str, rank: int,
                   perspective: tuple[float, np.ndarray] | None = None,
                   planar_ratio: float = PLANAR_PERSPECTIVE_RATIO,
                   basis: bool = True) -> NRSfMResult:
    """A batch solve with ``method``; over ``BATCH_MAX_TRACKS`` tracks on a spread subset,
    extended to every track (core/nrsfm/extend.py).  ``perspective``: the camera's (focal,
    principal point), for ``auto``'s planar test, and ``planar_ratio`` its bound; ``basis``:
    ``auto``'s rigid choice as its rank-``rank`` basis (:func:`auto_solve`)."""
    from .extend import subset_solve
    return subset_solve(lambda W, V: _solve_all(W, V, method, rank, perspective,
                                                 planar_ratio, basis), W, V, BATCH_MAX_TRACKS)


def bmm_lam(frames: int) -> float:
    """``lam`` of the stream's ``bmm`` solves for a batch of ``frames``: bmm's own (4.0) up to
    ``BMM_LAM_FRAMES``, then x sqrt(frames / BMM_LAM_FRAMES)."""
    return BMM_LAM * float(np.sqrt(max(frames, BMM_LAM_FRAMES) / BMM_LAM_FRAMES))


def _warm_bmm(W: np.ndarray, V: np.ndarray, start: NRSfMResult) -> NRSfMResult:
    """The stream's ``bmm`` of tracks near those ``start`` explains (the perspective step's
    corrected measurements), started from it (``bmm.bmm_warm``), on the same spread subset as
    ``_solve_default``."""
    from .bmm import bmm_warm
    from .extend import spread_subset, subset_solve
    idx = spread_subset(V.shape[1], BATCH_MAX_TRACKS)      # the subset subset_solve takes
    sub_start = start if idx.size == V.shape[1] else replace(start, S=start.S[:, idx])
    return subset_solve(lambda W, V: bmm_warm(W, V, sub_start, lam=bmm_lam(V.shape[0]),
                                              iterations=BMM_ITERATIONS), W, V, BATCH_MAX_TRACKS)


def _warm_bmm_staged(W: np.ndarray, V: np.ndarray, start: NRSfMResult
                     ) -> tuple[NRSfMResult, Callable[[], NRSfMResult]]:
    """``_warm_bmm`` in two stages (``bmm.bmm_warm_staged``), for tracks within
    ``BATCH_MAX_TRACKS`` (no subset)."""
    from .bmm import bmm_warm_staged
    return bmm_warm_staged(W, V, start, lam=bmm_lam(V.shape[0]), iterations=BMM_ITERATIONS)


def _solve_all(W: np.ndarray, V: np.ndarray, method: str, rank: int,
               perspective: tuple[float, np.ndarray] | None = None,
               planar_ratio: float = PLANAR_PERSPECTIVE_RATIO,
               basis: bool = True) -> NRSfMResult:
    from . import reconstruct
    if method == 'auto':
        return auto_solve(W, V, perspective, planar_ratio, rank if basis else 0)
    kw = {'rank': rank} if method in ('lowrank', 'amp') else {}
    if method == 'bmm':
        kw = {'iterations': BMM_ITERATIONS, 'lam': bmm_lam(V.shape[0])}
    if method == 'planar':          # chosen (by the user or by auto's first decision): the
        kw = {'rigid_check': False}  # stream never reads converged, skip its rigid solve
    return reconstruct(W, V, method=method, **kw)


def rigid_observed(rig: NRSfMResult, trial: NRSfMResult) -> bool:
    """``auto``'s second test of ``bmm`` (``trial``) against rigid (``rig``, the same tracks):
    both cameras turn less than ``SMALL_RANGE_DEG`` over the batch, where ``bmm`` flattens the
    depth the views barely observe, and rigid's cameras turn at least ``RANGE_AGREEMENT`` x as
    far as ``bmm``'s, so its depth is not stretched by the bas-relief ambiguity: rigid is then
    the better shape (the face at 12 deg 3x ``bmm``'s e3D), and where rigid's rotation is
    shrunk ``bmm`` stays (the breathing cap at 12 deg, rigid's relief twice the truth's)."""
    rr, rb = rotation_range_deg(rig.R), rotation_range_deg(trial.R)
    return max(rr, rb) < SMALL_RANGE_DEG and rr >= RANGE_AGREEMENT * rb


def auto_solve(W: np.ndarray, V: np.ndarray,
               perspective: tuple[float, np.ndarray] | None = None,
               planar_ratio: float = PLANAR_PERSPECTIVE_RATIO, rank: int = 2
               ) -> NRSfMResult:
    """``method: auto``: the deformation model chosen from the tracks, among three nested in
    freedom: ``planar`` where its tests pass (a flat rest shape whose reprojection residual is
    at most ``PLANAR_RIGID_RATIO`` x one rigid shape's; with the camera's ``perspective``
    (focal, principal point) also a perspective image explained at most ``planar_ratio``
    (``PLANAR_PERSPECTIVE_RATIO``; the stream allows more after a planar batch) x as badly as
    by the rigid shape, and "flat" then up to ``PLANAR_REST_RATIO_PERSPECTIVE``), else ``bmm``,
    unless
    ``bmm`` explains less than ``1 - BMM_RIGID_RATIO`` of the reprojection residual that the
    rigid factorisation leaves: its per-frame shapes then fit what the rigid shape cannot by
    depths the camera motion does not observe (or its fill of hidden tracks failed), and rigid
    is taken; or where the cameras turn too little to observe the deformation's depth and the
    rigid factorisation's cameras turn as far as bmm's (``rigid_observed``).  Where rigid is
    taken, its shapes become a rank-``rank`` shape basis started from it (``lowrank``,
    :func:`_rigid_basis`): the deformation the rigid shape leaves in its residual; ``rank``
    0: rigid itself (the stream's ``spva`` prior, whose weights and subspace were measured
    on it; ``dspr`` takes the basis, its recurrence test ``BASIS_RECURRENCE`` x looser)."""
    from .bmm import bmm, bmm_warm
    from .extend import extend, spread_subset
    from .planar import (PLANAR_REST_RATIO, PLANAR_REST_RATIO_PERSPECTIVE, PLANAR_RIGID_RATIO,
                         planar, rigid_residual, safe_rigid)
    lam = bmm_lam(V.shape[0])
    # the rigid factorisation and the planar solve two at a time: planar reads the rigid
    # result only in its last test (the residual ratio, applied here as planar applies it);
    # its flatness bound with the camera is the one for a rigid result that did not fail
    # (with the camera the perspective test below also judges planar: the flatness test may
    # then allow the relief a weak-perspective fit reads into a close camera's perspective)
    rest_ratio = PLANAR_REST_RATIO_PERSPECTIVE if perspective is not None \
        else PLANAR_REST_RATIO
    rig, res = map_threads(lambda f: f(), [
        lambda: safe_rigid(W, V),
        lambda: planar(W, V, rigid_check=False, rest_ratio=rest_ratio)])
    checked = perspective is not None and rig is not None
    if perspective is not None and rig is None:       # the bound without the camera's test
        res = planar(W, V, rigid_check=None, rest_ratio=PLANAR_REST_RATIO)
    elif res.converged and res.residual_px > PLANAR_RIGID_RATIO * rigid_residual(rig):
        res = replace(res, converged=False)
    if res.converged and checked and \
            reflected_error(res, W, V, *perspective, per_frame=True) > \
            planar_ratio * reflected_error(rig, W, V, *perspective):
        res = replace(res, converged=False)
    if res.converged:
        return res
    if rig is None:
        return bmm(W, V, lam=lam, iterations=BMM_ITERATIONS)
    # bmm against rigid is decided on a spread subset of the tracks (the residual ratio is a
    # mean over tracks): the full bmm solve is only paid where bmm is taken
    idx = spread_subset(V.shape[1], DECISION_TRACKS)
    sub = idx.size < V.shape[1]
    Ws, Vs = (W[:, idx], V[:, idx]) if sub else (W, V)
    trial, rig_sub = map_threads(lambda f: f(), [          # two at a time, as above
        lambda: bmm(Ws, Vs, lam=lam, iterations=BMM_ITERATIONS),
        lambda: safe_rigid(Ws, Vs) if sub else rig])
    if trial.residual_px > BMM_RIGID_RATIO * rigid_residual(rig_sub) or \
            (rig_sub is not None and rigid_observed(rig_sub, trial)):
        return _rigid_basis(W, V, rig, rank) if rank > 0 else rig
    if not sub:
        return trial
    # the full solve starts from the subset's, extended to every track: its cameras stand in
    # for a metric projection of all tracks (the same e3D within +-6% on the sweep's bmm
    # cases, BENCHMARKS issue 17, session 16)
    return bmm_warm(W, V, extend(trial, idx, W, V), lam=lam, iterations=BMM_ITERATIONS)


def _rigid_basis(W: np.ndarray, V: np.ndarray, rig: NRSfMResult, rank: int) -> NRSfMResult:
    """``auto`` where it takes the rigid factorisation ``rig``: the rank-``rank`` shape basis
    (``lowrank``) started from its cameras and shape, ``rig`` itself where that cannot run
    (a frame that sees no track) or fails; on at most ``DECISION_TRACKS`` spread tracks,
    extended to every track by its basis.  On the 48-case sweep (BENCHMARKS, issue 12,
    session 46) the face's jaw and cheeks, which one rigid shape averages away, come back:
    the face through the tracker 1.03x -> 0.87x static (median), on ground-truth tracks 0.88x
    -> 0.70x; the breathing cap 1.22x -> 1.26x."""
    from .extend import extend, spread_subset
    idx = spread_subset(V.shape[1], DECISION_TRACKS)     # then every track by its basis
    sub = idx.size < V.shape[1]
    try:
        res = low_rank(W[:, idx], V[:, idx], rank=rank, init=replace(rig, S=rig.S[:, idx])) \
            if sub else low_rank(W, V, rank=rank, init=rig)
        if sub:
            res = extend(res, idx, W, V)
    except (ValueError, np.linalg.LinAlgError):
        return rig
    return res if np.isfinite(res.S).all() and np.isfinite(res.R).all() else rig


def _auto_basis(W: np.ndarray, V: np.ndarray, rank: int) -> NRSfMResult:
    """``auto``'s choice of the rigid basis (:func:`_rigid_basis`) solved again, on the
    perspective-corrected tracks: the rigid factorisation, then its basis."""
    from .planar import safe_rigid
    rig = safe_rigid(W, V)
    return low_rank(W, V, rank=rank) if rig is None else _rigid_basis(W, V, rig, rank)


def _integer(name: str, value: Any, lo: int) -> int:
    """``value`` as an int, or a ValueError naming ``name`` unless it is an integer >= ``lo``
    (a bool is not)."""
    if isinstance(value, (bool, np.bool_)) or int(value) != value or value < lo:
        raise ValueError(f'{name}: expected an integer >= {lo}, got {value}')
    return int(value)


class StreamNRSfM:
    """``push(ids, uv, visibility)`` -> the shapes that became available; ``flush()`` -> the
    rest.  Shapes come out in frame order, exactly one per pushed frame over the stream."""

    def __init__(self, mode: str = 'window', window: int = 15, rank: int = 2,
                 iterations: int = 10, method: str = 'auto', batch_frames: int = 60,
                 batch_context: int = 30,
                 solver: Callable[[np.ndarray, np.ndarray, str, int], NRSfMResult] | None = None,
                 projection: str = 'weak', dspr_recurrence_px: float = 0.0,
                 dspr_distinct: float = 0.0, dspr_prior_weight: float = 0.01,
                 spva_prior_frames: int = 10, spva_weighting: str = 'pixel',
                 spva_prior_weight: float = 10.0, spva_smoothness: float = 0.05,
                 spva_refresh: float = 0.0, spva_iterations: int = 10,
                 min_seen: float = MIN_SEEN) -> None:
        if mode not in MODES:
            raise ValueError(f'mode={mode!r}: expected one of {MODES}')
        if solver is None and method not in BATCH_METHODS:    # a solver takes its own names
            raise ValueError(f'method={method!r}: expected one of {BATCH_METHODS}')
        if projection not in PROJECTIONS:
            raise ValueError(f'projection={projection!r}: expected one of {PROJECTIONS}')
        self.projection = projection
        self._intrinsics: tuple[float, np.ndarray] | None = None
        self.reflected_frames = 0        # batch frames reflected by _frame_reflections
        self.perspective_solves = 0      # batch solves where the perspective model won
        self.pinhole_refinements = 0     # planar batch solves refined under the pinhole camera
        self.batch_splits = 0            # batches solved as two halves (_fragmented)
        self.pinhole_signs = 0           # first batches whose depth sign a pinhole fit decided
        self.last_method = ''            # the method of the last batch solve (auto's choice)
        if not (np.isfinite(min_seen) and 0 <= min_seen <= 1):
            raise ValueError(f'min_seen: expected 0..1, got {min_seen}')
        self.min_seen = float(min_seen)
        self.tracks_left_out = 0         # tracks the last batch solve left out (min_seen)
        for name, v, lo in (('window', window, 3), ('rank', rank, 1), ('iterations', iterations,
                                                                        1),
                            ('batch_frames', batch_frames, 3)):
            if v < lo:
                raise ValueError(f'{name}: expected >= {lo}, got {v}')
        self.batch_context = _integer('batch_context', batch_context, 0)
        self.mode, self.window, self.rank, self.iterations = mode, window, rank, iterations
        self.method, self.batch_frames = method, batch_frames
        for name, v in (('dspr_recurrence_px', dspr_recurrence_px),
                        ('dspr_distinct', dspr_distinct)):
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f'{name}: expected a finite value >= 0, got {v}')
        if not (np.isfinite(dspr_prior_weight) and dspr_prior_weight > 0):
            raise ValueError(f'dspr_prior_weight: expected > 0, got {dspr_prior_weight}')
        self.dspr_recurrence_px, self.dspr_distinct = dspr_recurrence_px, dspr_distinct
        self.dspr_prior_weight = dspr_prior_weight
        if not 1 <= spva_prior_frames <= (batch_frames if mode == 'spva' else np.inf):
            raise ValueError(f'spva_prior_frames: expected 1..batch_frames ({batch_frames}), '
                             f'got {spva_prior_frames}')
        if spva_weighting not in WEIGHTINGS:
            raise ValueError(f'spva_weighting={spva_weighting!r}: expected one of {WEIGHTINGS}')
        for name, v in (('spva_prior_weight', spva_prior_weight),
                        ('spva_smoothness', spva_smoothness)):
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f'{name}: expected a finite value >= 0, got {v}')
        if not (np.isfinite(spva_refresh) and 0 <= spva_refresh <= 1):
            raise ValueError(f'spva_refresh: expected 0..1, got {spva_refresh}')
        _integer('spva_iterations', spva_iterations, 1)
        self.spva = dict(prior_frames=int(spva_prior_frames), weighting=spva_weighting,
                         prior_weight=float(spva_prior_weight),
                         smoothness=float(spva_smoothness), refresh=float(spva_refresh),
                         iterations=int(spva_iterations))
        self._solver = solver or _solve_default
        size = batch_frames if mode in ('batch', 'dspr', 'spva') else window
        self._frames: deque[_Frame] = deque(maxlen=size + (batch_context if mode == 'batch'
                                                           else 0))
        self._pending: list[_Frame] = []          # pushed, no shape published yet
        self._published: deque[StreamShape] = deque(maxlen=size)
        self._count = 0
        self._last: tuple[np.ndarray, NRSfMResult] | None = None   # window warm start
        self._basis: tuple[np.ndarray, np.ndarray] | None = None   # online: ids, (K, 3, P)
        self._known = np.empty(0, np.int64)     # online: every id the basis' window reported
        self._left_out = np.empty(0, np.int64)  # the ids the last batch left out (min_seen)
        self._R2 = np.eye(3)[:2]
        self._a = np.zeros(rank)
        self.fallbacks: list[tuple[int, str]] = []   # (frame, why) published by a fallback
        self._flip = np.ones(3)                       # reflection of the last _emit
        self._batch_last: tuple[np.ndarray, NRSfMResult, np.ndarray] | None = None
        self.prior: DynamicShapePrior | ShapePrior | None = None   # dspr / spva: the prior
        self._batch_perspective = False               # the last batch solve was perspective
        self._pinhole_signed = False    # the last batch's depth sign is its pinhole fit's
        self._prior_perspective = False               # spva's prior from a perspective batch
        self._prior_ids = np.empty(0, np.int64)
        self._last_G: np.ndarray | None = None        # the last solve's gauge rotation
        self._prior_G: np.ndarray | None = None       # dspr / spva: the prior's batch's
        self._new_ids: set[int] = set()
        self._expected: int | None = None   # the stream's length where known (expect)
        self.dspr_seconds: list[float] = []           # dspr: per-frame solve time after the prior

    @property
    def compression_ratio(self) -> float:
        """dspr: frames represented by the prior / its states (1.0 before it exists and in
        the other modes, which store every shape)."""
        return self.prior.compression_ratio if isinstance(self.prior, DynamicShapePrior) \
            else 1.0

    @property
    def dspr_new_tracks(self) -> int:
        """dspr: distinct tracks published that are not in the prior (depth from neighbours)."""
        return len(self._new_ids)

    @property
    def frames_seen(self) -> int:
        return self._count

    def set_intrinsics(self, focal: float, principal: np.ndarray) -> None:
        """Focal length (px) and principal point (cx, cy) of the camera, for ``perspective``."""
        self._intrinsics = check_intrinsics(focal, principal)

    # ------------------------------------------------------------------ public
    def set_batch(self, frames: int, context: int) -> None:
        """Resize the batches (``batch_frames``, ``batch_context``) before the first batch is
        solved: the reconstructor's batch measured in time (``batch_seconds``) once the
        stream's frame rate is known; a ValueError once a shape was published."""
        if self._count != len(self._pending):
            raise ValueError('set_batch: a batch was solved already')
        frames = _integer('batch_frames', frames, 3)
        context = _integer('batch_context', context, 0)
        if self.mode == 'spva' and self.spva['prior_frames'] > frames:
            raise ValueError(f'batch_frames={frames}: below spva_prior_frames '
                             f'({self.spva["prior_frames"]})')
        self.batch_frames, self.batch_context = int(frames), int(context)
        if self.mode in ('batch', 'dspr', 'spva'):
            extra = self.batch_context if self.mode == 'batch' else 0
            size = 2 * self.batch_frames + extra if self.mode == 'batch' and \
                self._expected is not None else self.batch_frames + extra
            self._frames = deque(self._frames, maxlen=size)
            self._published = deque(self._published, maxlen=self.batch_frames)

    def expect(self, frames: int) -> None:
        """The stream's length in frames, where it is known (``process`` on a bag).  In
        ``batch`` mode a batch that fills with at most ``batch_frames // 2`` frames left waits
        for them and is solved with them, so the stream never ends on a short batch solved
        alone or with a few frames of context (150-frame renders through the tracker,
        BENCHMARKS issue 12, session 36), unless the last batch was ``planar`` (then
        the rest is the flush's, as live: two of the planar renders lost up to 1.5x)."""
        self._expected = _integer('frames', frames, 0)
        if self.mode == 'batch':        # a last batch of up to 1.5 batch_frames, its context
            self._frames = deque(self._frames, maxlen=2 * self.batch_frames + self.batch_context)

    def _waits(self) -> bool:
        """A full batch waits for the stream's last frames (:meth:`expect`)."""
        if self.mode != 'batch' or self._expected is None or self.last_method == 'planar':
            return False
        return 0 < self._expected - self._count <= self.batch_frames // 2

    def push(self, ids: np.ndarray, uv: np.ndarray, visibility: np.ndarray | None = None
             ) -> list[StreamShape]:
        ids = np.asarray(ids).astype(np.int64)
        uv = np.asarray(uv, dtype=np.float64)
        if uv.ndim != 2 or uv.shape != (ids.size, 2):
            raise ValueError(f'uv: expected shape ({ids.size}, 2), got {uv.shape}')
        vis = np.ones(ids.size) if visibility is None else np.asarray(visibility, np.float64)
        if vis.shape != (ids.size,):
            raise ValueError(f'visibility: expected shape ({ids.size},), got {vis.shape}')
        if duplicates(ids):
            raise ValueError('ids: duplicated track ids in one frame')
        fr = _Frame(self._count, ids, uv, np.clip(np.nan_to_num(vis), 0.0, 1.0))
        self._count += 1
        self._frames.append(fr)
        self._pending.append(fr)
        if self.mode in ('dspr', 'spva') and self.prior is not None:
            return [self._publish(self._step_dspr(fr))]
        if self.mode in ('batch', 'dspr', 'spva'):
            if len(self._pending) < self.batch_frames or self._waits():
                return []
            out = self._solve_batch(self._context() + list(self._pending),
                                    self.mode == 'spva')
            if self.mode == 'dspr':
                self._build_prior()
                self._prior_G = self._last_G if self.prior is not None else None
            return out
        if self.mode == 'online' and self._basis is not None:
            if self._new_fraction(fr) <= REBASE_FRACTION:
                try:
                    return [self._publish(self._fit_online(fr))]
                except (np.linalg.LinAlgError, ValueError, ArithmeticError) as err:
                    self.fallbacks.append((fr.index, f'{type(err).__name__}: {err}'))
                    return [self._publish(_flat_shape(fr))]
            self._basis = None                  # too many new tracks: re-solve the window
        if len(self._frames) < self.window:
            return []
        return self._solve_window()

    def flush(self) -> list[StreamShape]:
        """Shapes for every frame still pending (end of stream)."""
        if not self._pending:
            return []
        if self.mode == 'batch' and len(self._pending) >= self.batch_frames:
            # a batch that waited for frames that did not come (expect): solved as it is
            return self._solve_batch(self._context() + list(self._pending))
        if len(self._frames) >= 2 and self._pending[0].index >= self._frames[0].index:
            if self.mode == 'batch' and self._published and self.last_method != 'planar' \
                    and self.batch_context > 0:
                # a short last batch is solved with the frames before it (a full batch, its
                # published ones as context): alone it sees little camera motion (face 30 deg,
                # 30-frame flush: 0.155 -> 0.03); planar solves lost with it (flag 60 deg
                # amplitude 2 0.140 -> 0.228): BENCHMARKS, issue 12, session 35
                return self._solve_batch(list(self._frames)[-self.batch_frames:])
            return self._solve_batch(list(self._pending)) \
                if self.mode in ('batch', 'dspr', 'spva') \
                else self._solve_window()
        # a single frame: no depth is observable; its points at the centroid's depth
        return [self._publish(_flat_shape(fr)) for fr in list(self._pending)]

    def _context(self) -> list[_Frame]:
        """``batch`` mode, a later batch: the last up to ``batch_context`` published frames
        before it that see at least ``CONTEXT_OVERLAP`` of the tracks visible in its first
        frame (back to the first that does not: a reference re-selected before the batch ends
        its context).  Solved with the batch (not published again), they give it the camera
        motion before it: a batch where the camera passes near a planar surface's normal cannot
        fix the tilt alone (sheet 60 deg, frames 60-119: 0.103 -> 0.049)."""
        if self.mode != 'batch' or not self._published or self.batch_context == 0:
            return []
        first = self._pending[0]
        ref = first.ids[first.vis >= 0.5]
        before = [f for f in self._frames if f.index < first.index][-self.batch_context:]
        keep: list[_Frame] = []
        for f in reversed(before):
            seen = np.intersect1d(f.ids[f.vis >= 0.5], ref, assume_unique=True).size
            if seen < CONTEXT_OVERLAP * max(ref.size, 1):
                break
            keep.append(f)
        return keep[::-1]

    # ------------------------------------------------------------------ tracks -> W, V
    @staticmethod
    def _tracks(frames: list[_Frame]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """W (2F, P) and V (F, P) over the union of the frames' ids (absent = invisible),
        keeping tracks seen in at least ``MIN_OBSERVED`` frames; returns ids, W, V."""
        F, first = len(frames), frames[0].ids
        if all(np.array_equal(f.ids, first) for f in frames[1:]) and \
                bool((first[1:] > first[:-1]).all()):
            # one ascending track set in every frame (a tracker that reports each track with
            # its visibility): the columns are the frames' own order
            all_ids = first
            W = np.stack([f.uv.T for f in frames]).reshape(2 * F, first.size)
            V = np.maximum(np.stack([f.vis for f in frames]), 1e-3)
        else:
            all_ids = sorted_unique(np.concatenate([f.ids for f in frames]))
            W = np.zeros((2 * F, all_ids.size))
            V = np.zeros((F, all_ids.size))
            for i, f in enumerate(frames):
                col = np.searchsorted(all_ids, f.ids)
                W[2 * i, col], W[2 * i + 1, col] = f.uv[:, 0], f.uv[:, 1]
                # present but occluded: weakly kept (the low-rank model carries it)
                V[i, col] = np.maximum(f.vis, 1e-3)
        keep = (V >= 0.5).sum(axis=0) >= min(MIN_OBSERVED, F)
        if keep.sum() < 4:                      # nearly nothing visible: use what is there
            keep = V.sum(axis=0) > 0
        # np.compress keeps (W, V) C-ordered (W[:, keep] is not: every numba kernel and
        # perspective_error call of a batch then copied the whole tracks)
        return all_ids[keep], np.compress(keep, W, axis=1), np.compress(keep, V, axis=1)

    def _batch_tracks(self, frames: list[_Frame],
                      tracks: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``_tracks`` (or ``tracks``, already assembled for ``frames``) less those seen in
        fewer than ``min_seen`` of the frames that report them, where at least
        ``MIN_SEEN_TRACKS`` remain (``tracks_left_out`` counts them), in modes ``batch`` and
        ``dspr`` (whose frames after the prior leave the same ids out: taken at their
        neighbours' depth as new tracks they cost the periodic cap 0.043 -> 0.050; left out,
        0.032); in ``spva`` (its prior term fills what an occluder hides) at most
        ``SPVA_MIN_SEEN`` of them, and none left out of a fragmented batch."""
        ids, W, V = self._tracks(frames) if tracks is None else tracks
        self.tracks_left_out, self._left_out = 0, np.empty(0, ids.dtype)
        share = self.min_seen
        if self.mode == 'spva':
            share = min(share, SPVA_MIN_SEEN) if self._fragment_share(frames, V) >= \
                FRAGMENTED_SHARE else 0.0
        elif self.mode not in ('batch', 'dspr'):
            share = 0.0
        if share <= 0:
            return ids, W, V
        often = (V >= 0.5).sum(axis=0) >= share * (V > 0).sum(axis=0)
        if often.all() or often.sum() < MIN_SEEN_TRACKS:
            return ids, W, V
        self.tracks_left_out = int((~often).sum())
        self._left_out = ids[~often]            # dspr: left out of its later frames too
        return ids[often], np.compress(often, W, axis=1), np.compress(often, V, axis=1)

    # ------------------------------------------------------------------ solves
    def _solve_window(self) -> list[StreamShape]:
        frames = list(self._frames)
        ids, W, V = self._tracks(frames)
        init = None
        if self._last is not None and len(frames) == self._last[1].S.shape[0]:
            init = _warm_start(self._last[0], _shifted(self._last[1]), ids, W)
        res = self._safe(lambda: low_rank(W, V, rank=self.rank, iterations=self.iterations
                                          if init is not None else max(self.iterations, 60),
                                          init=init), W, V, frames)
        self._last = (ids, res)
        out = self._emit(frames, ids, res, list(self._pending))
        if self.mode == 'online' and self._basis is None:
            self._init_basis(ids, res)
            self._known = sorted_unique(np.concatenate([f.ids for f in frames]))
        return out

    def _fragment_share(self, frames: list[_Frame], V: np.ndarray) -> float:
        """The share of the batch's tracks seen in ``min_seen`` of its frames (1 where
        ``min_seen`` is 0 or the batch is too short to halve: not fragmented)."""
        if len(frames) < 2 * MIN_PART_FRAMES or self.min_seen <= 0 or not V.shape[1]:
            return 1.0
        return float(((V >= 0.5).sum(axis=0) >= self.min_seen * V.shape[0]).mean())

    def _fragmented(self, frames: list[_Frame], V: np.ndarray) -> bool:
        """A ``batch`` (or ``dspr``'s first) whose tracks are each seen in few of its frames
        (under ``FRAGMENTED_SHARE`` of them in ``min_seen`` of the batch's frames: a surface whose
        visible side turns away, the tracker's reference re-selected inside the batch), long
        enough to halve into parts of at least ``MIN_PART_FRAMES``: one factorisation of it
        is ill-posed (the 60 deg occluded cap: rigid's cameras turn 133 deg where the truth's
        turn 74).  ``V``: the visibility of the frames' tracks (``_tracks``)."""
        return self.mode in ('batch', 'dspr') and \
            self._fragment_share(frames, V) < FRAGMENTED_SHARE

    def _solve_batch(self, frames: list[_Frame], spva: bool = False) -> list[StreamShape]:
        tracks = self._tracks(frames)
        if self._fragmented(frames, tracks[2]):
            # solved as two halves in turn, each published (and so each in the stream's gauge)
            # before the next: each half's tracks are seen in more of its frames; dspr's prior
            # then comes from the last half (the tracks later frames still see).  Not spva
            # (_fragmented: batch and dspr only; its prior rebuilt from the last half, the
            # held-out tube at 60 deg behind the occluder 0.162 -> 0.274: BENCHMARKS, issue 13,
            # session 48)
            half = len(frames) // 2
            self.batch_splits += 1
            return self._solve_batch(frames[:half]) + self._solve_batch(frames[half:])
        ids, W, V = self._batch_tracks(frames, tracks)
        if len(frames) == 2:
            res = self._safe(lambda: low_rank(W, V, rank=1), W, V, frames)
        else:
            res = self._safe(lambda: self._batch_solve(W, V), W, V, frames)
        res = self._frame_reflections(res, W, V)
        if spva and res.method != 'flat':
            res = self._spva_prior(ids, W, V, res)
        indices = {f.index for f in frames}
        out = self._emit(frames, ids, res, [f for f in self._pending if f.index in indices])
        if spva and self.prior is not None and self._prior_G is None:
            self._prior_G = self._last_G    # the prior's object frame is this batch's
        self._batch_last = (ids, res, self._flip)
        return out

    def _batch_solve(self, W: np.ndarray, V: np.ndarray) -> NRSfMResult:
        def solve(W: np.ndarray, V: np.ndarray) -> NRSfMResult:
            if self._solver is _solve_default:     # batch mode: auto's rigid as its basis
                persp = self.projection == 'perspective'
                return _solve_default(W, V, self.method, self.rank,
                                      self._intrinsics if persp else None,
                                      PLANAR_PERSPECTIVE_RATIO * (
                                          PLANAR_KEPT_RATIO if persp and
                                          self.last_method == 'planar' else 1.0),
                                      self.mode in ('batch', 'dspr'))
            return self._solver(W, V, self.method, self.rank)
        self._batch_perspective = False
        self._pinhole_signed = False
        if self.projection != 'perspective' or self._intrinsics is None:
            res = solve(W, V)
        else:
            weak = solve(W, V)
            # auto decides once, on the measured tracks: the corrected ones re-tested could flip
            # a flat-at-rest surface to bmm (sheet 60 deg amplitude 2: rest ratio 0.077 -> 0.085
            # against 0.08, e3D 0.10 -> 0.25)
            method = weak.method if self.method == 'auto' and \
                weak.method in ('planar', 'bmm', 'rigid', 'lowrank') else self.method
            basis = self.method == 'auto' and method == 'lowrank' and \
                self._solver is _solve_default     # auto's rigid basis, as auto built it

            def solve_fixed(W: np.ndarray, V: np.ndarray) -> NRSfMResult:
                if basis:
                    from .extend import subset_solve
                    return subset_solve(lambda W, V: _auto_basis(W, V, self.rank), W, V,
                                        BATCH_MAX_TRACKS)
                return self._solver(W, V, method, self.rank)
            warm = _warm_bmm if method == 'bmm' and weak.method == 'bmm' and \
                self._solver is _solve_default else None
            staged = _warm_bmm_staged if warm is not None and \
                V.shape[1] <= BATCH_MAX_TRACKS else None
            res = perspective_solve(solve_fixed, W, V, *self._intrinsics, weak=weak, warm=warm,
                                    staged=staged)
            if method == 'planar' and res.method == 'planar':
                refined = self._refine_planar(res, W, V)
                self._pinhole_signed = refined is not res and V.shape[0] >= SIGN_FIT_FRAMES
                res = refined
            self.perspective_solves += res is not weak
            self._batch_perspective = res is not weak
        self.last_method = res.method
        return res

    def _refine_planar(self, res: NRSfMResult, W: np.ndarray, V: np.ndarray) -> NRSfMResult:
        """A planar batch fitted to the pinhole image itself (:mod:`.planar_pinhole`: 2-4x
        lower e3D than the corrected re-solve alone at a 45 deg field of view).  ``planar``
        takes each frame's depth sign from the previous frame's and a local fit cannot undo a
        run of Necker-reversed frames, so where the perspective image reflects some frames
        (``frame_reflections``) the refinement also starts from those signs and the lower
        reprojection error decides (ground-truth tracks, 1.6 m, as-is / sign start: flag 30 deg
        amplitude 2 0.079 / 0.057 at 1.99 / 1.02 px, sheet 12 deg 0.067 / 0.040 at 0.77 / 0.28
        px, the flag at 96x72 0.101 / 0.186 at 0.33 / 0.51 px).  A slip at a frame where the
        plane faces the camera (``plane_crossings``) leaves the rest of the batch reflected
        with little evidence in the unrefined image, so the refinement also starts from the
        batch reflected after each such frame (the 300-frame sheet at 30 deg: its third batch
        0.78 px as-is, 0.36 px from its crossing).  The starts' rounds run on the spread
        subset and are ranked by their reprojection error there; only the best that explains
        the image better than its start is finished on every track (the final passes were a
        quarter of each start's time)."""
        intrinsics = self._intrinsics
        assert intrinsics is not None
        signs = frame_reflections(frame_errors(res, W, V, *intrinsics), per_frame=True)
        starts = [res] + ([reflect_frames(res, signs)] if (signs < 0).any() else [])
        after = np.arange(res.S.shape[0])
        starts += [reflect_frames(res, np.where(after > c, -1.0, 1.0))
                   for c in plane_crossings(res.R)]
        image = pinhole_image(W, V, *intrinsics)      # one for every start
        fits = map_threads(lambda s: fit_planar_pinhole(s, W, V, *intrinsics, image=image),
                           starts)
        for fit in sorted((f for f in fits if f is not None), key=lambda f: f.subset_px):
            refined = finish_planar_pinhole(fit, *intrinsics, ROBUST_PX, image)
            if refined is not fit.start:
                self.pinhole_refinements += 1
                return refined
        return res

    def _frame_reflections(self, res: NRSfMResult, W: np.ndarray, V: np.ndarray
                           ) -> NRSfMResult:
        """With intrinsics (``projection: perspective``): a batch solve in the depth
        reflection its perspective image agrees with (``perspective.frame_reflections``).  An
        orthographic solve leaves the sign to chance where the perspective refinement is not
        kept (a cap solved rigid came out concave in every frame), and the planar model picks
        each frame's sign from the previous frame's, so a flag turning through the view plane
        came out with its later frames reflected: for ``planar`` runs of frames may also take
        the other sign.  ``reflected_frames`` counts the frames reflected.

        The stream's first solve of a model with one sign for the batch (not ``planar``) asks
        the pinhole image after fitting: a rigid shape adjusted to the pixels from each Necker
        start (:func:`.rigid_pinhole.batch_sign`; a breathing cap imaged unfitted favoured the
        wrong reflection by 0.4%, fitted the right one by 4-7%), the image of the unfitted
        solve deciding only where the fits tie (``pinhole_signs`` counts the fits' decisions).
        The fits (~0.5 s, once a stream) are asked even where the unfitted image looks clear:
        the cap at 60 deg, amplitude 2, on its well-seen tracks (``min_seen``), solved ``bmm``,
        had a clear unfitted verdict (mean log error ratio 0.11 a frame) for the wrong
        reflection, the fits +6.1 standard errors for the right one (session 42; asking only
        below 0.05 had saved the fits' time on the sweep's other cases).  Later solves take
        the published frames' sign (``_reflection``)."""
        if self.projection != 'perspective' or self._intrinsics is None or \
                res.method == 'flat' or not np.isfinite(res.S).all():
            return res
        per_frame = res.method == 'planar'
        errors = frame_errors(res, W, V, *self._intrinsics)
        sign = 0.0
        if not per_frame and not self._published:
            sign, _ = batch_sign(res, W, V, *self._intrinsics)
            self.pinhole_signs += sign != 0.0
        if sign != 0.0:
            signs = np.full(res.S.shape[0], sign)
        else:
            signs = frame_reflections(errors, per_frame=per_frame)
        self.reflected_frames += int((signs < 0).sum())
        return reflect_frames(res, signs) if (signs < 0).any() else res

    def _safe(self, solve: Callable[[], NRSfMResult], W: np.ndarray, V: np.ndarray,
              frames: list[_Frame]) -> NRSfMResult:
        """``solve()``; if it raises or returns non-finite shapes, the rigid factorisation,
        and if that fails too, the flat shapes (the tracks at the centroid's depth).  Every
        fallback is recorded in ``fallbacks`` with its reason, per frame."""
        why = ''
        for attempt in (solve, lambda: rigid(W, V)):
            try:
                res = attempt()
                if np.isfinite(res.S).all() and np.isfinite(res.t).all():
                    break
                why = why or 'non-finite shapes'
            except (np.linalg.LinAlgError, ValueError, FloatingPointError,
                    ArithmeticError) as err:
                why = why or f'{type(err).__name__}: {err}'
        else:
            res = _flat_result(W, V)
        if why:
            pending = {f.index for f in self._pending}
            self.fallbacks += [(f.index, why) for f in frames if f.index in pending]
        return res

    def _emit(self, frames: list[_Frame], ids: np.ndarray, res: NRSfMResult,
              wanted: list[_Frame]) -> list[StreamShape]:
        """Shapes of ``wanted`` frames (a subset of ``frames``) from ``res``, in the stream's
        depth reflection, published in order."""
        pos = {f.index: i for i, f in enumerate(frames)}
        X_all = res.S * res.scale[:, None, None]             # (F, P, 3) image units
        self._flip = np.ones(3)
        signed, self._pinhole_signed = self._pinhole_signed, False     # this solve's only
        if self._published and not signed:
            self._flip = self._reflection(frames, ids, X_all)
            X_all = X_all * self._flip
        run = self._reflected_start(frames, ids, res, X_all) if signed else 0
        if run:             # signed: no stream flip to apply
            res = reflect_frames(res, np.where(np.arange(len(frames)) < run, -1.0, 1.0))
            X_all = res.S * res.scale[:, None, None]
        R_all, ratio = self._gauge(frames, res)
        shapes = []
        for fr in list(wanted):
            if fr.index not in pos:         # left the buffer unsolved: its tracks, flat
                self.fallbacks.append((fr.index, 'frame left the window unsolved'))
                shapes.append(self._publish(_flat_shape(fr)))
                continue
            i = pos[fr.index]
            col, have = _lookup(ids, fr.ids)
            shapes.append(self._publish(StreamShape(
                fr.index, fr.ids[have], X_all[i, col[have]], res.t[i], res.residual_px,
                None if R_all is None else R_all[i], float(ratio[i]))))
        return shapes

    def _reflected_start(self, frames: list[_Frame], ids: np.ndarray, res: NRSfMResult,
                         X_all: np.ndarray) -> int:
        """A ``planar`` solve whose sign its pinhole fit chose and that shares no frame with
        the published ones (a planar stream's last batch): how many of its first frames to
        reflect.  Its frames' signs are continuous in time, and a Necker reflection slips in
        continuously only where the plane faces the camera most (a plane's two reflections
        coincide there): a first frame whose depths run against each of the last
        ``START_FLIP_FRAMES`` published frames' (correlation below ``-START_FLIP_CORRELATION``;
        one wrong published frame is not followed) is taken to be in the other reflection up
        to the frame of least tilt (150-frame renders: 4-8 frames at the start of a 30-frame
        flush published reflected in 5 of 12 planar renders, fixed; BENCHMARKS, issue 12,
        session 36)."""
        if res.method != 'planar' or not self._published:
            return 0
        published = {sh.index for sh in self._published}
        if any(f.index in published for f in frames):
            return 0
        for sh in list(self._published)[-START_FLIP_FRAMES:]:
            dot, norms = _depth_agreement(sh, ids, X_all[0])
            if norms == 0.0 or dot >= -START_FLIP_CORRELATION * norms:
                return 0
        Xc = X_all - X_all.mean(axis=1, keepdims=True)
        normal = np.linalg.svd(Xc, full_matrices=False)[2][:, -1]     # (F, 3) per frame
        return int(np.argmin(np.hypot(normal[:, 0], normal[:, 1]))) + 1

    def _gauge(self, frames: list[_Frame], res: NRSfMResult
               ) -> tuple[np.ndarray | None, np.ndarray]:
        """The solve's cameras as proper rotations object -> camera and its frames' depth
        ratios (1 / scale), both carried into the stream's gauge: each solve has an object frame
        and a scale of its own, so they are aligned to the published frames they share with
        it (window solves overlap), else the first frame is taken to continue the last
        published ones at their last rate of turn and of depth change (a new batch: the camera
        moves smoothly); the stream's
        first solve puts its first camera at the identity and its mean depth ratio at 1.
        Rotations None for a solve without cameras (``flat``); a ratio outside
        ``DEPTH_RATIO_RANGE`` of the carried gauge is clipped (a degenerate scale)."""
        with np.errstate(divide='ignore', invalid='ignore'):
            r = 1.0 / np.asarray(res.scale, np.float64)
        good = np.isfinite(r) & (r > 0)
        r = np.where(good, r, np.median(r[good]) if good.any() else 1.0)
        Q = None
        if res.method != 'flat' and np.isfinite(res.R).all():
            Q = np.array(res.R, np.float64) * self._flip[:, None]     # diag(flip) R_f
            Q[:, :, 2] *= np.sign(np.linalg.det(Q))[:, None]          # proper: Q_f diag(1,1,d)
        pos = {f.index: i for i, f in enumerate(frames)}
        shared = [(pos[sh.index], sh) for sh in self._published if sh.index in pos]
        last = self._published[-1] if self._published else None
        turn, change = self._rate()
        if shared:
            k = float(np.median([sh.depth_ratio / r[i] for i, sh in shared
                                 if sh.depth_ratio is not None] or [1.0]))
        elif last is not None and last.depth_ratio is not None:
            k = last.depth_ratio * change / r[0]   # continues the last ones at their rate
        else:
            k = 1.0 / float(np.mean(r))
        ratio = np.clip(k * r, *DEPTH_RATIO_RANGE)
        if Q is None:
            self._last_G = None
            return None, ratio
        pairs = [(Q[i], sh.R) for i, sh in shared if sh.R is not None]
        if not pairs and last is not None and last.R is not None:
            pairs = [(Q[0], turn @ last.R)]
        if pairs:           # G = argmin sum |Q_i G - R_pub|: the polar factor of sum Q_i^T R
            U, _, Vt = np.linalg.svd(sum(q.T @ p for q, p in pairs))
            G = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
        else:
            G = Q[0].T
        self._last_G = G
        return Q @ G, ratio

    def _rate(self) -> tuple[np.ndarray, float]:
        """The published cameras' turn and depth-ratio change per frame, averaged over the last
        ``RATE_FRAMES`` frames (identity and 1 where fewer or without cameras)."""
        pub = [sh for sh in list(self._published)[-RATE_FRAMES - 1:]
               if sh.R is not None and sh.depth_ratio is not None]
        if len(pub) < 2 or pub[-1].index == pub[0].index:
            return np.eye(3), 1.0
        from scipy.spatial.transform import Rotation
        n = pub[-1].index - pub[0].index
        turn = Rotation.from_rotvec(Rotation.from_matrix(pub[-1].R @ pub[0].R.T).as_rotvec() / n)
        assert pub[0].depth_ratio and pub[-1].depth_ratio
        return turn.as_matrix(), float((pub[-1].depth_ratio / pub[0].depth_ratio) ** (1.0 / n))

    def _reflection(self, frames: list[_Frame], ids: np.ndarray, X_all: np.ndarray
                    ) -> np.ndarray:
        """[1, 1, +-1]: the depth sign agreeing with the published shapes of shared frames
        (their depths, centred, correlated on the shared tracks)."""
        score = 0.0
        pos = {f.index: i for i, f in enumerate(frames)}
        for sh in self._published:
            i = pos.get(sh.index)
            if i is not None:
                score += _depth_agreement(sh, ids, X_all[i])[0]
        if score == 0.0 and self._published:
            # no frame in common (a new batch): compare with the last published frame
            score = _depth_agreement(self._published[-1], ids, X_all[0])[0]
        return np.array([1.0, 1.0, -1.0 if score < 0 else 1.0])

    def _publish(self, shape: StreamShape) -> StreamShape:
        if shape.depth_ratio is None:       # a step without a scale keeps the last depth
            last = self._published[-1].depth_ratio if self._published else None
            shape = replace(shape, depth_ratio=1.0 if last is None else last)
        self._pending = [f for f in self._pending if f.index != shape.index]
        self._published.append(shape)
        return shape

    # ------------------------------------------------------------------ spva
    def _spva_prior(self, ids: np.ndarray, W: np.ndarray, V: np.ndarray, res: NRSfMResult
                    ) -> NRSfMResult:
        """spva: the shape prior from the first batch's solve, then the batch re-solved with
        it (the result published); the batch solve itself where that fails (in fallbacks)."""
        try:
            prior = ShapePrior.from_batch(res, W, V, **self.spva)
            out = prior.solve(W, V)
            if not (np.isfinite(out.S).all() and np.isfinite(out.t).all()):
                raise ArithmeticError('non-finite shapes')
        except (ValueError, np.linalg.LinAlgError, ArithmeticError) as err:
            pending = {f.index for f in self._pending}
            self.fallbacks += [(i, f'spva: {type(err).__name__}: {err}')
                               for i in sorted(pending)]
            return res
        self.prior, self._prior_ids = prior, ids
        self._prior_perspective = self._batch_perspective
        # each frame in the depth sign of the batch solve it was re-solved from (which the
        # perspective image chose): the orthographic re-solve of a near-planar frame leaves it
        # to chance (runs of the flag's and the sheet's batch frames came out reflected)
        za = res.S[:, :, 2] - res.S[:, :, 2].mean(axis=1, keepdims=True)
        zb = out.S[:, :, 2] - out.S[:, :, 2].mean(axis=1, keepdims=True)
        agree = (za * zb * V).sum(axis=1) >= 0
        return reflect_frames(out, np.where(agree, 1.0, -1.0)) if not agree.all() else out

    # ------------------------------------------------------------------ dspr
    def _build_prior(self) -> None:
        """The dynamic shape prior from the first batch's object-frame shapes, in the depth
        reflection they were published in (object_shapes x the flip: a proper rotation of the
        published camera-frame shapes)."""
        assert self._batch_last is not None
        ids, res, flip = self._batch_last
        if res.method == 'flat' or res.S.shape[0] < 2:
            return                              # nothing to learn from: stay in batch mode
        shapes = object_shapes(res) * flip
        basis = self.method == 'auto' and self.last_method == 'lowrank'   # auto's rigid basis
        distinct = self.dspr_distinct or max(
            DISTINCT_AUTO * float(np.mean(shape_distance(shapes[0], shapes))), DISTINCT_MIN)
        self.prior, _ = DynamicShapePrior.from_batch(
            replace(res, S=shapes, R=np.broadcast_to(np.eye(3), res.R.shape).copy(),
                    scale=np.ones(res.S.shape[0])),
            distinct=distinct, recurrence_px=self.dspr_recurrence_px
            or RECURRENCE_AUTO * (BASIS_RECURRENCE if basis else 1.0) * max(
                res.residual_px if np.isfinite(res.residual_px) else 0.0, RECURRENCE_MIN_PX),
            prior_weight=self.dspr_prior_weight)
        self._prior_ids = ids

    def _step_dspr(self, fr: _Frame) -> StreamShape:
        """One frame through the prior; tracks not in the prior at their image neighbours'
        depth, but for those the prior's batch left out (``min_seen``); the flat shape
        (recorded in ``fallbacks``) when too few prior tracks are seen."""
        assert self.prior is not None
        if self._left_out.size:                # what the first batch left out (min_seen)
            k = ~_lookup(self._left_out, fr.ids)[1]
            fr = _Frame(fr.index, fr.ids[k], fr.uv[k], fr.vis[k])
        pids = self._prior_ids
        col, have = _lookup(pids, fr.ids)
        uv = np.full((pids.size, 2), np.nan)
        vis = np.zeros(pids.size)
        fuv = fr.uv
        # with the camera dspr's prior poses its states by the pinhole camera on the pixels
        # and corrects them by the best posed state's depth ratios for its energy (dspr.py)
        camera = self._intrinsics if self.projection == 'perspective' and \
            isinstance(self.prior, DynamicShapePrior) else None
        if camera is None and self._prior_perspective and self._intrinsics is not None and \
                self._published:
            # spva's prior is in weak-perspective-equivalent coordinates: correct the tracks
            # by the depth ratio 1 + z / f of the last published shape (perspective.py)
            focal, c = self._intrinsics
            last = self._published[-1]
            lcol, lhave = _lookup(np.sort(last.ids), fr.ids)
            z = np.zeros(fr.ids.size)
            z[lhave] = last.X[np.argsort(last.ids)[lcol[lhave]], 2]
            fuv = c + (fr.uv - c) * np.clip(1.0 + z / focal, *RATIO_RANGE)[:, None]
        uv[col[have]] = fuv[have]
        vis[col[have]] = np.maximum(fr.vis[have], 1e-3)    # occluded: weakly kept, as _tracks
        vis[~np.isfinite(uv).all(axis=1)] = 0.0
        try:
            out = self.prior.step(uv, vis, camera=camera) if camera is not None else \
                self.prior.step(uv, vis)
        except (ValueError, np.linalg.LinAlgError, ArithmeticError) as err:
            self.fallbacks.append((fr.index, f'dspr: {type(err).__name__}: {err}'))
            return _flat_shape(fr)
        self.dspr_seconds.append(out.seconds)      # (spva too: per-frame seconds)
        X = np.empty((fr.ids.size, 3))
        X[have] = out.X[col[have]]
        if (~have).any():
            self._new_ids.update(int(i) for i in fr.ids[~have])
            X[~have, :2] = fuv[~have] - out.t
            X[~have, 2] = 0.0                             # the centroid's depth, unless ...
            finite = np.isfinite(fuv).all(axis=1)
            known = np.nonzero(have & finite)[0]
            new = np.nonzero(~have & finite)[0]
            if known.size and new.size:                   # ... the neighbours' depth
                from scipy.spatial import cKDTree
                k = min(NEW_TRACK_NEIGHBOURS, known.size)
                d, j = cKDTree(fuv[known]).query(fuv[new], k=k)
                d, j = d.reshape(-1, k), j.reshape(-1, k)
                w = 1.0 / np.maximum(d, 1e-6)
                X[new, 2] = (w * X[known[j], 2]).sum(axis=1) / w.sum(axis=1)
        R = out.R if np.isfinite(out.R).all() and np.linalg.det(out.R) > 0 else None
        if isinstance(self.prior, ShapePrior) and self.projection == 'perspective' and \
                self._intrinsics is not None and \
                self._spva_reflected(fr, have, self.prior.T[col[have]],
                                     out.X[col[have], 2]):
            # spva's orthographic step left a near-planar shape's depth sign to chance (the
            # flag's and the sheet's steps came out reflected in runs): the pinhole camera's
            X = X * [1.0, 1.0, -1.0]
            if R is not None:
                R = necker_partner(R, out.X_object)
        # the step's camera is in the prior's object frame, the first batch's (published with
        # no reflection: the stream's first solve): into the stream's by that batch's gauge
        R = None if R is None or self._prior_G is None else R @ self._prior_G
        return StreamShape(fr.index, fr.ids, X, out.t, out.residual_px, R)

    def _spva_reflected(self, fr: _Frame, have: np.ndarray, T: np.ndarray, z: np.ndarray
                        ) -> bool:
        """Whether spva's step, camera-frame depths ``z`` on the frame's tracks ``have`` that
        the prior has, runs against the depths of the prior's template ``T`` (on those tracks)
        posed by the pinhole camera on the frame's pixels (dspr.fit_states_pinhole, from both
        Necker poses; the step's own shape posed so did worse: flag 19 -> 36 reflected)."""
        from .dspr import _fit, fit_states_pinhole
        from .extend import spread_subset
        assert self._intrinsics is not None
        focal, c = self._intrinsics
        sub = spread_subset(T.shape[0], SIGN_TRACKS)
        T, z = T[sub], z[sub]
        uv, vis = fr.uv[have][sub], fr.vis[have][sub]
        v = np.where(vis >= 0.5, vis, 0.0)
        ok = np.isfinite(uv).all(axis=1)
        uv, v = np.where(ok[:, None], uv, 0.0), np.where(ok, v, 0.0)
        if v.sum() <= 0 or (v > 0).sum() < 4:
            return False
        pin = fit_states_pinhole(T[None], uv, v, focal, c, _fit(T[None], uv, v), mirror=True)
        if not np.isfinite(pin.residual_px[0]):
            return False
        depth = (T / focal @ pin.R[0].T)[:, 2]
        depth = depth - v @ depth / v.sum()
        return float((v * (z - v @ z / v.sum())) @ depth) < 0

    # ------------------------------------------------------------------ online
    def _init_basis(self, ids: np.ndarray, res: NRSfMResult) -> None:
        S_obj = np.einsum('fpi,fij->fpj', res.S * res.scale[:, None, None], res.R)  # (F, P, 3)
        F, P, _ = S_obj.shape
        U, s, Vt = np.linalg.svd(S_obj.transpose(0, 2, 1).reshape(F, 3 * P),
                                 full_matrices=False)
        K = min(self.rank, F)
        self._basis = (ids, Vt[:K].reshape(K, 3, P))
        self._a = U[-1, :K] * s[:K]
        self._R2 = res.R[-1, :2]

    def _new_fraction(self, fr: _Frame) -> float:
        """The share of a frame's tracks the basis' window never reported (one it reported
        but left out, seen in under ``MIN_OBSERVED`` of its frames, is not new)."""
        assert self._basis is not None
        return float((~_lookup(self._known, fr.ids)[1]).mean())

    def _fit_online(self, fr: _Frame) -> StreamShape:
        assert self._basis is not None
        bids, B = self._basis
        col, have = _lookup(bids, fr.ids)
        vis = np.zeros(bids.size)
        w = np.zeros((2, bids.size))
        vis[col[have]] = fr.vis[have]
        w[:, col[have]] = fr.uv[have].T
        K, _, P = B.shape
        sw = np.sqrt(vis)
        R2, a = self._R2, self._a
        T = np.zeros((2, 2 * P))
        T[0, :P], T[1, P:] = 1.0, 1.0
        for _ in range(5):
            # coefficients and translation by linear least squares, then the camera (polar)
            RB = np.einsum('ij,kjp->kip', R2, B).reshape(K, 2 * P)
            A = np.vstack([RB, T]).T * np.tile(sw, 2)[:, None]
            sol = np.linalg.lstsq(A, w.reshape(-1) * np.tile(sw, 2), rcond=None)[0]
            a, t = sol[:K], sol[K:]
            S = np.einsum('k,kip->ip', a, B)
            U, _, Vt = np.linalg.svd(((w - t[:, None]) * vis) @ S.T, full_matrices=False)
            R2 = U @ Vt
        self._R2, self._a = R2, a
        S = np.einsum('k,kip->ip', a, B)
        R3 = np.concatenate([R2, np.cross(R2[0], R2[1])[None]])
        X = (R3 @ S).T
        X = X * self._reflection([fr], bids, X[None])
        resid = np.linalg.norm(w - t[:, None] - R2 @ S, axis=0)
        return StreamShape(fr.index, fr.ids[have], X[col[have]], t,
                           float((resid * vis).sum() / max(vis.sum(), 1e-12)))


def _depth_agreement(sh: StreamShape, ids: np.ndarray, X: np.ndarray) -> tuple[float, float]:
    """A published shape's centred depths against a solved frame's X (P, 3) over the tracks
    they share (``ids``, ascending, label X's rows): their dot product and the product of
    their norms (0.0, 0.0 where fewer than 4 are shared)."""
    if ids.size == 0 or sh.ids.size == 0:
        return 0.0, 0.0
    if np.array_equal(sh.ids, ids):       # the same tracks (a window's frames, mostly)
        za, zb = sh.X[:, 2], X[:, 2]
    else:                                   # ids sorted: a search, not intersect1d's sorts
        col, have = _lookup(ids, sh.ids)
        za, zb = sh.X[have, 2], X[col[have], 2]
    if za.size < 4:
        return 0.0, 0.0
    za = za - za.mean()
    zb = zb - zb.mean()
    return float(za @ zb), float(np.linalg.norm(za) * np.linalg.norm(zb))


def _flat_shape(fr: _Frame) -> StreamShape:
    """The frame's tracks at their centroid's depth (no depth is observable from them)."""
    ok = np.isfinite(fr.uv).all(axis=1)
    t = fr.uv[ok].mean(axis=0) if ok.any() else np.zeros(2)
    return StreamShape(fr.index, fr.ids, np.concatenate([fr.uv - t, np.zeros((fr.ids.size, 1))],
                                                        axis=1), t, 0.0)


def _flat_result(W: np.ndarray, V: np.ndarray) -> NRSfMResult:
    F, P = V.shape
    Wf = W.reshape(F, 2, P)
    t = Wf.mean(axis=2)
    S = np.concatenate([(Wf - t[:, :, None]).transpose(0, 2, 1), np.zeros((F, P, 1))], axis=2)
    return NRSfMResult(S=S, R=np.broadcast_to(np.eye(3), (F, 3, 3)).copy(), scale=np.ones(F),
                       t=t, method='flat', rank=0, residual_px=float('nan'), iterations=0,
                       converged=False, seconds=0.0)


def _lookup(sorted_ids: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Columns of ``ids`` in ``sorted_ids`` and which of them are there at all."""
    col = np.clip(np.searchsorted(sorted_ids, ids), 0, sorted_ids.size - 1)
    return col, sorted_ids[col] == ids


def _warm_start(prev_ids: np.ndarray, prev: NRSfMResult, ids: np.ndarray, W: np.ndarray
                ) -> NRSfMResult:
    """The previous window's result on the new window's track set: shared tracks keep their
    shapes; a new track starts in its frames' image planes at the centroid depth."""
    if np.array_equal(prev_ids, ids):       # the same track set (most frames): as it is
        return prev
    F = prev.S.shape[0]
    col, have = _lookup(prev_ids, ids)
    S = np.empty((F, ids.size, 3))
    S[:, have] = prev.S[:, col[have]]
    uv = W.reshape(F, 2, -1)[:, :, ~have].transpose(0, 2, 1)             # (F, n, 2)
    S[:, ~have, :2] = (uv - prev.t[:, None, :]) / prev.scale[:, None, None]
    S[:, ~have, 2] = 0.0
    return replace(prev, S=S)


def _shifted(res: NRSfMResult) -> NRSfMResult:
    def shift(a: np.ndarray) -> np.ndarray:
        return np.concatenate([a[1:], a[-1:]], axis=0)
    return replace(res, S=shift(res.S), R=shift(res.R), scale=shift(res.scale), t=shift(res.t))
