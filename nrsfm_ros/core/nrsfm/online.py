"""Online (sequential) NRSfM: a shape per new frame in constant time after initialisation.

The first ``window`` frames are reconstructed by the sliding-window low-rank method; its shapes
give a rank-K basis B (K, 3, P) in the object frame (the top K right singular vectors of S#).
From then on each new frame is fitted alone: camera R_f (orthonormal rows), coefficients a_f
(scale absorbed) and translation t_f minimise sum_p v_p |w_p - t_f - R_f sum_k a_fk B_kp|^2, by
a few alternations warm-started from the previous frame (coefficients and translation by linear
least squares, the camera by the polar factor).  Cost O(K P) per frame, no window re-solve:
this is what the reconstructor's ``mode: online`` publishes.
"""
from __future__ import annotations

import numpy as np

from .factorization import complete_rotations
from .window import FrameShape, WindowNRSfM


class OnlineNRSfM:
    """``push(uv, visibility)`` -> shapes that became available (the whole initial window at
    once, then one per frame).  A change in the number of points resets."""

    def __init__(self, window: int = 15, rank: int = 2, iterations: int = 10,
                 alternations: int = 5) -> None:
        if alternations < 1:
            raise ValueError(f'alternations: expected >= 1, got {alternations}')
        self._win = WindowNRSfM(window=window, rank=rank, iterations=iterations)
        self.rank, self.alternations = rank, alternations
        self.basis: np.ndarray | None = None
        self._R2 = np.eye(3)[:2]
        self._a = np.zeros(rank)
        self._count = 0

    def reset(self) -> None:
        self._win.reset()
        self.basis = None
        self._count = 0

    def push(self, uv: np.ndarray, visibility: np.ndarray | None = None) -> list[FrameShape]:
        uv = np.asarray(uv, dtype=np.float64)
        if self.basis is not None and uv.shape[0] != self.basis.shape[2]:
            self.reset()
        self._count += 1
        if self.basis is None:
            out = self._win.push(uv, visibility)
            if out:
                self._init_basis(out)
            return out
        vis = np.ones(uv.shape[0]) if visibility is None else np.asarray(visibility, np.float64)
        return [self._fit(uv, vis)]

    def _init_basis(self, shapes: list[FrameShape]) -> None:
        # object-frame shapes, scale applied, as S# (F, 3P)
        S_obj = np.stack([(fs.S * fs.scale) @ fs.R for fs in shapes])      # (F, P, 3)
        F, P, _ = S_obj.shape
        S_sharp = S_obj.transpose(0, 2, 1).reshape(F, 3 * P)
        U, s, Vt = np.linalg.svd(S_sharp, full_matrices=False)
        K = min(self.rank, F)
        self.basis = Vt[:K].reshape(K, 3, P)
        self._a = U[-1, :K] * s[:K]
        self._R2 = shapes[-1].R[:2]

    def _fit(self, uv: np.ndarray, vis: np.ndarray) -> FrameShape:
        assert self.basis is not None
        B = self.basis
        K, _, P = B.shape
        w = uv.T                                                  # (2, P)
        sw = np.sqrt(vis)
        R2, a = self._R2, self._a
        t = (w * vis).sum(1) / max(vis.sum(), 1e-12) - R2 @ (np.einsum('k,kip->ip', a, B)
                                                              * vis).sum(1) / max(vis.sum(),
                                                                                  1e-12)
        for _ in range(self.alternations):
            # coefficients and translation: linear least squares over the 2P equations
            RB = np.einsum('ij,kjp->kip', R2, B).reshape(K, 2 * P)         # (K, 2P)
            T = np.zeros((2, 2 * P))
            T[0, :P], T[1, P:] = 1.0, 1.0
            A = np.vstack([RB, T]).T * np.tile(sw, 2)[:, None]             # (2P, K + 2)
            sol = np.linalg.lstsq(A, w.reshape(-1) * np.tile(sw, 2), rcond=None)[0]
            a, t = sol[:K], sol[K:]
            # camera: polar factor of the weighted cross-covariance
            S = np.einsum('k,kip->ip', a, B)                               # (3, P)
            Mx = ((w - t[:, None]) * vis) @ S.T
            U, _, Vt = np.linalg.svd(Mx, full_matrices=False)
            R2 = U @ Vt
        self._R2, self._a = R2, a
        S = np.einsum('k,kip->ip', a, B)
        R = complete_rotations(R2[None])[0]
        resid = np.linalg.norm(w - t[:, None] - R2 @ S, axis=0)
        return FrameShape(index=self._count - 1, S=(R @ S).T, R=R, scale=1.0, t=t,
                          residual_px=float((resid * vis).sum() / max(vis.sum(), 1e-12)))
