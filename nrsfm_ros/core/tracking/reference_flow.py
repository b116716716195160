"""Reference-to-frame dense flow tracking, seeded by the previous frame's flow.

Each frame is matched directly against the reference (no frame-to-frame chaining, so errors do
not accumulate); the previous frame's reference->frame flow initialises the solver, so large
accumulated motion stays within the solver's basin.  Data step: OpenCV DIS (fast, measured
0.61 px EPE on Middlebury at 14 ms/pair here).  Visibility comes from the photometric residual of
the warped frame against the reference.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .rules import MASKS, PRESETS, check_param

__all__ = ['MASKS', 'PRESETS', 'ReferenceFlowTracker', 'TrackFrame', 'texture_mask']


NOISE_FACTOR = 1.5   # texture: a local std above this many times the image's noise too


def noise_std(grey: np.ndarray) -> float:
    """The image's noise (std, grey levels), robustly: Immerkaer's Laplacian-difference filter
    (6 sigma of white noise), its 25th percentile over the pixels (0.3186 sigma for Gaussian
    values), so that flat areas (a quarter of the image suffices) give it while texture and
    edges do not; on an image all texture it reads the texture's finest scale (~4 on ours)."""
    g = np.asarray(grey, np.float32)
    if min(g.shape) < 3:
        return 0.0
    k = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    r = np.abs(cv2.filter2D(g, -1, k, borderType=cv2.BORDER_REFLECT)[1:-1, 1:-1])
    return float(np.percentile(r, 25)) / (0.3186 * 6.0)


def texture_mask(grey: np.ndarray, block: int = 7, min_std: float = 4.0) -> np.ndarray:
    """Pixels whose local intensity standard deviation exceeds ``min_std`` and
    ``NOISE_FACTOR`` x the image's noise (trackable texture, not a noisy flat area), closed and
    with small holes filled; (H, W) bool."""
    g = grey.astype(np.float32)
    mean = cv2.boxFilter(g, -1, (block, block))
    sq = cv2.boxFilter(g * g, -1, (block, block))
    std = np.sqrt(np.maximum(sq - mean * mean, 0.0))
    mask = (std > max(min_std, NOISE_FACTOR * noise_std(grey))).astype(np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (block, block))
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel)
    mask = cv2.erode(mask, cv2.getStructuringElement(cv2.MORPH_RECT, (3, 3)))
    return mask.astype(bool)


def roi_region(mask: np.ndarray, margin: int) -> np.ndarray:
    """A segmentation ``mask`` (H, W; nonzero: the surface) eroded by ``margin`` px (a disc):
    the region a new reference tracks (``tracker.roi``), away from the mask's edge."""
    m8 = (np.asarray(mask) != 0).astype(np.uint8)
    if margin > 0:
        m8 = cv2.erode(m8, cv2.getStructuringElement(cv2.MORPH_ELLIPSE,
                                                     (2 * margin + 1, 2 * margin + 1)))
    return m8.astype(bool)


def black_out(grey: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``grey`` with what lies outside the ``mask`` (nonzero: the surface) set to 0: the flow
    and the texture mask then see a plain background, not what lies behind the surface."""
    return np.where(np.asarray(mask) != 0, grey, np.uint8(0)).astype(np.uint8)


MIN_SIDE = 16   # px: a smaller image has no level for DIS's patches (OpenCV rejects it deep in
#   its flow with "Incorrect size of input array")


def check_grey(grey: np.ndarray, reference: np.ndarray | None) -> np.ndarray:
    """An (H, W) uint8 frame of the reference's size, or a ValueError naming what is wrong."""
    grey = np.asarray(grey)
    if grey.ndim != 2 or grey.dtype != np.uint8:
        raise ValueError(f'grey: expected an (H, W) uint8 image, got {grey.dtype} '
                         f'{grey.shape}')
    if reference is not None and grey.shape != reference.shape:
        raise ValueError(f'grey: size {grey.shape} differs from the reference '
                         f'{reference.shape}')
    if min(grey.shape) < MIN_SIDE:
        raise ValueError(f'grey: image {grey.shape} smaller than {MIN_SIDE} px on a side (too '
                         f'small for the flow pyramid)')
    return grey


def reference_pixels(grey: np.ndarray, mask: str, stride: int, min_std: float,
                     roi: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tracked pixels of a reference frame: the mask (H, W), the linear indices
    ``y * W + x`` of every ``stride``-th mask pixel, and their (x, y) positions (P, 2).
    ``roi``: a bool (H, W) region the mask is limited to (the surface's segmentation)."""
    h, w = grey.shape
    m = texture_mask(grey, min_std=min_std) if mask == 'texture' else np.ones((h, w), bool)
    if roi is not None:
        if roi.shape != (h, w):
            raise ValueError(f'roi: size {roi.shape} differs from the frame {(h, w)}')
        m = m & roi
    grid = np.zeros((h, w), bool)
    grid[::stride, ::stride] = True
    ys, xs = np.nonzero(m & grid)
    _check_count(xs.size, roi is not None)
    return m, (ys * w + xs).astype(np.intp), np.stack([xs, ys], axis=1).astype(np.float32)


def check_trackable(grey: np.ndarray, mask: str, stride: int, min_std: float) -> None:
    """The ValueError ``reference_pixels`` would raise on ``grey`` (fewer than 4 trackable
    pixels), without building its pixel lists (a check of every frame: 2.4 -> 1.8 ms at
    640x480)."""
    if mask == 'texture':
        _check_count(int(np.count_nonzero(texture_mask(grey, min_std=min_std)[::stride,
                                                                            ::stride])), False)
    else:
        _check_count(len(range(0, grey.shape[0], stride)) * len(range(0, grey.shape[1], stride)),
                     False)


def _check_count(n: int, roi: bool) -> None:
    if n < 4:
        raise ValueError(f'reference frame: only {n} trackable pixels (need >= 4); '
                         + ('the region of interest is too small or untextured'
                            if roi else 'lower min_std or use mask=full'))


@dataclass(frozen=True)
class TrackFrame:
    """Tracks of one frame: uv (P, 2) pixel positions, visibility (P,) in [0, 1],
    flow (H, W, 2) reference->frame, index of the frame."""

    index: int
    uv: np.ndarray
    visibility: np.ndarray
    flow: np.ndarray


class ReferenceFlowTracker:
    """Tracks every ``stride``-th pixel of the reference mask through the sequence.

    Track ids are the reference pixels' linear indices ``y * width + x``, so they are stable and
    comparable with ground truth.
    """

    def __init__(self, preset: str = 'medium', stride: int = 2, mask: str = 'texture',
                 min_std: float = 4.0, occlusion_threshold: float = 25.0) -> None:
        for name, value in (('preset', preset), ('stride', stride), ('mask', mask),
                            ('min_std', min_std), ('occlusion_threshold', occlusion_threshold)):
            check_param(name, value)
        self.preset, self.stride, self.mask_mode = preset, stride, mask
        self.min_std, self.occlusion_threshold = min_std, occlusion_threshold
        self._dis = cv2.DISOpticalFlow_create(PRESETS[preset])
        self._ref: np.ndarray | None = None
        self._flow: np.ndarray | None = None
        self.ids = np.zeros(0, np.uint32)
        self._xy = np.zeros((0, 2), np.float32)
        self._index = -1
        self.roi: np.ndarray | None = None   # bool (H, W): a new reference tracks only it

    @property
    def reference(self) -> np.ndarray | None:
        return self._ref

    def reset(self) -> None:
        self._ref = None
        self._flow = None
        self._index = -1

    def _set_reference(self, grey: np.ndarray) -> None:
        h, w = grey.shape
        _, lin, self._xy = reference_pixels(grey, self.mask_mode, self.stride, self.min_std,
                                            self.roi)
        self.ids = lin.astype(np.uint32)
        self._ref = grey
        self._flow = np.zeros((h, w, 2), np.float32)

    def step(self, grey: np.ndarray) -> TrackFrame:
        """Track one grey uint8 frame (H, W); the first frame becomes the reference."""
        grey = check_grey(grey, self._ref)
        self._index += 1
        if self._ref is None:
            self._set_reference(grey)
            flow = self._flow
        else:
            self._dis.setUseSpatialPropagation(True)
            flow = self._dis.calc(self._ref, grey, self._flow.copy())
            self._flow = flow
        assert flow is not None
        xi, yi = self._xy[:, 0].astype(np.intp), self._xy[:, 1].astype(np.intp)
        uv = self._xy + flow[yi, xi]
        vis = self._visibility(grey, flow, uv)
        return TrackFrame(index=self._index, uv=uv, visibility=vis, flow=flow)

    def _visibility(self, grey: np.ndarray, flow: np.ndarray, uv: np.ndarray) -> np.ndarray:
        assert self._ref is not None
        h, w = grey.shape
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
        if self._index == 0:
            return inside.astype(np.float32)
        gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        warped = cv2.remap(grey, gx + flow[..., 0], gy + flow[..., 1], cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REPLICATE)
        resid = cv2.blur(np.abs(warped.astype(np.float32) - self._ref.astype(np.float32)),
                         (5, 5))
        r = resid[self._xy[:, 1].astype(np.intp), self._xy[:, 0].astype(np.intp)]
        vis = np.clip(1.5 - r / self.occlusion_threshold, 0.0, 1.0)
        return (vis * inside).astype(np.float32)
