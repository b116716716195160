"""Multi-frame subspace optical flow (MFOF) tracking with an occlusion tensor.

Every pixel of a reference mask is tracked reference->frame (never chained frame to frame).
Per incoming frame (streaming, bounded latency):

1. prediction: the motion subspace extrapolates the per-frame coefficients (constant velocity),
   giving a dense flow that seeds the data step, so large motion and occluded regions start from
   the subspace's guess, not from the previous measurement; with ``predict_offset`` (default)
   the data step's prediction adds every pixel's last offset from the subspace (step 4), i.e. a
   pixel starts at its own last position moved by the subspace's velocity, while the recapture
   pass keeps the smooth subspace-only seed.  Without the offset, folds that deform faster than
   the subspace follows (the first frames have only the polynomial images) are pre-warped
   wrongly by several px, lost within ~5 frames and carried on a drifting subspace
   (bench/bench_tracker_views.py, flag 256x192, 60 deg camera motion, amplitude 2: mean track
   error 10.8 -> 1.36 px, GT-visible kept 0.69 -> 0.86; end to end (bench_pipeline, batch)
   e3D 0.228 -> 0.069, ground-truth tracks 0.050);
2. data step: the frame is warped onto the reference by the prediction and OpenCV DIS (preset
   by name) measures the small residual flow reference->warped frame (and warped frame->
   reference for the forward-backward check); both images are contrast-normalised first (local
   zero mean, unit deviation), so shading changes and foreshortening do not bias the data step;
   recapture (``recapture_margin`` > 0): a second DIS pass matches the frame itself, seeded by
   the prediction (DIS starts from it at its coarsest scale, so it searches coarse to fine
   around it), and replaces the residual measurement where its local dissimilarity (below) is
   lower by the margin (smoothed over ~3 px).  A pixel whose prediction went wrong (lost on a
   foreshortened or shaded view, then carried by the subspace) distorts the pre-warped frame
   so the residual pass cannot find it again; the coarse-to-fine pass can, once the view
   allows (bench/bench_tracker_views.py, rendered face 256x192, 60 deg camera motion: mean
   track error 5.4 -> 1.2 px, GT-visible points kept 0.60 -> 0.78; ~1.3-1.45x the time per
   frame);
3. occlusion tensor: per reference pixel, the forward-backward inconsistency of the residual flow
   (px) and the dissimilarity 1 - ZNCC of the reference and the aligned frame in a small window
   (invariant to gain and bias, i.e. to shading) give an occlusion probability;
   visibility = (1 - occlusion) x in-view; with ``support_radius`` > 0, a reference pixel
   whose neighbourhood (``support_radius`` px) is less than ``support_fraction`` visible is
   reported not visible (occlusion 1) too: a pixel that passes both checks among occluded
   neighbours has mostly been dragged there by an occluder or slid onto a neighbouring point of
   a surface turning away, its FB and ZNCC checks passing on the texture it slid to (rendered
   flag, 60 deg, amplitude 2, occluder: visible observations over 3 px off 9.6% -> 2.9%, the
   true visible ones kept within 3 px 62.4% -> 59.4%); only what is published changes, the
   subspace and the re-selection test see the unchecked visibility (off by default: through
   the reconstructor a wash, docs/methods.md); with ``fusion_gap_px`` > 0 (1 px, the default)
   a track whose published, fused position (step 4) lies further than that from the frame's
   own flow measurement is reported not visible: the subspace carries it where the image does
   not put it (the occluded cap at 60 deg: visible observations over 3 px off 16% -> 5.5%, 1.3%
   of the good ones lost; published visibility only, like the support check);
4. subspace step: the frame's coefficients are fitted to the measured flow by weighted, Huber-
   robust least squares with a temporal prior (the constant-velocity prediction); the output
   fuses data and subspace per pixel ``(w u + beta (s + o)) / (w + beta)``, where o is the
   pixel's last offset from the subspace, so occluded trajectories are carried by the subspace;
4b. affine Lucas-Kanade (``lk_radius`` > 0, off by default): each track the frame calls visible is
   refined against the reference: the (2r+1)^2 template around its reference position, warped
   by an affine map that starts at the track's position with the dense flow's local Jacobian,
   inverse compositional Gauss-Newton (``lk_iterations``) on the contrast-normalised images;
   kept where it moved less than ``LK_MAX_MOVE`` px and raised the template's ZNCC.  DIS's
   patches are translations refined by a variational step, so on a foreshortened or turning
   view its positions carry a sub-pixel bias that an affine template removes (rendered face /
   flag 256x192, 60 deg camera motion: median track error 0.38 / 0.22 -> 0.22 / 0.10 px,
   BENCHMARKS issue 12, session 32); only the published positions change, the subspace and
   the flow keep the fused data.  Off by default for its cost, ~4.5 us a track on 2 cores
   (320x240: +20-25 ms a frame; 640x480: +200 ms), against ~1% of end-to-end e3D;
5. chained check (``chain_check_px`` > 0, off by default): each track's position against its
   previous one moved by a frame-to-frame DIS flow (medium preset); where they differ by more
   than ``chain_check_px`` the track is reported not visible (occlusion 1) and the chain
   carries its chained position on, so a track drifting a little every frame is caught once
   the drift adds up.  The reference-based flow can drift off a surface seen edge-on and half
   occluded while its FB and ZNCC checks still pass on the surface's own texture (the occluded
   cap at 60 deg, amplitude 2: 5-20% of the tracks called visible 18-50 px off); the check
   takes the visible observations' mean error there 4.7 -> 0.5 px (BENCHMARKS, session 21);
6. windowed refinement: every ``refine_every`` frames the learned basis is re-estimated over the
   last ``window`` frames by weighted alternating least squares on a coarse grid, spatially
   regularised and warm-started (subspace.fit_basis).

``track_sequence`` runs the same tracker over a whole sequence, then re-fuses every frame with
a subspace fitted on a window centred on it (past and future frames; ``batch_rank`` images).
When the tracked area is lost for ``reselect_patience`` frames in a row (less than
``reselect_fraction`` of the reference in view, or less than ``collapse_fraction`` of the in-view
part still consistent: the flow quality collapsed), the current frame becomes the new reference.
The tracks still visible there are carried across with their ids: their sub-pixel positions in the
new reference become their reference positions, sampled bilinearly in the new reference->frame
flow from then on; only pixels of the new reference with no carried track within ``stride`` px
get new ids ``epoch * H * W + y * W + x``.  Outputs list carried tracks first, then new ones.
"""
from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, fields, replace
from typing import TypeVar

import cv2
import numpy as np

from .. import threads
from ..arrays import duplicates
from . import _refine_kernel
from .reference_flow import check_grey, reference_pixels
from .rules import PARAM_RULES, PRESETS, check_param
from .subspace import GridSampler, fit_basis, fit_coefficients


_T = TypeVar('_T')

LK_MAX_MOVE = 3.0   # px: an affine Lucas-Kanade refinement moving a track further is dropped
_LK_POOL: tuple[int, ThreadPoolExecutor] | None = None


def _lk_threads() -> int:
    """Threads of the Lucas-Kanade refinement: NUMBA_NUM_THREADS (the fleet's workers set 1),
    else the CPUs this process may use."""
    n = os.environ.get('NUMBA_NUM_THREADS', '')
    if n.isdigit():
        return max(1, int(n))
    affinity = getattr(os, 'sched_getaffinity', None)       # Linux; elsewhere every CPU
    return max(1, len(affinity(0)) if affinity else os.cpu_count() or 1)


def _lk_pool() -> ThreadPoolExecutor:
    """This process's thread pool of the refinement (made in the process that uses it: a
    pool's threads do not survive a fork)."""
    global _LK_POOL
    if _LK_POOL is None or _LK_POOL[0] != os.getpid():
        _LK_POOL = (os.getpid(), ThreadPoolExecutor(_lk_threads(), 'mfof-lk'))
    return _LK_POOL[1]


@dataclass(frozen=True)
class MFOFConfig:
    preset: str = 'medium'          # OpenCV DIS preset of the data step
    recapture_finest_scale: int = -1  # DIS's finest pyramid level of the recapture pass;
    #                                 -1: the preset's own below 640 px on the long side, one
    #                                 level coarser per doubling from there
    rank: int = 8                   # learned trajectory-basis images (plus 6 polynomial ones)
    window: int = 20                # frames in the sliding refinement window
    refine_every: int = 5           # re-estimate the learned basis every N frames
    spatial_sigma: float = 2.0      # px, smoothing of the learned basis images (0: none)
    subspace_weight: float = 0.3    # beta: pull of the subspace on visible pixels
    fb_threshold: float = 2.0       # px, forward-backward error at occlusion probability 1/2
    ncc_threshold: float = 0.5      # 1 - ZNCC (reference vs aligned frame) at probability 1/2
    huber_px: float = 2.0           # robust fit of the frame coefficients
    outlier_px: float = 3.0         # data further than this from the subspace loses weight
    temporal_weight: float = 0.05   # pull of the coefficients towards the prediction
    batch_rank: int = 4             # learned images in the two-sided batch pass
    backward: bool = True           # compute the frame->reference flow for the FB check
    backward_preset: str = 'fast'   # DIS preset of the backward flow (only checks consistency)
    reselect_fraction: float = 0.35  # new reference when less of the mask stays in view ...
    collapse_fraction: float = 0.1  # ... or less of the in-view part is consistent ...
    reselect_patience: int = 3      # ... for this many frames in a row
    stride: int = 2                 # output every stride-th mask pixel as a track
    mask: str = 'texture'           # 'texture' (pixels with local contrast) or 'full'
    min_std: float = 4.0            # texture mask threshold
    recapture_margin: float = 0.07  # 1 - ZNCC gain for the coarse-to-fine pass to win (0: off)
    predict_offset: bool = True     # the prediction keeps each pixel's offset from the subspace
    chain_check_px: float = 0.0     # px: not visible where the frame-to-frame chain disagrees
    support_radius: int = 0         # px: the neighbourhood of the visibility support (0: off)
    support_fraction: float = 0.7   # not visible where less of the neighbourhood is visible
    lk_radius: int = 0              # px: affine Lucas-Kanade template half-size (0: off)
    lk_iterations: int = 2          # its inverse compositional Gauss-Newton iterations
    fusion_gap_px: float = 1.0      # px: not visible where the fused position is this far
    #                                 from the frame's flow measurement (0: off)

    def validate(self) -> None:
        """ValueError naming the first field that ``rules.PARAM_RULES`` rejects (the tracker
        node's parameters are checked by the same rules)."""
        for f in fields(self):
            if f.name in PARAM_RULES:
                check_param(f.name, getattr(self, f.name))


@dataclass(frozen=True)
class MFOFFrame:
    """One frame's output: ``uv`` (P, 2) track positions, ``visibility`` (P,) in [0, 1],
    ``occlusion`` (P,) occlusion probability (the frame's slice of the occlusion tensor),
    ``flow`` (H, W, 2) fused reference->frame flow, ``ids`` (P,) track ids (carried tracks
    first, then the current reference's own), ``reselected`` when this frame became a new
    reference (its tracks are then those carried across plus the new reference's own)."""

    index: int
    uv: np.ndarray
    visibility: np.ndarray
    occlusion: np.ndarray
    flow: np.ndarray
    ids: np.ndarray
    reselected: bool = False


AUTO_SCALE_SIDE = 640     # px: the long side from which the auto level (-1) is coarser


def dis_finest_scale(finest_scale: int, preset_finest: int, shape: tuple[int, int]) -> int:
    """DIS's finest pyramid level for an image of ``shape``: ``finest_scale`` where >= 0,
    else (-1, auto) the preset's ``preset_finest`` plus one level per doubling of the long side
    from ``AUTO_SCALE_SIDE`` (320x240: the preset's; 640x480: one coarser).  The medium
    preset's level 1 is a 320x240 image's flow at 160x120 px; at 640x480 it cost 10.5 ms a call
    against 2.8 ms at level 2: the recapture pass there at level 2 leaves the tracks' error
    and the pipeline's e3D as they were (BENCHMARKS, issue 17, session 44)."""
    if finest_scale >= 0:
        return int(finest_scale)
    side = max(shape)
    extra = int(np.floor(np.log2(side / (AUTO_SCALE_SIDE / 2)))) if side >= AUTO_SCALE_SIDE else 0
    return preset_finest + extra


def contrast_normalise(grey: np.ndarray, sigma: float = 4.0, floor: float = 3.0
                       ) -> np.ndarray:
    """Local zero-mean, unit-deviation intensities (Gaussian window ``sigma``) as uint8 around
    128: invariant to smooth gain and bias (shading); ``floor`` keeps flat areas flat."""
    g = grey.astype(np.float32)
    hp = g - cv2.GaussianBlur(g, (0, 0), sigma)
    sd = cv2.sqrt(cv2.GaussianBlur(hp * hp, (0, 0), sigma) + floor * floor)
    return np.clip(hp / sd * 48.0 + 128.0, 0, 255).astype(np.uint8)


def local_stats(a: np.ndarray, sigma: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Local mean and variance of a float32 image in a Gaussian window ``sigma``."""
    m = cv2.GaussianBlur(a, (0, 0), sigma)
    return m, np.maximum(cv2.GaussianBlur(a * a, (0, 0), sigma) - m * m, 0.0)


def local_zncc(a: np.ndarray, b: np.ndarray, sigma: float = 2.0, eps: float = 4.0,
               a_stats: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Zero-mean normalised cross-correlation of two float32 images in a Gaussian window: 1 for
    images equal up to gain and bias; ``eps`` (intensity variance) makes two flat patches agree
    and a flat patch disagree with a textured one.  ``a_stats``: ``local_stats(a, sigma)``."""
    ma, va = a_stats if a_stats is not None else local_stats(a, sigma)
    mb, vb = local_stats(b, sigma)
    cov = cv2.GaussianBlur(a * b, (0, 0), sigma) - ma * mb
    return (cov + eps) / np.sqrt((va + eps) * (vb + eps))


def visible_support(visible: np.ndarray, mask: np.ndarray, radius: int) -> np.ndarray:
    """Per pixel, the share (H, W) of the ``mask`` pixels within ``radius`` px (a square
    window, clipped at the image border) that are ``visible`` (both bool (H, W)); 0 where the
    window holds no mask pixel."""
    k = 2 * radius + 1

    def count(a: np.ndarray) -> np.ndarray:
        return cv2.boxFilter((a & mask).astype(np.float32), -1, (k, k), normalize=False,
                             borderType=cv2.BORDER_CONSTANT)
    return count(visible) / np.maximum(count(mask), 1.0)


def sample_bilinear(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """``img`` (H, W[, C]) float32 at sub-pixel positions xy (P, 2) (border replicated)."""
    xy = np.ascontiguousarray(xy, np.float32).reshape(1, -1, 2)
    out = cv2.remap(img, xy[..., 0], xy[..., 1], cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(xy.shape[1], *img.shape[2:])


def _remap(img: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    return cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _interleave(planes: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(2, H*W) float32 planes (rows contiguous) -> (H, W, 2) contiguous flow (cv2.merge: the
    same values as numpy's transposed copy at ~1/10 of its time)."""
    h, w = shape
    return cv2.merge([planes[0].reshape(h, w), planes[1].reshape(h, w)])


def _warp(img: np.ndarray, gx: np.ndarray, gy: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """``img`` sampled at x + flow(x) (bilinear, border replicated)."""
    return _remap(img, gx + flow[..., 0], gy + flow[..., 1])


class LKReference:
    """A contrast-normalised reference frame (uint8 (H, W), ``contrast_normalise``) prepared
    for the affine Lucas-Kanade refinement of tracks against it (module notes, step 4b)."""

    def __init__(self, ref_n: np.ndarray) -> None:
        self.image = np.asarray(ref_n, np.float32)
        self.gx = cv2.Sobel(self.image, cv2.CV_32F, 1, 0, ksize=3) / 8.0
        self.gy = cv2.Sobel(self.image, cv2.CV_32F, 0, 1, ksize=3) / 8.0

    def refine(self, grey_n: np.ndarray, flow: np.ndarray, reference_xy: np.ndarray,
               uv: np.ndarray, which: np.ndarray, radius: int, iterations: int
               ) -> np.ndarray:
        """Positions ``uv`` (P, 2) with those selected by ``which`` (P,) bool refined in the
        contrast-normalised frame ``grey_n`` against their reference positions
        ``reference_xy`` (P, 2); ``flow`` (H, W, 2): the dense reference->frame flow, whose
        local affine map starts each refinement.  A refinement is kept where it moved the
        track less than ``LK_MAX_MOVE`` px, stayed in the frame and raised the template's
        correlation."""
        j = np.flatnonzero(which)
        if j.size == 0:
            return uv
        p = uv[j].astype(np.float64)
        out = np.empty_like(p)
        zncc = np.empty(j.size)
        args = (self.image, self.gx, self.gy, np.asarray(grey_n, np.float32),
                np.ascontiguousarray(flow, np.float32))
        p0 = np.ascontiguousarray(reference_xy[j], np.float64)
        parts = np.array_split(np.arange(j.size), _lk_threads() if j.size >= 1024 else 1)

        def run(k: np.ndarray) -> None:
            a, b = int(k[0]), int(k[-1]) + 1
            _refine_kernel.refine(*args, p0[a:b], p[a:b], int(radius), int(iterations),
                                  LK_MAX_MOVE, out[a:b], zncc[a:b])
        if len(parts) == 1:
            run(parts[0])
        else:
            list(_lk_pool().map(run, parts))
        uv = uv.copy()
        uv[j] = out
        return uv


@dataclass
class _Window:
    data: deque = field(default_factory=deque)      # (2, P) measured displacement
    weight: deque = field(default_factory=deque)    # (P,) data confidence
    model: deque = field(default_factory=deque)     # (2, P) fused output


class MFOFTracker:
    """Streaming MFOF tracker; ``step(grey)`` per frame, the first frame is the reference."""

    def __init__(self, config: MFOFConfig | None = None) -> None:
        self.config = config or MFOFConfig()
        self.config.validate()
        self._fwd = cv2.DISOpticalFlow_create(PRESETS[self.config.preset])
        self._bwd = cv2.DISOpticalFlow_create(PRESETS[self.config.backward_preset])
        # the recapture pass has its own instance: DIS carries state from one call to the next
        self._rec = cv2.DISOpticalFlow_create(PRESETS[self.config.preset])
        self._preset_finest = self._rec.getFinestScale()
        self._chain_dis = cv2.DISOpticalFlow_create(PRESETS['medium'])
        # the recapture pass' thread (_beside), made on first use
        self._pool: tuple[int, ThreadPoolExecutor] | None = None
        self.chain_rejected = 0     # tracks the chained check reported not visible, last frame
        self.epoch = -1
        self.keep_history = False   # track_sequence: record (d, w) of the first reference
        self.history: list[tuple[np.ndarray, ...]] = []
        # bool (H, W), the surface's segmentation: a new reference (the first frame, a
        # re-selection) tracks only its pixels; None: the whole mask
        self.roi: np.ndarray | None = None
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        self._ref: np.ndarray | None = None
        self._index = -1
        self._since_refine = 0
        self._low_visible = 0
        self._win = _Window()
        self._learned = np.zeros((0, 0), np.float32)
        self._basis = self._learned
        self._q: list[np.ndarray] = []
        self._flow: np.ndarray | None = None
        self._chain: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    @property
    def reference(self) -> np.ndarray | None:
        return self._ref

    @property
    def basis(self) -> np.ndarray:
        """Current basis images (M + R, H*W): polynomial block, then the learned images."""
        return self._basis

    def _set_learned(self, coarse: np.ndarray) -> None:
        """The learned images from their coarse-grid form ``coarse`` (R, h*w), upsampled into
        the basis (M + R, H*W) after the polynomial block.  The basis is one buffer a reference,
        rewritten in place (nothing outside the tracker holds it): a new 17 MB array at each
        refinement at 640x480 page-faulted in at 28 ms."""
        M, R = self._poly.shape[0], coarse.shape[0]
        buf = self._basis_buf
        if buf is None or buf.shape[0] != M + R:
            buf = np.empty((M + R, self._poly.shape[1]), np.float32)
            buf[:M] = self._poly
            self._basis_buf = buf
        self._grid.up(coarse, out=buf[M:])
        self._learned, self._basis = buf[M:], buf

    def _set_reference(self, grey: np.ndarray,
                       carried: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Make ``grey`` the reference; ``carried`` (ids (Pc,), positions (Pc, 2) in ``grey``)
        are tracks of the previous reference that continue with their ids."""
        c = self.config
        h, w = grey.shape
        self.epoch += 1
        self._ref = grey
        self._rec.setFinestScale(dis_finest_scale(c.recapture_finest_scale,
                                                  self._preset_finest, (h, w)))
        self._ref_n = contrast_normalise(grey)
        self._ref_f = grey.astype(np.float32)
        self._ref_stats = local_stats(self._ref_f)
        self._lk = LKReference(self._ref_n) if c.lk_radius > 0 else None
        self._shape = (h, w)
        self._gx, self._gy = np.meshgrid(np.arange(w, dtype=np.float32),
                                         np.arange(h, dtype=np.float32))
        self._grid = GridSampler((h, w))
        self._poly = self._grid.fixed
        self._basis_buf: np.ndarray | None = None
        self._set_learned(np.zeros((0, self._grid.small[0] * self._grid.small[1]), np.float32))
        if self.epoch == 0:
            self.history_grid = self._grid
        mask, lin, xy = reference_pixels(grey, c.mask, c.stride, c.min_std, self.roi)
        if carried is None:
            carried = (np.zeros(0, np.uint32), np.zeros((0, 2), np.float32))
        self._carry_ids = np.asarray(carried[0], np.uint32)
        self._carry_xy = np.asarray(carried[1], np.float32).reshape(-1, 2)
        if self._carry_ids.size:
            # new tracks only where no carried track lies within ``stride`` px
            free = np.full((h, w), 255, np.uint8)
            cx = np.clip(np.rint(self._carry_xy[:, 0]).astype(np.intp), 0, w - 1)
            cy = np.clip(np.rint(self._carry_xy[:, 1]).astype(np.intp), 0, h - 1)
            free[cy, cx] = 0
            dist = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
            keep = dist.ravel()[lin] >= c.stride
            lin, xy = lin[keep], xy[keep]
        self._lin, self._xy = lin, xy
        own = ((self.epoch * h * w + lin) % 2 ** 32).astype(np.uint32)
        self.ids = np.concatenate([self._carry_ids, own])
        self._mask, self._mask_lin = mask, np.flatnonzero(mask)
        # a fixed strided sample of at most ~20000 mask pixels for the per-frame coefficient
        # fit (rounding the stride down fitted up to 80000: all of a 320x240 mask)
        step = max(1, int(np.ceil(np.sqrt(self._mask_lin.size / 20000))))
        self._sample = np.flatnonzero((mask & (self._gx % step == 0) & (self._gy % step == 0))
                                      .ravel())
        if self.epoch == 0:
            self.first_lin, self.first_xy, self.history_sample = self._lin, self._xy, self._sample
        self._win = _Window()
        self._q = []
        self._last_models: list[np.ndarray] = []
        self._coarse = np.zeros((0, 0), np.float32)
        self._since_refine = 0
        self._low_visible = 0
        self._flow = np.zeros((h, w, 2), np.float32)
        self._offset = np.zeros((2, h * w), np.float32)

    @property
    def reference_xy(self) -> np.ndarray:
        """(P, 2) sub-pixel positions of ``ids`` in the current reference frame (where their
        colour is, for example)."""
        return np.concatenate([self._carry_xy, self._xy])

    # ------------------------------------------------------------------ per frame
    def _predicted_q(self) -> np.ndarray | None:
        if len(self._q) < 2:
            return None
        return 2 * self._q[-1] - self._q[-2]

    def _predict(self) -> tuple[np.ndarray, np.ndarray]:
        """The prediction (H, W, 2) of the residual data step and the seed of the recapture
        pass: the subspace extrapolated (constant velocity of the coefficients), plus
        (``predict_offset``) every pixel's last offset from the subspace for the data step, so
        a pixel tracked where the subspace does not reach (a fold deforming faster than the
        learned images follow) is predicted at its own last position moved by the subspace's
        velocity.  The recapture pass keeps the smooth subspace-only seed: a pixel whose offset
        went wrong is found again from it."""
        assert self._flow is not None
        q = self._predicted_q()
        if q is None:
            return self._flow, self._flow
        s = q @ self.basis
        sub = _interleave(s, self._shape)
        if not self.config.predict_offset:
            return sub, sub
        return _interleave(s + self._offset, self._shape), sub

    def dissimilarity(self, aligned: np.ndarray) -> np.ndarray:
        """1 - local ZNCC (H, W) of the reference and the frame ``aligned`` onto it."""
        return 1.0 - local_zncc(self._ref_f, aligned, a_stats=self._ref_stats)

    def occlusion(self, aligned: np.ndarray | None, flow: np.ndarray, fb_sq: np.ndarray | None,
                  dissimilar: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Occlusion probability (H, W) and in-view mask (H, W) of reference pixels, from the
        frame ``aligned`` onto the reference (float32 (H, W)) by the reference->frame ``flow``
        and the squared forward-backward error ``fb_sq`` (px^2, (H, W); None: no FB check);
        ``dissimilar``: ``dissimilarity(aligned)`` when already computed (aligned may then be
        None)."""
        c = self.config
        h, w = self._shape
        x, y = self._gx + flow[..., 0], self._gy + flow[..., 1]
        inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
        if dissimilar is None:
            if aligned is None:
                raise ValueError('occlusion: pass the aligned frame or its dissimilarity')
            dissimilar = self.dissimilarity(aligned)
        score = (dissimilar / c.ncc_threshold) ** 2
        if fb_sq is not None:
            score = score + fb_sq / c.fb_threshold ** 2
        score = score * score       # sharp: ~0 for inliers, 1/2 at the thresholds
        occ = score / (1.0 + score)
        return occ.astype(np.float32), inside

    def step(self, grey: np.ndarray) -> MFOFFrame:
        """Track one grey uint8 frame (H, W)."""
        grey = check_grey(grey, self._ref)
        frame = self._step(grey)
        if self.config.chain_check_px > 0:
            frame = self._chain_check(contrast_normalise(grey), frame)
        return frame

    def _chain_check(self, grey_n: np.ndarray, frame: MFOFFrame) -> MFOFFrame:
        """``frame`` with the tracks whose position disagrees with the frame-to-frame chain by
        more than ``chain_check_px`` reported not visible (see the module notes, step 5)."""
        ids, uv = frame.ids, frame.uv.astype(np.float64)
        anchor = uv.copy()
        self.chain_rejected = 0
        if self._chain is not None and self._chain[0].shape == grey_n.shape:
            prev_n, prev_ids, prev_xy = self._chain
            flow = self._chain_dis.calc(prev_n, grey_n, None)
            _, ia, ib = np.intersect1d(prev_ids, ids, assume_unique=True, return_indices=True)
            chained = prev_xy[ia] + sample_bilinear(flow, prev_xy[ia])
            lost = np.linalg.norm(chained - uv[ib], axis=1) > self.config.chain_check_px
            if lost.any():
                j = ib[lost]
                vis, occ = frame.visibility.copy(), frame.occlusion.copy()
                vis[j], occ[j] = 0.0, 1.0
                anchor[j] = chained[lost]
                frame = replace(frame, visibility=vis, occlusion=occ)
                self.chain_rejected = int(lost.sum())
        self._chain = (grey_n, ids.copy(), anchor)
        return frame

    def _step(self, grey: np.ndarray) -> MFOFFrame:
        self._index += 1
        if self._ref is None:
            return self._new_reference(grey)
        c = self.config
        h, w = self._shape
        gx, gy = self._gx, self._gy
        pred, seed = self._predict()
        # data step on the frame pre-warped by the prediction: DIS measures only the residual
        # r (small, locally undistorted), so u(x) = r(x) + pred(x + r(x))
        grey_n = contrast_normalise(grey)
        grey_f = grey.astype(np.float32)
        # the recapture pass depends only on the frame and the seed: it runs in a second
        # thread while the data step and its backward check run here (OpenCV's DIS releases
        # the GIL; each call is the same as in sequence, so the tracks are too), unless this
        # process is held to one thread (core.threads.set_workers: a fleet worker)
        recapture = self._beside(self._recapture_flow, grey_n, grey_f, seed) \
            if c.recapture_margin > 0 and threads.WORKERS > 1 else None
        warped = _warp(grey_n, gx, gy, pred)
        r = self._fwd.calc(self._ref_n, warped, None)
        mx, my = gx + r[..., 0], gy + r[..., 1]
        u = r + _remap(pred, mx, my)
        fb_sq = None
        if c.backward:   # FB check of the residual flow: back(x + r(x)) + r(x) ~ 0
            back = self._bwd.calc(warped, self._ref_n, np.ascontiguousarray(-r))
            fb = _remap(back, mx, my) + r
            fb_sq = fb[..., 0] ** 2 + fb[..., 1] ** 2
        dis = self.dissimilarity(_warp(grey_f, gx, gy, u))
        if c.recapture_margin > 0:
            u2, dis2 = recapture.result() if recapture is not None else \
                self._recapture_flow(grey_n, grey_f, seed)
            u, dis, fb_sq = self._recapture(u2, dis2, u, dis, fb_sq)
        occ, inside = self.occlusion(None, u, fb_sq, dis)
        weight = ((1.0 - occ) * inside).ravel()
        w_data = weight
        d = np.ascontiguousarray(u.reshape(-1, 2).T)     # (2, H*W)
        q = fit_coefficients(self.basis, d, weight, c.huber_px, sample=self._sample,
                             prior=self._predicted_q(), prior_weight=c.temporal_weight)
        s = q @ self.basis
        prior = s + self._offset
        if self._learned.shape[0] and c.outlier_px > 0:
            weight = weight / (1.0 + ((d - prior) ** 2).sum(0) / c.outlier_px ** 2)
        fused = (weight * d + c.subspace_weight * prior) / (weight + c.subspace_weight + 1e-12)
        self._offset = fused - s
        self._q.append(q)
        if len(self._q) > 3:
            self._q.pop(0)
        self._push(d, weight, fused)
        if self.keep_history and self.epoch == 0:
            win = self._win
            self.history.append((d, w_data, win.data[-1], win.weight[-1]))
        flow = _interleave(fused, (h, w))
        self._flow = flow
        # visibility: the fused position must be in view too
        fx, fy = gx + flow[..., 0], gy + flow[..., 1]
        in_view = ((fx >= 0) & (fx <= w - 1) & (fy >= 0) & (fy <= h - 1)).ravel()
        occ = occ.ravel()
        vis = (1.0 - occ) * in_view
        vis_out, occ_out = self._supported(vis, occ) if c.support_radius > 0 else (vis, occ)
        if c.fusion_gap_px > 0:     # the published position is not where the data puts it
            gap = (fused[0] - d[0]) ** 2 + (fused[1] - d[1]) ** 2 > c.fusion_gap_px ** 2
            vis_out, occ_out = np.where(gap, 0.0, vis_out), np.where(gap, 1.0, occ_out)
        uv, vis_t, occ_t = self._tracks(flow, fused, vis_out, occ_out)
        if c.lk_radius > 0:
            uv = self.lk_refine(grey_n, flow, uv, vis_t > 0.5)
        # the tracked area is lost when little of the reference stays in view, or the flow
        # quality collapsed (almost nothing in view is consistent); occlusion alone is no cause
        m_in = in_view[self._mask_lin]
        in_frac = float(m_in.mean())
        ok_frac = float((vis[self._mask_lin] > 0.5).sum() / max(int(m_in.sum()), 1))
        lost = in_frac < c.reselect_fraction or ok_frac < c.collapse_fraction
        self._low_visible = self._low_visible + 1 if lost else 0
        if self._low_visible >= c.reselect_patience:
            return self._reselect(grey, uv, vis_t, occ_t)
        return MFOFFrame(self._index, uv, vis_t, occ_t, flow, self.ids)

    def lk_refine(self, grey_n: np.ndarray, flow: np.ndarray, uv: np.ndarray,
                  which: np.ndarray) -> np.ndarray:
        """``LKReference.refine`` of the current tracks against the current reference."""
        assert self._lk is not None
        c = self.config
        return self._lk.refine(grey_n, flow, self.reference_xy, uv, which, c.lk_radius,
                               c.lk_iterations)

    def _supported(self, vis: np.ndarray, occ: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Visibility and occlusion (H*W,) with the reference pixels whose neighbourhood is
        less than ``support_fraction`` visible (``visible_support``) reported not visible
        (occlusion 1): a pixel judged visible among occluded neighbours has mostly been dragged
        there (module notes, step 3)."""
        h, w = self._shape
        ok = np.zeros(h * w, bool)
        ok[self._mask_lin] = vis[self._mask_lin] > 0.5
        share = visible_support(ok.reshape(h, w), self._mask, self.config.support_radius)
        weak = share.ravel() < self.config.support_fraction
        return np.where(weak, 0.0, vis), np.where(weak, 1.0, occ)

    def _beside(self, fn: Callable[..., _T], *args: object) -> Future[_T]:
        """``fn(*args)`` started in this tracker's second thread (made in the process that
        uses it: a pool's threads do not survive a fork)."""
        if self._pool is None or self._pool[0] != os.getpid():
            self._pool = (os.getpid(), ThreadPoolExecutor(1, 'mfof-recapture'))
        return self._pool[1].submit(fn, *args)

    def _recapture_flow(self, grey_n: np.ndarray, grey_f: np.ndarray, pred: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
        """The coarse-to-fine pass: DIS reference -> frame (H, W, 2) seeded by the prediction,
        and its dissimilarity (H, W)."""
        u2 = self._rec.calc(self._ref_n, grey_n, pred.copy())
        return u2, self.dissimilarity(_warp(grey_f, self._gx, self._gy, u2))

    def _recapture(self, u2: np.ndarray, dis2: np.ndarray, u: np.ndarray, dis: np.ndarray,
                   fb_sq: np.ndarray | None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Where the coarse-to-fine flow ``u2`` matches better (smoothed dissimilarity lower by
        ``recapture_margin``) it replaces the flow ``u`` and dissimilarity ``dis``; the FB
        error is unknown there (set to 0)."""
        gain = cv2.GaussianBlur((dis - dis2).astype(np.float32), (0, 0), 3.0)
        better = gain > self.config.recapture_margin
        if not better.any():
            return u, dis, fb_sq
        np.copyto(u, u2, where=better[..., None])     # u, dis, fb_sq: this frame's own arrays
        np.copyto(dis, dis2, where=better)
        if fb_sq is not None:
            fb_sq[better] = 0.0
        return u, dis, fb_sq

    def _tracks(self, flow: np.ndarray, fused: np.ndarray, vis: np.ndarray, occ: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions (P, 2), visibility and occlusion (P,) of carried then own tracks."""
        uv = self._xy + fused[:, self._lin].T
        vis_t, occ_t = vis[self._lin], occ[self._lin]
        if self._carry_ids.size:
            h, w = self._shape
            cxy = self._carry_xy
            cuv = cxy + sample_bilinear(flow, cxy)
            c_in = ((cuv[:, 0] >= 0) & (cuv[:, 0] <= w - 1) & (cuv[:, 1] >= 0)
                    & (cuv[:, 1] <= h - 1))
            c_occ = np.clip(sample_bilinear(occ.reshape(h, w), cxy), 0.0, 1.0)
            uv = np.concatenate([cuv, uv])
            vis_t = np.concatenate([((1.0 - c_occ) * c_in).astype(np.float32), vis_t])
            occ_t = np.concatenate([c_occ, occ_t])
        return uv.astype(np.float32), vis_t.astype(np.float32), occ_t.astype(np.float32)

    def _reselect(self, grey: np.ndarray, uv: np.ndarray, vis: np.ndarray, occ: np.ndarray
                  ) -> MFOFFrame:
        """This frame becomes the new reference; tracks visible in it (> 1/2) carry over."""
        keep = vis > 0.5
        self.reselect(grey, self.ids[keep], uv[keep])
        n = int(keep.sum())
        P = self.ids.size
        vis_new = np.ones(P, np.float32)
        occ_new = np.zeros(P, np.float32)
        vis_new[:n], occ_new[:n] = vis[keep], occ[keep]
        assert self._flow is not None
        return MFOFFrame(self._index, self.reference_xy, vis_new, occ_new, self._flow,
                         self.ids, True)

    def reselect(self, grey: np.ndarray, ids: np.ndarray | None = None,
                 xy: np.ndarray | None = None) -> None:
        """Make ``grey`` (uint8 (H, W), the current frame) the new reference, carrying the
        tracks ``ids`` at their positions ``xy`` (P, 2) in it (by default none; ids must be
        unique current ids); the learned subspace restarts."""
        grey = check_grey(grey, self._ref)
        if ids is None or xy is None:
            ids, xy = np.zeros(0, np.uint32), np.zeros((0, 2), np.float32)
        ids = np.asarray(ids, np.uint32)
        xy = np.asarray(xy, np.float32).reshape(-1, 2)
        if ids.size != xy.shape[0]:
            raise ValueError(f'reselect: {ids.size} ids but {xy.shape[0]} positions')
        if duplicates(ids) or not np.isin(ids, self.ids).all():
            raise ValueError('reselect: ids must be unique current track ids')
        h, w = grey.shape
        if xy.size and not ((xy >= 0).all() and (xy[:, 0] <= w - 1).all()
                            and (xy[:, 1] <= h - 1).all()):
            raise ValueError('reselect: carried positions must lie in the frame')
        self._set_reference(grey, (ids, xy))

    def _new_reference(self, grey: np.ndarray) -> MFOFFrame:
        self._set_reference(grey)
        P = self.ids.size
        assert self._flow is not None
        return MFOFFrame(self._index, self.reference_xy, np.ones(P, np.float32),
                         np.zeros(P, np.float32), self._flow, self.ids, self.epoch > 0)

    def _push(self, d: np.ndarray, weight: np.ndarray, fused: np.ndarray) -> None:
        c = self.config
        win = self._win
        g = self._grid
        win.data.append(g.down(d.astype(np.float32, copy=False)))
        win.weight.append(g.down(weight[None].astype(np.float32, copy=False))[0])
        win.model.append(g.down(fused.astype(np.float32, copy=False)))
        self._last_models = (self._last_models + [fused])[-2:]
        while len(win.data) > c.window:
            win.data.popleft()
            win.weight.popleft()
            win.model.popleft()
        self._since_refine += 1
        n = len(win.data)
        ready = n >= min(c.window, max(3, (c.rank + 1) // 2 + 1))
        if c.rank > 0 and ready and (self._learned.size == 0 or
                                    self._since_refine >= c.refine_every):
            self.refine()

    def refine(self) -> None:
        """Re-estimate the learned basis over the window (weighted ALS, warm-started)."""
        c = self.config
        win = self._win
        if not win.data:
            return
        D = np.concatenate(list(win.data))
        Wt = np.stack(list(win.weight))
        model = np.concatenate(list(win.model))
        g = self._grid
        warm = self._coarse if self._learned.shape[0] == c.rank else None
        self._coarse = fit_basis(D, Wt, g.fixed_small, c.rank, g.small,
                                 c.spatial_sigma / g.step, iterations=2 if warm is not None else 4,
                                 initial=model, start=warm)
        self._set_learned(self._coarse)
        self._since_refine = 0
        # re-express the last frames' coefficients in the new basis (for the prediction)
        self._q = [fit_coefficients(self.basis, m, np.ones(m.shape[1], np.float32),
                                    iterations=0, sample=self._sample)
                   for m in self._last_models]
        # the per-pixel offset from the subspace, re-expressed in the new basis
        self._offset = self._last_models[-1] - self._q[-1] @ self.basis


@dataclass
class TrackResult:
    """A whole sequence: ``W`` (2F x P), ``V`` (F x P), ``O`` (F x P) occlusion tensor,
    ``ids`` (P,), and the frames at which a new reference was selected."""

    W: np.ndarray
    V: np.ndarray
    O: np.ndarray   # noqa: E741 -- the occlusion tensor, named as W and V
    ids: np.ndarray
    reselections: list[int]
    seconds: float


def track_sequence(frames, config: MFOFConfig | None = None, smooth: bool = True,
                   rois=None) -> TrackResult:
    """Track a sequence of grey uint8 frames: the streaming tracker, then (``smooth``) a
    two-sided pass that re-fits the subspace on a window centred on each frame (past and
    future frames) and re-fuses every frame's data with it.  ``rois``: per frame the bool
    (H, W) region a new reference selected there may track (``MFOFTracker.roi``), or None.

    Tracks are returned for the first reference's ids (P fixed): after a re-selection those
    carried across continue; the others keep their last position and are marked invisible."""
    import time
    t0 = time.perf_counter()
    cfg = config or MFOFConfig()
    tracker = MFOFTracker(cfg)
    tracker.keep_history = smooth
    frames = list(frames)
    if rois is not None and len(rois) != len(frames):
        raise ValueError(f'rois: {len(rois)} regions for {len(frames)} frames')
    out = []
    for k, f in enumerate(frames):
        tracker.roi = None if rois is None else rois[k]
        out.append(tracker.step(np.asarray(f)))
    ids = out[0].ids
    F, P = len(out), ids.size
    W = np.zeros((2 * F, P), np.float32)
    V = np.zeros((F, P), np.float32)
    O = np.ones((F, P), np.float32)   # noqa: E741
    reselections = [fr.index for fr in out[1:] if fr.reselected]
    last = reselections[0] if reselections else F
    order = np.argsort(ids)
    uv = out[0].uv.copy()
    for f, fr in enumerate(out):
        if f < last:
            uv, V[f], O[f] = fr.uv, fr.visibility, fr.occlusion
        else:   # first-reference ids still carried in this frame
            pos = np.clip(np.searchsorted(ids, fr.ids, sorter=order), 0, P - 1)
            j = order[pos]
            hit = ids[j] == fr.ids
            uv = uv.copy()
            uv[j[hit]] = fr.uv[hit]
            V[f, j[hit]], O[f, j[hit]] = fr.visibility[hit], fr.occlusion[hit]
        W[2 * f], W[2 * f + 1] = uv[:, 0], uv[:, 1]
    if smooth and last > 3 and cfg.rank > 0:
        hist = tracker.history[:last - 1]       # frames 1..last-1 of the first reference
        fused = _two_sided(tracker, hist)
        lin, xy = tracker.first_lin, tracker.first_xy
        lk = LKReference(contrast_normalise(np.asarray(frames[0]))) if cfg.lk_radius > 0 else None
        for k, f in enumerate(range(1, last)):
            pos = xy + fused[k][:, lin].T
            if lk is not None:
                pos = lk.refine(contrast_normalise(np.asarray(frames[f])),
                                _interleave(fused[k], tracker.history_grid.shape), xy, pos,
                                V[f] > 0.5, cfg.lk_radius, cfg.lk_iterations)
            W[2 * f], W[2 * f + 1] = pos[:, 0], pos[:, 1]
    return TrackResult(W, V, O, ids, reselections, time.perf_counter() - t0)


def _two_sided(tracker: MFOFTracker, hist: list) -> list[np.ndarray]:
    """Re-fuse each recorded frame (data d, weight w, coarse d, coarse w) with a subspace fitted
    on a window centred on it; the basis is re-fitted every ``refine_every`` frames."""
    c = tracker.config
    g = tracker.history_grid
    n = len(hist)
    half = c.window // 2
    out: list[np.ndarray] = []
    coarse = None
    B = None
    offset = np.zeros_like(hist[0][0])
    for k in range(n):
        if B is None or k % c.refine_every == 0:
            B_old = B
            a = max(0, min(k - half, n - c.window))
            b = min(n, a + c.window)
            D = np.concatenate([h[2] for h in hist[a:b]])
            Wt = np.stack([h[3] for h in hist[a:b]])
            coarse = fit_basis(D, Wt, g.fixed_small, c.batch_rank, g.small,
                               c.spatial_sigma / g.step,
                               iterations=2 if coarse is not None else 4, start=coarse)
            B = np.ascontiguousarray(np.concatenate([g.fixed, g.up(coarse)]))
            if B_old is not None:     # re-express the offsets in the new basis
                q = fit_coefficients(B, out[-1], np.ones(B.shape[1], np.float32),
                                     iterations=0, sample=tracker.history_sample)
                offset = out[-1] - q @ B
        d, w = hist[k][0], hist[k][1]
        q = fit_coefficients(B, d, w, c.huber_px, sample=tracker.history_sample)
        s = q @ B
        prior = s + offset
        if c.outlier_px > 0:
            w = w / (1.0 + ((d - prior) ** 2).sum(0) / c.outlier_px ** 2)
        fused = (w * d + c.subspace_weight * prior) / (w + c.subspace_weight + 1e-12)
        offset = fused - s
        out.append(fused)
    return out
