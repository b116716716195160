"""Middlebury ``.flo`` optical-flow files: float32 magic 202021.25, int32 width, int32 height,
then (u, v) float32 per pixel, row-major; values above 1e9 mean unknown."""
from __future__ import annotations

from pathlib import Path

import numpy as np

MAGIC = 202021.25
UNKNOWN = 1e9


def read_flo(path: str | Path) -> np.ndarray:
    """(H, W, 2) float32 flow; unknown entries become NaN."""
    raw = Path(path).read_bytes()
    if len(raw) < 12:
        raise ValueError(f'{path}: {len(raw)} bytes, too short for a .flo header')
    magic = np.frombuffer(raw, '<f4', 1)[0]
    if magic != np.float32(MAGIC):
        raise ValueError(f'{path}: magic {magic!r}, expected {MAGIC} (not a .flo file)')
    w, h = (int(v) for v in np.frombuffer(raw, '<i4', 2, 4))
    if not (0 < w < 100000 and 0 < h < 100000) or len(raw) != 12 + 8 * w * h:
        raise ValueError(f'{path}: header says {w}x{h} but the file has {len(raw)} bytes')
    flow = np.frombuffer(raw, '<f4', 2 * w * h, 12).reshape(h, w, 2).copy()
    flow[np.abs(flow) > UNKNOWN] = np.nan
    return flow


def write_flo(path: str | Path, flow: np.ndarray) -> None:
    flow = np.asarray(flow, np.float32)
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise ValueError(f'flow: expected (H, W, 2), got {flow.shape}')
    h, w = flow.shape[:2]
    data = np.where(np.isnan(flow), np.float32(1e10), flow).astype('<f4')
    Path(path).write_bytes(np.array([MAGIC], '<f4').tobytes()
                           + np.array([w, h], '<i4').tobytes() + data.tobytes())


def endpoint_error(flow: np.ndarray, gt: np.ndarray) -> float:
    """Mean endpoint error over pixels with known ground truth."""
    ok = np.isfinite(gt).all(axis=-1)
    return float(np.hypot(*(flow[ok] - gt[ok]).T).mean())
