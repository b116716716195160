"""Load the numba kernels once (from numba's on-disk cache, compiling on a first run), each
with the argument types its solver passes, so the compiled specialisation is the one used.

Loading them costs ~0.3-0.5 s a process, on the first call of each.  The fleet's fork server
imports this, so every worker it forks starts with them loaded instead of paying that on its
first bag (a 128x96 20-frame bag is ~1.6 s of work); the reconstructor (node and ``process``)
imports it in a thread when it starts (``processing.warm_in_background``), so the loading runs
while the tracker's first frames arrive instead of inside the first batch solve.  Importing it
anywhere else is harmless: a few calls on tiny arrays."""
from __future__ import annotations

import numpy as np

from .core.nrsfm import _admm, _pinhole_kernels, _planar_kernels
from .core.registration import _rays_kernel
from .core.sceneflow import _flow_kernels

def warm() -> None:
    """One call of each kernel on tiny arrays, with the argument types the solvers pass: the
    ADMM's in ``ADMM_DTYPE``, the batch solve's (the metric projection, the rigid pinhole
    fits of the depth sign, the frames' perspective errors), the planar pinhole refinement's
    the registrar's ray pose and the scene flow's window fit in float64."""
    from .core.nrsfm.bmm import ADMM_DTYPE, metric_projection_Q
    from .core.nrsfm.rigid_pinhole import fit_rigid_pinhole
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
    metric_projection_Q(np.eye(6)[[0, 1, 2, 3, 4, 5, 0, 2]] + 0.1, iterations=2)
    # a rigid fit of 5 frames x 15 points (the fewest it accepts) through the bundle kernels
    rng = np.random.default_rng(0)
    Fb, Pb = 5, 15
    X = rng.normal(size=(Pb, 3))
    Tb = np.tile([0.0, 0.0, 10.0], (Fb, 1))
    Rb = np.tile(np.eye(3), (Fb, 1, 1))
    Y = X[None] + Tb[:, None]
    uv = 100.0 * Y[..., :2] / Y[..., 2:]
    W = uv.transpose(0, 2, 1).reshape(2 * Fb, Pb)
    fit_rigid_pinhole(W, np.ones((Fb, Pb)), Rb, X, Tb, 100.0, np.zeros(2), iterations=1)
    S = np.ones((F, P, 3))
    _pinhole_kernels.frame_error_table(S, np.ones(F), np.zeros((F, 2)), np.ones((2 * F, P)),
                                       np.ones((F, P)), 1.0, 0.0, 0.0, 0.5, 2.0)
    _pinhole_kernels.weak_image_error(S, np.ones(F), np.zeros((F, 2)), np.ones((2 * F, P)),
                                      np.ones((F, P)), 0.0, 0.0, np.ones((F, P)), 1.0)
    m, w = np.zeros((F, P, 2)), np.ones((F, P))
    _pinhole_kernels.pose_normal_equations(S, m, w, eye, T)
    _pinhole_kernels.reprojection_loss(S, m, w, 1.0)
    pts = np.ones((P, 3))
    _rays_kernel.ray_normal_equations(np.eye(4), pts, pts.copy(), pts / np.sqrt(3.0), 0.9, 1.0)
    _rays_kernel.ray_residual_lengths(np.eye(4), pts, pts.copy(), pts / np.sqrt(3.0), 0.1)
    rest, h = np.zeros((P, 2)), np.zeros((F, P))
    _pinhole_kernels.cauchy_weights(rest, h, eye, T, m, w, 1.0)
    _pinhole_kernels.height_terms(S, eye, T, rest, w)
    _pinhole_kernels.rest_coordinates(S, eye, T, h, w, rest)
    _flow_kernels.add_object_displacement(np.zeros((P, 3)), pts, np.zeros(0, np.intp),
                                          np.zeros(3), np.eye(3), 1.0)
    nb = np.zeros((P, 2), np.intp)
    _flow_kernels.neighbour_means(np.ones(P), nb)


warm()
