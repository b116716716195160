"""HDM-Net (Golyanik et al. 2018; METHODS.md section 8): one RGB image -> a GRID x GRID grid of
3-D points of a thin surface, camera optical frame, metres.  This module holds the model's
contract and its NumPy pre- and post-processing; the network itself runs elsewhere (ONNX
Runtime in ``io.hdmnet_model``, PyTorch in ``learning.hdmnet_train``).

The model sees the *canonical camera*: a square ``INPUT_SIZE`` image with focal ``CANON_FOCAL``
px and the principal point at its centre, and predicts the grid in that camera's frame.  Any
image is padded to a square (edge pixels repeated) and resized to it; the prediction's canonical
pixel positions and depths are then mapped back through the real intrinsics: pixel positions
undo the pad and resize, and the depth scales by the ratio of the real focal (in canonical
pixels) to ``CANON_FOCAL`` (an object of a given pixel size is that much further away).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

INPUT_SIZE = 224            # px, the model's square input
CANON_FOCAL = 640.0         # px at INPUT_SIZE: the training camera (a ~20 deg field of view)
GRID = 73                   # the output grid is GRID x GRID (5329 points)
MIN_SIDE = 32               # px: smaller images are refused


@dataclass(frozen=True)
class Canon:
    """How an image of ``height`` x ``width`` became the model's input: padded by ``pad``
    (left, top) px to a square, scaled by ``scale`` (input px per image px)."""
    height: int
    width: int
    pad: tuple[int, int]
    scale: float


@dataclass(frozen=True)
class HDMNetResult:
    """``points`` (GRID, GRID, 3) float64 camera frame (m), NaN where the prediction is unusable
    (non-finite, or not in front of the camera); ``valid`` (GRID, GRID) bool; timings in ms."""
    points: np.ndarray
    valid: np.ndarray
    infer_ms: float
    total_ms: float

    def cloud(self) -> tuple[np.ndarray, np.ndarray]:
        """The valid points (N, 3) and their grid ids (N,) uint32 (row * GRID + column: the
        same material point in every frame)."""
        ids = np.flatnonzero(self.valid.ravel()).astype(np.uint32)
        return self.points.reshape(-1, 3)[ids], ids


def check_image(image: np.ndarray) -> np.ndarray:
    """An (H, W, 3) uint8 RGB image, or a ValueError naming what is wrong."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f'image: expected shape (H, W, 3) rgb, got {image.shape}')
    if image.dtype != np.uint8:
        raise ValueError(f'image: expected dtype uint8 (rgb8), got {image.dtype}')
    h, w = image.shape[:2]
    if min(h, w) < MIN_SIDE:
        raise ValueError(f'image: {w}x{h} px is smaller than {MIN_SIDE} px on a side')
    return image


def preprocess(image: np.ndarray) -> tuple[np.ndarray, Canon]:
    """rgb8 image (H, W, 3) -> the model input (1, 3, INPUT_SIZE, INPUT_SIZE) float32 in
    [0, 1] and the :class:`Canon` mapping back."""
    image = check_image(image)
    h, w = image.shape[:2]
    side = max(h, w)
    left, top = (side - w) // 2, (side - h) // 2
    sq = cv2.copyMakeBorder(image, top, side - h - top, left, side - w - left,
                            cv2.BORDER_REPLICATE) if side != min(h, w) else image
    interp = cv2.INTER_AREA if side > INPUT_SIZE else cv2.INTER_LINEAR
    x = cv2.resize(sq, (INPUT_SIZE, INPUT_SIZE), interpolation=interp) if side != INPUT_SIZE \
        else sq
    x = np.ascontiguousarray(x.transpose(2, 0, 1)[None], np.float32) * np.float32(1 / 255)
    return x, Canon(h, w, (left, top), INPUT_SIZE / side)


def default_K(canon: Canon) -> np.ndarray:
    """Intrinsics assumed without CameraInfo: the canonical camera's field of view over the
    padded square, the principal point at the image centre."""
    f = CANON_FOCAL / canon.scale
    return np.array([[f, 0, (canon.width - 1) / 2], [0, f, (canon.height - 1) / 2],
                     [0, 0, 1.0]])


def postprocess(grid: np.ndarray, canon: Canon, K: np.ndarray | None = None) -> np.ndarray:
    """The model's output (GRID, GRID, 3) (canonical camera frame) -> points (GRID, GRID, 3)
    in the frame of the camera with intrinsics ``K`` (3, 3) (default: :func:`default_K`), NaN
    where unusable."""
    g = np.asarray(grid, np.float64).reshape(GRID, GRID, 3)
    K = default_K(canon) if K is None else np.asarray(K, np.float64)
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f'K: expected finite (3, 3) intrinsics with fx, fy > 0, got {K!r}')
    z = g[..., 2]
    ok = np.isfinite(g).all(axis=-1) & (z > 1e-3)
    zs = np.where(ok, z, 1.0)
    c = (INPUT_SIZE - 1) / 2
    uc = CANON_FOCAL * g[..., 0] / zs + c
    vc = CANON_FOCAL * g[..., 1] / zs + c
    u = (uc + 0.5) / canon.scale - 0.5 - canon.pad[0]
    v = (vc + 0.5) / canon.scale - 0.5 - canon.pad[1]
    f_canon = float(np.sqrt(K[0, 0] * K[1, 1])) * canon.scale
    Z = zs * f_canon / CANON_FOCAL
    out = np.stack([(u - K[0, 2]) / K[0, 0] * Z, (v - K[1, 2]) / K[1, 1] * Z, Z], axis=-1)
    out[~ok] = np.nan
    return out


def grid_uv(points: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pinhole projection (..., 2) px of camera-frame points (..., 3)."""
    z = np.where(points[..., 2] > 0, points[..., 2], np.nan)
    return np.stack([K[0, 0] * points[..., 0] / z + K[0, 2],
                     K[1, 1] * points[..., 1] / z + K[1, 2]], axis=-1)


def sample_grid(points: np.ndarray, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Bilinear interpolation (N, 3) of a (GRID, GRID, 3) grid at material coordinates
    s (columns), t (rows) in [0, 1]."""
    n = points.shape[0]
    x = np.clip(np.asarray(s, np.float64), 0, 1) * (n - 1)
    y = np.clip(np.asarray(t, np.float64), 0, 1) * (n - 1)
    x0 = np.minimum(np.floor(x).astype(int), n - 2)
    y0 = np.minimum(np.floor(y).astype(int), n - 2)
    ax, ay = (x - x0)[:, None], (y - y0)[:, None]
    p = points
    return ((1 - ax) * (1 - ay) * p[y0, x0] + ax * (1 - ay) * p[y0, x0 + 1]
            + (1 - ax) * ay * p[y0 + 1, x0] + ax * ay * p[y0 + 1, x0 + 1])


def e3d_per_frame(S: np.ndarray, S_gt: np.ndarray) -> np.ndarray:
    """Metric B per frame (F,) (``core.metrics.e3d_frobenius`` with per-frame Procrustes and
    scale, the pipeline benchmark's metric) of shapes S against S_gt, both (F, P, 3)."""
    from .metrics import batched_procrustes
    S = np.asarray(S, np.float64)
    S_gt = np.asarray(S_gt, np.float64)
    if S.shape != S_gt.shape or S.ndim != 3 or S.shape[2] != 3:
        raise ValueError(f'S: expected shape (F, P, 3) equal to S_gt {S_gt.shape}, got {S.shape}')
    A = batched_procrustes(S - S.mean(axis=1, keepdims=True),
                           S_gt - S_gt.mean(axis=1, keepdims=True), scale=True)
    B = S_gt - S_gt.mean(axis=1, keepdims=True)
    num = np.linalg.norm((A - B).reshape(len(S), -1), axis=1)
    return num / np.maximum(np.linalg.norm(B.reshape(len(S), -1), axis=1), 1e-300)
