"""Synthetic data with known answers for the core tests."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def low_rank_sequence(K: int = 3, F: int = 60, P: int = 300, seed: int = 0
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthographic tracks W (2F, P) of a rank-K shape sequence seen by a rotating camera;
    returns W, camera-frame shapes S (F, P, 3) and rotations R (F, 3, 3)."""
    rng = np.random.default_rng(seed)
    B = rng.normal(size=(K, 3, P))
    B[0] *= 3
    tt = np.linspace(0, 6, F)[:, None]
    c = np.concatenate([np.ones((F, 1)), 0.3 * np.sin(tt * rng.uniform(0.5, 2, (1, K - 1)))],
                       axis=1)
    S_obj = np.einsum('fk,kip->fip', c, B)
    ang = np.stack([0.5 * np.sin(np.linspace(0, 3, F)), 0.8 * np.cos(np.linspace(0, 2, F)),
                    np.linspace(0, 1, F)], axis=1)
    R = Rotation.from_euler('xyz', ang).as_matrix()
    S = np.einsum('fij,fjp->fpi', R, S_obj)
    W = S[:, :, :2].transpose(0, 2, 1).reshape(2 * F, P) + 5.0
    return W, S, R
