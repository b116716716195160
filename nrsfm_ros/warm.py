"""Load the numba kernels once (from numba's on-disk cache, compiling on a first run): the
fleet's fork server imports this, so every worker it forks starts with them loaded instead of
paying ~0.3-0.5 s on its first bag (a 128x96 20-frame bag is ~1.6 s of work).  Importing it
anywhere else is harmless: a few calls on tiny arrays."""
from __future__ import annotations

import numpy as np

from .core.nrsfm import _admm, _planar_kernels


def warm() -> None:
    """One call of each kernel on tiny arrays, with the argument types the solvers pass (so
    the compiled specialisations are the ones they use): the ADMM's in ``ADMM_DTYPE``."""
    from .core.nrsfm.bmm import ADMM_DTYPE
    F, P = 2, 4
    dt = np.dtype(ADMM_DTYPE).type
    z = np.zeros((F, 3, P), dt)
    eye = np.tile(np.eye(3, dtype=dt), (F, 1, 1))
    _admm.data_step(z, z.copy(), z.copy(), eye, np.ones((F, 3), dt), np.ones((F, P), dt),
                    dt(1.0), dt(1.0), dt(1.0), z.copy(), z.copy())
    _admm.dual_step(z, z.copy(), z.copy(), z.copy(), dt(1.0))
    T = np.zeros((F, 3))
    T[:, 2] = 1.0
    eye = np.tile(np.eye(3), (F, 1, 1))
    _planar_kernels.final_passes(np.ones((P, F, 3)), np.ones((P, F)), eye, T, np.ones((F, 2)),
                                 np.zeros((P, 2)), np.zeros((P, F)), 0.01, 2, 1e-9)


warm()
