"""Sliding-window NRSfM for streaming tracks: one shape per incoming frame."""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace

import numpy as np

from .factorization import low_rank
from .result import NRSfMResult


@dataclass(frozen=True)
class FrameShape:
    """One frame's reconstruction: S (P, 3) camera frame, image units; W_f ~= scale*S[:, :2]+t."""

    index: int
    S: np.ndarray
    R: np.ndarray
    scale: float
    t: np.ndarray
    residual_px: float


class WindowNRSfM:
    """Low-rank NRSfM over the last ``window`` frames, warm-started frame to frame.

    ``push(uv, visibility)`` returns the shapes that became available: nothing until the window
    is full, then every buffered frame at once, then one shape per new frame.  The depth
    reflection is kept consistent between windows.  A change in the number of points resets.
    """

    def __init__(self, window: int = 20, rank: int = 3, iterations: int = 30) -> None:
        if window < 3:
            raise ValueError(f'window: expected >= 3, got {window}')
        if rank < 1:
            raise ValueError(f'rank: expected >= 1, got {rank}')
        self.window, self.rank, self.iterations = window, rank, iterations
        self._uv: deque[np.ndarray] = deque(maxlen=window)
        self._vis: deque[np.ndarray] = deque(maxlen=window)
        self._last: NRSfMResult | None = None
        self._count = 0

    @property
    def frames_seen(self) -> int:
        return self._count

    def reset(self) -> None:
        self._uv.clear()
        self._vis.clear()
        self._last = None

    def push(self, uv: np.ndarray, visibility: np.ndarray | None = None) -> list[FrameShape]:
        uv = np.asarray(uv, dtype=np.float64)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise ValueError(f'uv: expected shape (P, 2), got {uv.shape}')
        vis = np.ones(uv.shape[0]) if visibility is None else np.asarray(visibility, np.float64)
        if vis.shape != (uv.shape[0],):
            raise ValueError(f'visibility: expected shape ({uv.shape[0]},), got {vis.shape}')
        if self._uv and self._uv[0].shape != uv.shape:
            self.reset()
        self._uv.append(uv)
        self._vis.append(vis)
        self._count += 1
        if len(self._uv) < self.window:
            return []
        W = np.stack(self._uv, axis=0).transpose(0, 2, 1).reshape(-1, uv.shape[0])
        V = np.stack(self._vis, axis=0)
        # never-visible points inside the window would make the problem ill-posed: keep them
        # weakly (they are carried by the low-rank shape space)
        V = np.maximum(V, 1e-3)
        first = self._last is None
        init = None if first else self._shifted_init()
        res = low_rank(W, V, rank=self.rank, iterations=self.iterations if not first else
                       max(self.iterations, 60), init=init)
        if self._last is not None:
            res = self._consistent_reflection(res)
        self._last = res
        start = self._count - len(self._uv)
        frames = range(len(self._uv)) if first else [len(self._uv) - 1]
        return [FrameShape(index=start + i, S=res.S[i], R=res.R[i], scale=float(res.scale[i]),
                           t=res.t[i], residual_px=res.residual_px) for i in frames]

    def _shifted_init(self) -> NRSfMResult:
        last = self._last
        assert last is not None
        def shift(a: np.ndarray) -> np.ndarray:
            return np.concatenate([a[1:], a[-1:]], axis=0)
        return replace(last, S=shift(last.S), R=shift(last.R), scale=shift(last.scale),
                       t=shift(last.t))

    def _consistent_reflection(self, res: NRSfMResult) -> NRSfMResult:
        """Flip depth if that agrees better with the previous window on the shared frames."""
        prev = self._last
        assert prev is not None
        a = prev.S[1:, :, 2]
        b = res.S[:-1, :, 2]
        a = a - a.mean(axis=1, keepdims=True)
        b = b - b.mean(axis=1, keepdims=True)
        if float(np.sum(a * b)) >= 0:
            return res
        flip = np.diag([1.0, 1.0, -1.0])
        S = res.S @ flip
        R = np.einsum('ij,fjk->fik', flip, res.R) @ flip
        return replace(res, S=S, R=R)
