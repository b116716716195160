"""CDF: coherent depth fields for NRSfM with large occlusions (METHODS §6).

The motion-coherence regulariser of CPD (a Gaussian kernel over the reference image positions of
the tracks) is applied to per-frame fields, with per-point visibility weights, so that occluded
tracks are filled from their visible neighbours instead of from a global low-rank guess:

1. 2-D motion fields: for every frame, the displacement of the visible tracks from their
   reference positions is fitted by kernel ridge regression in Nystrom features of the Gaussian
   kernel (width ``beta`` in units of the reference RMS radius, weight ``lam``):
   (Phi^T diag(v_f) Phi + lam I) c_f = Phi^T diag(v_f) d_f, and the field predicts the hidden
   tracks.  Two passes: the second takes the reference positions of tracks hidden in the
   reference frame from the first pass's fill.
2. Cameras and shapes as in ``bmm`` on the filled, consistently centred tracks (the translation
   of a frame is the centroid of all its tracks, not of the visible ones, which a hidden block
   would bias); the shapes' data term uses the visible tracks only.
3. 3-D depth fields: each frame's 3-D displacement from the mean shape is fitted the same way
   on the visible points, and the hidden points take the field's value (their depth follows
   their visible neighbours).

The cost is linear in the number of tracks P (features P x L, one L x L solve per frame, with
the Gram matrix of all tracks down-dated by the hidden ones).
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ..registration.cpd import Nystrom
from .bmm import (_gauge_rounds, averaged_rotations, bmm, bmm_shapes,
                  check_camera_args, noise_level, row_space)
from .factorization import _centre, complete_rotations
from .result import NRSfMResult, check_tracks


def field_fit(Phi: np.ndarray, D: np.ndarray, visible: np.ndarray, lam: float) -> np.ndarray:
    """Per-frame ridge coefficients C (F, L, k) of the fields D (F, P, k) in the features Phi
    (P, L), using the points with ``visible`` (F, P) only."""
    F, P, k = D.shape
    L = Phi.shape[1]
    # every frame's right-hand side in one product (hidden entries zeroed), and each frame's
    # Gram from the whole one less its hidden points' (few, as a rule) or from its visible
    # ones: no (P, L) copy of the features per frame (they were 0.4 s of 0.5 at 60 x 10k)
    Dv = np.where(visible[..., None], D, 0.0)
    rhs = (Phi.T @ Dv.transpose(1, 0, 2).reshape(P, F * k)).reshape(L, F, k).transpose(1, 0, 2)
    G = np.empty((F, L, L))
    G0 = Phi.T @ Phi
    for f in range(F):
        hid = ~visible[f]
        n = int(hid.sum())
        if n == 0:
            G[f] = G0
        elif n < P // 2:
            G[f] = G0 - Phi[hid].T @ Phi[hid]
        else:
            G[f] = Phi[~hid].T @ Phi[~hid]
    G += lam * np.eye(L)
    return np.linalg.solve(G, rhs)


def _features(ref: np.ndarray, beta: float, landmarks: int, seed: int) -> np.ndarray:
    c = ref.mean(0)
    sc = max(float(np.sqrt(((ref - c) ** 2).sum(1).mean())), 1e-12)
    return Nystrom((ref - c) / sc, beta, landmarks, np.random.default_rng(seed)).features(
        (ref - c) / sc)


def coherent_fill(W: np.ndarray, V: np.ndarray, beta: float = 0.5, lam: float = 0.01,
                  landmarks: int = 300, seed: int = 0) -> np.ndarray:
    """W (2F, P) with the hidden entries (V < 0.5) predicted by the per-frame coherent 2-D
    motion fields of the visible tracks (reference: the frame with the most visible tracks)."""
    F, P = V.shape
    vis = V >= 0.5
    if vis.all():
        return W
    Wf = W.reshape(F, 2, P)
    r = int(np.argmax(vis.sum(1)))
    first = np.argmax(vis, axis=0)                      # a frame where each track is seen
    ref = np.where(vis[r][:, None], Wf[r].T, Wf[first, :, np.arange(P)])
    J = np.flatnonzero(~vis.all(axis=0))                # the fields are read where hidden only
    X = W
    for _ in range(2):
        Phi = _features(ref, beta, landmarks, seed)
        D = (Wf - ref.T[None]).transpose(0, 2, 1)       # (F, P, 2)
        fit = Phi[J] @ field_fit(Phi, D, vis, lam)      # (F, |J|, 2)
        filled = D + ref[None]
        filled[:, J] = np.where(vis[:, J, None], D[:, J], fit) + ref[None, J]
        X = filled.transpose(0, 2, 1).reshape(2 * F, P)
        ref = filled[r]                                  # consistent reference for pass 2
    return X


def cdf(W: np.ndarray, V: np.ndarray | None = None, beta: float = 0.5, lam: float = 0.01,
        lam_nuc: float = 4.0, landmarks: int = 300, iterations: int = 100,
        gauge_rounds: int = 1, trace_weight: float = 1e-3, seed: int = 0,
        camera_model: str = 'auto', smooth: float | None = None, orbit_tolerance: float = 0.1
        ) -> NRSfMResult:
    """Coherent depth fields: coherent 2-D fill of occluded tracks, ``bmm`` cameras and shapes
    (visible data term, nuclear-norm weight ``lam_nuc`` x the noise level, Procrustean gauge),
    then coherent 3-D fields for the hidden points.  ``beta`` kernel width (reference RMS
    radius units), ``lam`` ridge weight, ``landmarks`` Nystrom rank; ``camera_model``,
    ``smooth``, ``orbit_tolerance`` as in ``bmm``."""
    t0 = time.perf_counter()
    W, V = check_tracks(W, V)
    for name, v in (('beta', beta), ('lam', lam)):
        if not v > 0:
            raise ValueError(f'{name}: expected > 0, got {v}')
    if lam_nuc < 0 or landmarks < 1 or iterations < 1 or gauge_rounds < 0:
        raise ValueError(f'lam_nuc={lam_nuc}, landmarks={landmarks}, iterations={iterations}, '
                         f'gauge_rounds={gauge_rounds}: expected >= 0, >= 1, >= 1, >= 0')
    check_camera_args(camera_model, smooth, orbit_tolerance)
    F, P = V.shape
    vis = V >= 0.5
    if vis.all():        # nothing to fill: exactly bmm (incl. its exact low-rank path)
        res = bmm(W, V, lam=lam_nuc, iterations=iterations, trace_weight=trace_weight,
                  gauge_rounds=gauge_rounds, camera_model=camera_model, smooth=smooth,
                  orbit_tolerance=orbit_tolerance)
        return replace(res, method='cdf', seconds=time.perf_counter() - t0)
    X = coherent_fill(W, V, beta, lam, landmarks, seed)
    ones = np.ones_like(V)
    Xc, t = _centre(X, ones)
    Xr = row_space(Xc)[0]       # the cameras see only the column space: 2F x r, not 2F x P
    R2 = averaged_rotations(Xr, np.ones((F, Xr.shape[1])), trace_weight=trace_weight)
    lam_abs = lam_nuc * max(noise_level(Xc), 1e-4)
    init = R2.transpose(0, 2, 1) @ Xc.reshape(F, 2, P)
    S, it, conv = bmm_shapes(Xc, V, R2, lam_abs, iterations, init=init)
    R2, S, used = _gauge_rounds(Xc, V, R2, S, lam_abs, iterations, gauge_rounds,
                                camera=(camera_model, smooth, orbit_tolerance))
    Sbar = (S * vis[:, None, :]).sum(0) / np.maximum(vis.sum(0), 1)
    Phi = _features(X.reshape(F, 2, P)[int(np.argmax(vis.sum(1)))].T, beta, landmarks, seed)
    C = field_fit(Phi, (S - Sbar[None]).transpose(0, 2, 1), vis, lam)
    J = np.flatnonzero(~vis.all(axis=0))                # hidden points take the 3-D field
    S[:, :, J] = np.where(vis[:, None, J], S[:, :, J],
                          (Phi[J] @ C).transpose(0, 2, 1) + Sbar[None, :, J])
    R = complete_rotations(R2)
    pred = R2 @ S
    d = np.linalg.norm(Xc.reshape(F, 2, P) - pred, axis=1)
    resid = float((d * V).sum() / max(V.sum(), 1e-12))
    return NRSfMResult(S=np.einsum('fij,fjp->fpi', R, S), R=R, scale=np.ones(F), t=t,
                       method='cdf', rank=0, residual_px=resid, iterations=it, converged=conv,
                       seconds=time.perf_counter() - t0, camera_model=used)
