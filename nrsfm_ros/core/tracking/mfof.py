"""Multi-frame subspace optical flow (MFOF) tracking with an occlusion tensor.

Every pixel of a reference mask is tracked reference->frame (never chained frame to frame).
Per incoming frame (streaming, bounded latency):

1. prediction: the motion subspace extrapolates the per-frame coefficients (constant velocity),
   giving a dense flow that seeds the data step, so large motion and occluded regions start from
   the subspace's guess, not from the previous measurement;
2. data step: OpenCV DIS (preset by name) reference->frame, and frame->reference for the
   forward-backward check;
3. occlusion tensor: per reference pixel, the forward-backward inconsistency (px) and the
   illumination-robust warping residual (high-pass intensities) give an occlusion probability;
   visibility = (1 - occlusion) x in-view;
4. subspace step: the frame's coefficients are fitted to the measured flow by weighted, Huber-
   robust least squares with a temporal prior (the constant-velocity prediction); the output
   fuses data and subspace per pixel ``(w u + beta (s + o)) / (w + beta)``, where o is the
   pixel's last offset from the subspace, so occluded trajectories are carried by the subspace;
5. windowed refinement: every ``refine_every`` frames the learned basis is re-estimated over the
   last ``window`` frames by weighted alternating least squares on a coarse grid, spatially
   regularised and warm-started (subspace.fit_basis).

``track_sequence`` runs the same tracker over a whole sequence, then re-fuses every frame with
a subspace fitted on a window centred on it (past and future frames; ``batch_rank`` images).
When too little of the reference stays visible for ``reselect_patience`` frames, the next frame
becomes the new reference (track ids then change: ``epoch * H * W + y * W + x``).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np

from .reference_flow import PRESETS, check_grey, reference_pixels
from .subspace import GridSampler, fit_basis, fit_coefficients


@dataclass(frozen=True)
class MFOFConfig:
    preset: str = 'medium'          # OpenCV DIS preset of the data step
    rank: int = 8                   # learned trajectory-basis images (plus 6 polynomial ones)
    window: int = 20                # frames in the sliding refinement window
    refine_every: int = 5           # re-estimate the learned basis every N frames
    spatial_sigma: float = 2.0      # px, smoothing of the learned basis images (0: none)
    subspace_weight: float = 0.3    # beta: pull of the subspace on visible pixels
    fb_threshold: float = 2.0       # px, forward-backward error at occlusion probability 1/2
    residual_threshold: float = 14.0  # high-pass intensity residual at probability 1/2
    huber_px: float = 2.0           # robust fit of the frame coefficients
    outlier_px: float = 3.0         # data further than this from the subspace loses weight
    temporal_weight: float = 0.05   # pull of the coefficients towards the prediction
    batch_rank: int = 4             # learned images in the two-sided batch pass
    backward: bool = True           # compute the frame->reference flow for the FB check
    backward_preset: str = 'fast'   # DIS preset of the backward flow (only checks consistency)
    reselect_fraction: float = 0.35  # new reference when less of the mask stays visible ...
    reselect_patience: int = 3      # ... for this many frames in a row
    stride: int = 1                 # output every stride-th mask pixel as a track
    mask: str = 'full'              # 'full' or 'texture'
    min_std: float = 4.0            # texture mask threshold

    def validate(self) -> None:
        for name in ('preset', 'backward_preset'):
            if getattr(self, name) not in PRESETS:
                raise ValueError(f'{name}={getattr(self, name)!r}: expected one of '
                                 f'{sorted(PRESETS)}')
        if self.mask not in ('full', 'texture'):
            raise ValueError(f"mask={self.mask!r}: expected 'full' or 'texture'")
        for name in ('rank', 'batch_rank', 'refine_every', 'reselect_patience', 'stride'):
            if getattr(self, name) < (0 if 'rank' in name else 1):
                raise ValueError(f'{name}={getattr(self, name)}: too small')
        if self.window < 3:
            raise ValueError(f'window={self.window}: expected >= 3')
        if self.outlier_px < 0:
            raise ValueError(f'outlier_px={self.outlier_px}: expected >= 0 (0: off)')
        for name in ('fb_threshold', 'residual_threshold', 'huber_px'):
            if getattr(self, name) <= 0:
                raise ValueError(f'{name}={getattr(self, name)}: expected > 0')
        if self.subspace_weight < 0 or self.spatial_sigma < 0:
            raise ValueError('subspace_weight and spatial_sigma must be >= 0')
        if not 0 <= self.reselect_fraction < 1:
            raise ValueError(f'reselect_fraction={self.reselect_fraction}: expected [0, 1)')


@dataclass(frozen=True)
class MFOFFrame:
    """One frame's output: ``uv`` (P, 2) track positions, ``visibility`` (P,) in [0, 1],
    ``occlusion`` (P,) occlusion probability (the frame's slice of the occlusion tensor),
    ``flow`` (H, W, 2) fused reference->frame flow, ``ids`` (P,) track ids, ``reselected`` when
    this frame became a new reference."""

    index: int
    uv: np.ndarray
    visibility: np.ndarray
    occlusion: np.ndarray
    flow: np.ndarray
    ids: np.ndarray
    reselected: bool = False


def highpass(grey: np.ndarray, sigma: float = 3.0) -> np.ndarray:
    """Intensity minus its local mean: insensitive to smooth gain/bias changes."""
    g = grey.astype(np.float32)
    return g - cv2.GaussianBlur(g, (0, 0), sigma)


def _warp(img: np.ndarray, gx: np.ndarray, gy: np.ndarray, flow: np.ndarray) -> np.ndarray:
    return cv2.remap(img, gx + flow[..., 0], gy + flow[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


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
        self.epoch = -1
        self.keep_history = False   # track_sequence: record (d, w) of the first reference
        self.history: list[tuple[np.ndarray, ...]] = []
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

    @property
    def reference(self) -> np.ndarray | None:
        return self._ref

    @property
    def basis(self) -> np.ndarray:
        """Current basis images (M + R, H*W): polynomial block, then the learned images."""
        return self._basis

    def _set_learned(self, learned: np.ndarray) -> None:
        self._learned = learned
        self._basis = np.ascontiguousarray(np.concatenate([self._poly, learned]))

    def _set_reference(self, grey: np.ndarray) -> None:
        c = self.config
        h, w = grey.shape
        self.epoch += 1
        self._ref, self._ref_hp = grey, highpass(grey)
        self._shape = (h, w)
        self._gx, self._gy = np.meshgrid(np.arange(w, dtype=np.float32),
                                         np.arange(h, dtype=np.float32))
        self._grid = GridSampler((h, w))
        self._poly = self._grid.fixed
        self._set_learned(np.zeros((0, h * w), np.float32))
        if self.epoch == 0:
            self.history_grid = self._grid
        mask, self._lin, self._xy = reference_pixels(grey, c.mask, c.stride, c.min_std)
        self.ids = ((self.epoch * h * w + self._lin) % 2 ** 32).astype(np.uint32)
        self._mask_lin = np.flatnonzero(mask)
        # a fixed strided sample of mask pixels for the per-frame coefficient fit
        step = max(1, int(np.sqrt(self._mask_lin.size / 20000)))
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

    # ------------------------------------------------------------------ per frame
    def _predicted_q(self) -> np.ndarray | None:
        if len(self._q) < 2:
            return None
        return 2 * self._q[-1] - self._q[-2]

    def _predict(self) -> np.ndarray:
        assert self._flow is not None
        q = self._predicted_q()
        if q is None:
            return self._flow
        h, w = self._shape
        return (q @ self.basis).T.reshape(h, w, 2)

    def occlusion(self, grey: np.ndarray, flow: np.ndarray, back: np.ndarray | None
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Occlusion probability (H, W) and in-view mask (H, W) of reference pixels for the
        reference->frame ``flow`` (and frame->reference ``back`` for the FB check)."""
        c = self.config
        h, w = self._shape
        x, y = self._gx + flow[..., 0], self._gy + flow[..., 1]
        inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
        resid = np.abs(_warp(highpass(grey), self._gx, self._gy, flow) - self._ref_hp)
        resid = cv2.GaussianBlur(resid, (0, 0), 1.5)
        score = (resid / c.residual_threshold) ** 2
        if back is not None:
            fb = _warp(back, self._gx, self._gy, flow) + flow
            fb = np.sqrt((fb ** 2).sum(-1))
            score = score + (fb / c.fb_threshold) ** 2
        score = score * score       # sharp: ~0 for inliers, 1/2 at the thresholds
        occ = score / (1.0 + score)
        return occ.astype(np.float32), inside

    def step(self, grey: np.ndarray) -> MFOFFrame:
        """Track one grey uint8 frame (H, W)."""
        grey = check_grey(grey, self._ref)
        self._index += 1
        if self._ref is None:
            return self._new_reference(grey)
        c = self.config
        h, w = self._shape
        pred = self._predict()
        u = self._fwd.calc(self._ref, grey, np.ascontiguousarray(pred))
        back = None
        if c.backward:
            init = -_warp(u, self._gx, self._gy, -u)
            back = self._bwd.calc(grey, self._ref, np.ascontiguousarray(init))
        occ, inside = self.occlusion(grey, u, back)
        weight = ((1.0 - occ) * inside).ravel()
        w_data = weight
        d = u.reshape(-1, 2).T
        B = self.basis
        q = fit_coefficients(B, d, weight, c.huber_px, sample=self._sample,
                             prior=self._predicted_q(), prior_weight=c.temporal_weight)
        s = q @ B
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
        flow = fused.T.reshape(h, w, 2)
        self._flow = flow
        # visibility: the fused position must be in view too
        fx, fy = self._gx + flow[..., 0], self._gy + flow[..., 1]
        in_view = ((fx >= 0) & (fx <= w - 1) & (fy >= 0) & (fy <= h - 1)).ravel()
        vis = (1.0 - occ.ravel()) * in_view
        if vis[self._mask_lin].mean() < c.reselect_fraction:
            self._low_visible += 1
        else:
            self._low_visible = 0
        frame = MFOFFrame(self._index, self._xy + fused[:, self._lin].T, vis[self._lin],
                          occ.ravel()[self._lin], flow, self.ids)
        if self._low_visible >= c.reselect_patience:
            self._ref = None      # the next frame becomes the new reference
        return frame

    def _new_reference(self, grey: np.ndarray) -> MFOFFrame:
        self._set_reference(grey)
        P = self._lin.size
        assert self._flow is not None
        return MFOFFrame(self._index, self._xy.copy(), np.ones(P, np.float32),
                         np.zeros(P, np.float32), self._flow, self.ids, self.epoch > 0)

    def _push(self, d: np.ndarray, weight: np.ndarray, fused: np.ndarray) -> None:
        c = self.config
        win = self._win
        g = self._grid
        win.data.append(g.down(d.astype(np.float32)))
        win.weight.append(g.down(weight[None].astype(np.float32))[0])
        win.model.append(g.down(fused.astype(np.float32)))
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
        self._set_learned(g.up(self._coarse))
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
    O: np.ndarray
    ids: np.ndarray
    reselections: list[int]
    seconds: float


def track_sequence(frames, config: MFOFConfig | None = None, smooth: bool = True
                   ) -> TrackResult:
    """Track a sequence of grey uint8 frames: the streaming tracker, then (``smooth``) a
    two-sided pass that re-fits the subspace on a window centred on each frame (past and
    future frames) and re-fuses every frame's data with it.

    Tracks are returned for the first reference only (frames after a re-selection are marked
    invisible for those tracks), so W keeps one P."""
    import time
    t0 = time.perf_counter()
    cfg = config or MFOFConfig()
    tracker = MFOFTracker(cfg)
    tracker.keep_history = smooth
    frames = list(frames)
    out = [tracker.step(np.asarray(f)) for f in frames]
    ids = out[0].ids
    F, P = len(out), ids.size
    W = np.zeros((2 * F, P), np.float32)
    V = np.zeros((F, P), np.float32)
    O = np.ones((F, P), np.float32)
    reselections = [fr.index for fr in out[1:] if fr.reselected]
    last = reselections[0] if reselections else F
    for f in range(F):
        fr = out[min(f, last - 1)]
        W[2 * f], W[2 * f + 1] = fr.uv[:, 0], fr.uv[:, 1]
        if f < last:
            V[f], O[f] = fr.visibility, fr.occlusion
    if smooth and last > 3 and cfg.rank > 0:
        hist = tracker.history[:last - 1]       # frames 1..last-1 of the first reference
        fused = _two_sided(tracker, hist)
        lin, xy = tracker.first_lin, tracker.first_xy
        for k, f in enumerate(range(1, last)):
            pos = xy + fused[k][:, lin].T
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
