"""Prior-free NRSfM (Dai, Li, He; METHODS §1.3) and its scalable smoothed variant (SMSR, §3).

Motion: from a rank-3K factorisation W ~= P_hat B_hat, one column triple G (3K x 3) of the
corrective matrix makes every 2 x 3K block P_hat_f G scaled-orthonormal.  With Q = G G^T the
conditions are linear in Q (a Q a^T - b Q b^T = 0, a Q b^T = 0 per frame, plus a scale);
the rank-3 condition is relaxed to trace minimisation over the PSD cone.  We solve it by
accelerated proximal gradient (FISTA): a gradient step on the squared constraint residuals, then
the prox of the trace over the PSD cone (eigenvalue soft-thresholding) -- the dependency-free
equivalent of the SDP.  Rotations are the polar factors of P_hat_f G with temporally consistent
signs.

Shapes (BMM): min_S 1/2 sum_fp v_fp ||w_fp - R_f s_fp||^2 + lam ||S#||_*, by ADMM with the
splitting Z = S#: a closed-form per-point 3 x 3 least-squares step, singular value thresholding of
F x 3P, a dual step, and a growing penalty.  Linear in P per iteration.

SMSR: the same cameras and shapes on trajectory-smoothed measurements (projection of each point
trajectory onto the first d DCT vectors), the cameras from the smoothed W, the shapes then fitted
to the smoothed W.
"""
from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
from scipy.fft import dct, idct

from ._metric_kernels import fista_psd_trace
from .factorization import _centre, complete_rotations, impute_low_rank
from .result import NRSfMResult, check_tracks


# ------------------------------------------------------------------ cameras

def _constraint_matrices(Phat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear constraints on vec(Q): rows for a Q a^T - b Q b^T and a Q b^T per frame (2F, n^2),
    and the scale row (n^2,) = mean of (a Q a^T + b Q b^T) / 2."""
    a, b = Phat[0::2], Phat[1::2]
    n = a.shape[1]
    aa = np.einsum('fi,fj->fij', a, a)
    bb = np.einsum('fi,fj->fij', b, b)
    ab = np.einsum('fi,fj->fij', a, b)
    ab = (ab + ab.transpose(0, 2, 1)) / 2
    A = np.concatenate([(aa - bb).reshape(-1, n * n), ab.reshape(-1, n * n)])
    c0 = ((aa + bb) / 2).mean(axis=0).reshape(n * n)
    return A, c0


def metric_projection_Q(Phat: np.ndarray, trace_weight: float = 1e-3, iterations: int = 500,
                        tol: float = 1e-12) -> np.ndarray:
    """Trace-minimising PSD Q (n x n) satisfying the orthonormality constraints of every frame
    in the least-squares sense, by FISTA with the PSD trace prox."""
    A, c0 = _constraint_matrices(Phat)
    n = Phat.shape[1]
    m = A.shape[0]
    w0 = float(m)                              # the scale constraint counts like all frames
    H = A.T @ A + w0 * np.outer(c0, c0)
    lin = w0 * c0
    L = float(np.linalg.eigvalsh(H)[-1]) + 1e-12
    step = 1.0 / L
    gamma = trace_weight * L
    Q = np.eye(n).ravel() / max(float(c0 @ np.eye(n).ravel()), 1e-12)
    Q = fista_psd_trace(np.ascontiguousarray(H), lin, Q, step, gamma, iterations, tol)
    return Q.reshape(n, n)


def refine_G(Phat: np.ndarray, G0: np.ndarray) -> np.ndarray:
    """Rank-3 polish of the relaxed solution: Levenberg-Marquardt on G (n x 3) for the
    scale-normalised orthonormality residuals of every frame (exact on noise-free data)."""
    from scipy.optimize import least_squares
    a, b = Phat[0::2], Phat[1::2]
    n = Phat.shape[1]

    def resid(g: np.ndarray) -> np.ndarray:
        G = g.reshape(n, 3)
        aG, bG = a @ G, b @ G
        na, nb = (aG ** 2).sum(1), (bG ** 2).sum(1)
        mean = (na + nb).mean() / 2
        return np.concatenate([(na - nb) / mean, 2 * (aG * bG).sum(1) / mean, [mean - 1.0]])

    def jac(g: np.ndarray) -> np.ndarray:
        G = g.reshape(n, 3)
        aG, bG = a @ G, b @ G
        na, nb = (aG ** 2).sum(1), (bG ** 2).sum(1)
        m = (na + nb).mean() / 2
        F = a.shape[0]
        outer = lambda x, y: (x[:, :, None] * y[:, None, :]).reshape(F, -1)  # noqa: E731
        dm = (outer(a, aG) + outer(b, bG)).mean(axis=0)
        r1 = (na - nb) / m
        r2 = 2 * (aG * bG).sum(1) / m
        J1 = 2 * (outer(a, aG) - outer(b, bG)) / m - r1[:, None] * dm[None] / m
        J2 = 2 * (outer(a, bG) + outer(b, aG)) / m - r2[:, None] * dm[None] / m
        return np.vstack([J1, J2, dm[None]])

    # With more basis shapes than the tracks hold, exact tracks leave a flat valley at the
    # round-off floor along which LM creeps (cost 5e-20 -> 2.5e-20 in 7000 evaluations, 6 s):
    # stop once the cost is below _REFINE_FLOOR and has not halved for _REFINE_STALL calls.
    best = {'cost': np.inf, 'x': G0.ravel().copy(), 'ref': np.inf, 'since': 0}

    def tracked(g: np.ndarray) -> np.ndarray:
        r = resid(g)
        cost = float(r @ r) / 2
        if cost < best['ref'] / 2:
            best.update(ref=cost, since=0)
        else:
            best['since'] += 1
        if cost < best['cost']:
            best.update(cost=cost, x=g.copy())
        if best['cost'] < _REFINE_FLOOR and best['since'] >= _REFINE_STALL:
            raise _Stalled
        return r

    try:
        sol = least_squares(tracked, G0.ravel(), jac=jac, method='lm', xtol=1e-12, ftol=1e-12,
                            max_nfev=200 * (G0.size + 1))
        x = sol.x if 0.5 * float(sol.fun @ sol.fun) <= best['cost'] else best['x']
    except _Stalled:
        x = best['x']
    return x.reshape(n, 3)


_REFINE_FLOOR = 1e-18       # cost (half the squared, scale-free residuals)
_REFINE_STALL = 50


class _Stalled(Exception):
    """refine_G's early stop on a flat valley at the round-off floor."""


def consistent_signs(R2: np.ndarray) -> np.ndarray:
    """Flip R_f -> -R_f (the sign of the coefficient) so consecutive frames agree: the flip of
    frame f is the product of the signs of all consecutive overlaps up to f."""
    d = np.einsum('fij,fij->f', R2[1:], R2[:-1])
    c = np.concatenate([[1.0], np.cumprod(np.where(d < 0, -1.0, 1.0))])
    return R2 * c[:, None, None]


def dai_rotations(Wc: np.ndarray, V: np.ndarray, K: int, trace_weight: float = 1e-3
                  ) -> np.ndarray:
    """Orthographic cameras R2 (F, 2, 3) from centred tracks Wc (2F, P)."""
    F, P = V.shape
    if K < 1 or 9 * K > 2 * F + 1 or 3 * K > min(2 * F, P):
        raise ValueError(f'rank={K}: the motion factorisation needs 9K <= 2F + 1 and '
                         f'3K <= min(2F, P) (F={F}, P={P})')
    X = impute_low_rank(Wc, V, 3 * K) if (V < 0.5).any() else Wc
    if X.shape[1] > X.shape[0]:          # wide (dense tracks): the 2F x 2F Gram matrix
        lam, U = np.linalg.eigh(X @ X.T)
        U, s = U[:, ::-1], np.sqrt(np.maximum(lam[::-1], 0.0))
    else:
        U, s, _ = np.linalg.svd(X, full_matrices=False)
    r = min(3 * K, s.size)
    U = U[:, :r] * np.sign(U[np.abs(U[:, :r]).argmax(axis=0), np.arange(r)])   # (reproducible)
    Phat = U * np.sqrt(s[:r])
    Phat = Phat / np.sqrt(np.mean(Phat ** 2))        # unit scale helps the conditioning
    G = refine_G(Phat, start_G(metric_projection_Q(Phat, trace_weight)))
    M = (Phat @ G).reshape(F, 2, 3)
    Uo, _, Vt = np.linalg.svd(M, full_matrices=False)
    return consistent_signs(Uo @ Vt)


NULL_RATIO = 1e-6   # an eigenvalue of Q below this x its largest: a direction Q leaves unset


def start_G(Q: np.ndarray) -> np.ndarray:
    """The start (n x 3) of ``refine_G`` from the trace-minimising Q: its top three
    eigenvectors scaled by the roots of their eigenvalues, made reproducible.  eigh's output
    is fixed only up to each eigenvector's sign, and where Q has rank < 3 (the camera motion
    leaves a direction unobserved) its third eigenvector is any vector of Q's null space.
    Here each column's largest entry is positive and an unset direction is the projection of
    a fixed vector on the null space (spanned stably: the gap to the set eigenvalues is
    large).  With the signs of ``dai_rotations``' motion basis fixed too, 1e-12 changes of
    the tracks change the cameras by 1e-9 up to one global rotation (the metric upgrade's
    gauge), where they flipped frames and moved ``cdf``'s shapes by 33% before."""
    lam, E = np.linalg.eigh((Q + Q.T) / 2)
    n = E.shape[0]
    top = E[:, -3:].copy()
    set_ = lam[-3:] > NULL_RATIO * max(float(lam[-1]), 1e-300)
    if not set_.all():
        k = int(set_.sum())                     # eigenvectors of the set eigenvalues
        N = E[:, :n - k]                        # the rest: Q's (near-)null space
        fixed = np.stack([np.ones(n), np.arange(1.0, n + 1)])
        for j in range(3 - k):
            v = N @ (N.T @ fixed[j % 2])
            for prev in range(j):               # orthogonal to the ones already chosen
                v -= top[:, prev] * (top[:, prev] @ v)
            top[:, j] = v / max(float(np.linalg.norm(v)), 1e-300)
    top *= np.sign(top[np.abs(top).argmax(axis=0), np.arange(3)])
    return top * np.sqrt(np.maximum(lam[-3:], 1e-12))


AUTO_RANKS = (2, 3, 4, 5, 6)


def averaged_rotations(Wc: np.ndarray, V: np.ndarray, ranks=AUTO_RANKS,
                       trace_weight: float = 1e-3) -> np.ndarray:
    """Cameras from several motion ranks K, aligned to the first by one orthogonal matrix and a
    per-frame sign, averaged and re-orthonormalised.  Which K gives the best cameras varies by
    sequence (measured on the mocap sets: up to 2x in e3D); the average is within reach of the
    best single K everywhere, so the default needs no per-dataset rank."""
    F, P = V.shape
    r = exact_rank(Wc) if (V >= 0.5).all() else min(Wc.shape)
    ranks = [K for K in ranks if 9 * K <= 2 * F + 1 and 3 * K <= min(2 * F, P, r)] or \
        [max(1, min(r // 3, (2 * F + 1) // 9))]
    Rs = [dai_rotations(Wc, V, K, trace_weight) for K in ranks]
    ref = Rs[0]
    acc = np.zeros_like(ref)
    for R2 in Rs:
        U, _, Vt = np.linalg.svd(np.einsum('fki,fkj->ij', R2, ref))
        R2 = R2 @ (U @ Vt)
        acc += R2 * np.sign(np.einsum('fij,fij->f', R2, ref))[:, None, None]
    U, _, Vt = np.linalg.svd(acc, full_matrices=False)
    return consistent_signs(U @ Vt)


# ------------------------------------------------------------------ shapes

def _svt(X: np.ndarray, tau: float) -> np.ndarray:
    """Singular value soft-thresholding of X (F, N), through the F x F Gram when F < N."""
    F, N = X.shape
    if F <= N:
        lam, E = np.linalg.eigh(X @ X.T)
        s = np.sqrt(np.maximum(lam, 0.0))
        keep = s > tau
        if not keep.any():
            return np.zeros_like(X)
        E, s = E[:, keep], s[keep]
        return (E * ((s - tau) / s)) @ (E.T @ X)
    lam, E = np.linalg.eigh(X.T @ X)
    s = np.sqrt(np.maximum(lam, 0.0))
    keep = s > tau
    if not keep.any():
        return np.zeros_like(X)
    E, s = E[:, keep], s[keep]
    return ((X @ E) * ((s - tau) / s)) @ E.T


def second_difference_banded(F: int, mu: float, rho: float) -> np.ndarray:
    """Upper banded form (3, F) of mu D^T D + rho I, D the (F-2) x F second difference, for
    ``scipy.linalg.solveh_banded``."""
    ab = np.zeros((3, F))
    if F >= 3:
        w = np.array([1.0, -2.0, 1.0])
        diag = np.zeros(F)
        off1 = np.zeros(F - 1)
        off2 = np.zeros(F - 2)
        for a in range(3):
            diag[a:F - 2 + a] += w[a] ** 2
        for a in range(2):
            off1[a:F - 2 + a] += w[a] * w[a + 1]
        off2[:] = w[0] * w[2]
        ab[2] = mu * diag
        ab[1, 1:] = mu * off1
        ab[0, 2:] = mu * off2
    ab[2] += rho
    return ab


ADMM_DTYPE = np.float32   # the ADMM's arrays (bmm_shapes' ``dtype``): see bmm_shapes


def _svt_into(X: np.ndarray, tau: float, out: np.ndarray) -> None:
    """``_svt(X, tau)`` written into ``out`` (X's shape and dtype, not X), for F <= N: the
    F x F Gram and its eigenvectors in float64 whatever X's dtype, the two products in X's."""
    lam, E = np.linalg.eigh((X @ X.T).astype(np.float64))
    s = np.sqrt(np.maximum(lam, 0.0))
    keep = s > tau
    if not keep.any():
        out[...] = 0.0
        return
    E, s = E[:, keep], s[keep]
    A, B = (E * ((s - tau) / s)).astype(X.dtype), E.T.astype(X.dtype) @ X
    if A.shape[1] == 1:     # NumPy's matmul over an inner dimension of 1 is not BLAS: 1.9 ms
        np.multiply(A, B, out=out)      # against 0.1 ms at F = 80, 3P = 24k (a third of the
    else:                               # face batch's iterations keep one component)
        np.matmul(A, B, out=out)


def bmm_shapes(Wc: np.ndarray, V: np.ndarray, R2: np.ndarray, lam: float = 0.01,
               iterations: int = 300, rho: float = 1e-3, rho_growth: float = 1.2,
               rho_max: float = 1e6, tol: float = 1e-6,
               init: np.ndarray | None = None, smooth: float = 0.0,
               dtype: type = ADMM_DTYPE) -> tuple[np.ndarray, int, bool]:
    """Object-frame shapes (F, 3, P) minimising the visibility-weighted data term plus
    ``lam`` x nuclear norm of S# (``lam`` relative to the data's RMS) plus, with ``smooth`` > 0,
    smooth/2 x the squared second differences of every point's trajectory over frames (the
    trajectory prior of PTA/KSTA, in units of the data's RMS), by consensus ADMM: S (per-point
    closed-form data step) = Z (singular value thresholding) = Y (one banded F x F solve shared
    by every coordinate of every point).

    ``dtype``: the iterates' (F, 3, P) arrays.  float32 (the default) halves the memory every
    iteration streams through and doubles the thresholding's BLAS rate: the shapes equal the
    float64 ones to ~5e-6 relative at the stream's 16-40 iterations (a 320x240 face's batch, 80
    frames x 7.9k tracks), 2x faster (BENCHMARKS issue 17, session 43), and to ~2e-4 after
    100+ iterations: the float32 Gram resolves singular values to ~sqrt(eps32) = 3e-4 of the
    largest, which the threshold tau / rho reaches as rho grows (a float64 Gram keeps 3e-6
    there at 3x its cost).  The small eigenproblems and the residual norms stay in float64;
    the shapes are returned as float64."""
    from scipy.linalg import solveh_banded

    from ._admm import data_step, dual_step
    dt = np.dtype(dtype).type
    F, P = V.shape
    Wf = Wc.reshape(F, 2, P)
    unit = max(float(np.sqrt(np.mean(Wf ** 2))), 1e-12)
    Wf = Wf / unit
    Gm = np.einsum('fki,fkj->fij', R2, R2)
    ev, E = np.linalg.eigh(Gm)                          # (F, 3), (F, 3, 3)
    E, ev = np.ascontiguousarray(E, dt), np.ascontiguousarray(ev, dt)
    Vc = np.ascontiguousarray(V, dt)
    RtW = np.ascontiguousarray((R2.transpose(0, 2, 1) @ Wf) * V[:, None, :], dt)  # (F, 3, P)
    # initial shapes: pseudo-inverse with zero depth
    Z = RtW.copy() if init is None else np.ascontiguousarray(init / unit, dt)
    U = np.zeros_like(Z)
    S, T, Zn = np.empty_like(Z), np.empty_like(Z), np.empty_like(Z)   # reused every iteration
    use_y = smooth > 0 and F >= 3
    Y, U2 = (Z.copy(), np.zeros_like(Z)) if use_y else (None, None)
    tau = lam * np.sqrt(P)
    ab0 = second_difference_banded(F, smooth, 0.0) if use_y else None
    it, converged = 0, False
    for it in range(1, iterations + 1):
        # S-step and T = S + U / rho fused (core/nrsfm/_admm.py); the trajectory prior adds
        # rho Y - U2 to the linear term and rho to the diagonal
        lin = RtW + dt(rho) * Y - U2 if use_y else RtW
        data_step(Z, U, lin, E, ev, Vc, dt(rho), dt((2 if use_y else 1) * rho), dt(1.0 / rho),
                  S, T)
        if F <= 3 * P:
            _svt_into(T.reshape(F, 3 * P), tau / rho, Zn.reshape(F, 3 * P))
        else:
            Zn[...] = _svt(T.reshape(F, 3 * P), tau / rho).reshape(F, 3, P)
        r_primal, r_dual = dual_step(S, Zn, Z, U, dt(rho))
        if use_y:
            ab = ab0.copy()
            ab[2] += rho
            Yn = solveh_banded(ab, (rho * S + U2).reshape(F, 3 * P)).reshape(F, 3, P)
            Yn = Yn.astype(dt, copy=False)
            U2 = U2 + dt(rho) * (S - Yn)
            r_primal = max(r_primal, float(np.linalg.norm(S - Yn)))
            r_dual = max(r_dual, rho * float(np.linalg.norm(Yn - Y)))
            Y = Yn
        Z, Zn = Zn, Z
        rho = min(rho * rho_growth, rho_max)
        if it > 10 and max(r_primal, r_dual) <= tol * max(float(np.linalg.norm(Z)), 1e-12):
            converged = True
            break
    return Z.astype(np.float64) * unit, it, converged


def depth_em(Wc: np.ndarray, R2: np.ndarray, S: np.ndarray, K: int, iterations: int = 500,
             tol: float = 1e-13) -> np.ndarray:
    """Rank-K shapes consistent with the cameras: S_f = R_f^T W_f + n_f d_f^T (n_f the viewing
    direction, d_f the unknown depths), alternating d_f from the rank-K projection of S# and
    the projection itself (exact on noise-free rank-K data, where the nuclear norm's shrinkage
    leaves a bias)."""
    F, P = R2.shape[0], Wc.shape[1]
    n = complete_rotations(R2)[:, 2]
    A = R2.transpose(0, 2, 1) @ Wc.reshape(F, 2, P)
    X = S
    for _ in range(iterations):
        d = np.einsum('fi,fip->fp', n, X)
        X = A + n[:, :, None] * d[:, None, :]
        Xs = X.reshape(F, 3 * P)
        G = Xs @ Xs.T if F <= 3 * P else Xs.T @ Xs
        E = np.linalg.eigh(G)[1][:, -K:]
        Xn = ((E @ (E.T @ Xs)) if F <= 3 * P else (Xs @ E) @ E.T).reshape(F, 3, P)
        change = float(np.linalg.norm(Xn - X)) / max(float(np.linalg.norm(Xn)), 1e-300)
        X = Xn
        if change < tol:
            break
    d = np.einsum('fi,fip->fp', n, X)
    return A + n[:, :, None] * d[:, None, :]


def procrustean_gauge(S: np.ndarray, R: np.ndarray, reweight: int = 5,
                      basis: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Fix the per-frame rotation gauge: rotate every object-frame shape S_f (F, 3, P) onto
    the mean shape by weighted orthogonal Procrustes and move the rotation into the camera
    (R_f Q_f, so R_f S_f is unchanged).  The weights, 1 / (variance of the point about the
    mean + the median variance), re-estimated ``reweight`` times, make the alignment follow
    the least-deforming points (a body's trunk rather than its arms): the deformations keep no
    rotation that the cameras could explain, the Procrustean assumption of PND-style models.
    ``basis`` (r, P): S is given in reduced coordinates (the points are S @ basis)."""
    Sp = S if basis is None else S @ basis
    w = np.ones(Sp.shape[2])
    Q = np.broadcast_to(np.eye(3), (S.shape[0], 3, 3))
    for _ in range(max(1, reweight)):
        M = np.einsum('fip,jp->fij', Sp * w, Sp.mean(0))
        U, _, Vt = np.linalg.svd(M)
        U[:, :, 2] *= np.sign(np.linalg.det(U @ Vt))[:, None]
        Q = U @ Vt                                           # S_f ~= Q_f mean
        A = np.einsum('fji,fjp->fip', Q, Sp)
        var = ((A - A.mean(0)) ** 2).sum(1).mean(0)
        w = 1.0 / (var + max(float(np.median(var)), 1e-300))
    return np.einsum('fji,fjp->fip', Q, S), R @ Q


def orbit_cameras(R: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Fit a constant-rate orbit R_f = exp(f [w]x) R_0 to rotations R (F, 3, 3) -- the camera
    of a turntable, an orbiting rig, a steady pan -- by rotation averaging (chordal L2 mean of
    the frame-to-frame rotations for w, then of exp(-f [w]x) R_f for R_0).  Returns the orbit
    (F, 3, 3), the mean angle (degrees) between it and R, and the dispersion of the
    frame-to-frame rotations about w relative to its angle (mean over frames; 0 for a perfect
    orbit, inf for a still camera)."""
    from scipy.spatial.transform import Rotation
    F = R.shape[0]
    R = R * np.sign(np.linalg.det(R))[:, None, None]
    rel = Rotation.from_matrix(R[1:] @ R[:-1].transpose(0, 2, 1))
    mean = rel.mean()
    rate = float(mean.magnitude())
    dispersion = float((rel * mean.inv()).magnitude().mean()) / rate if rate > 0 else np.inf
    E = Rotation.from_rotvec(np.arange(F)[:, None] * mean.as_rotvec()[None])
    R0 = (E.inv() * Rotation.from_matrix(R)).mean()
    Ro = (E * R0).as_matrix()
    cos = (np.einsum('fij,fij->f', Ro, R) - 1) / 2
    return Ro, float(np.degrees(np.arccos(np.clip(cos, -1, 1))).mean()), dispersion


CAMERA_MODELS = ('auto', 'free', 'orbit')
ORBIT_SMOOTH = 100.0
ORBIT_MAX_DEVIATION = 15.0     # degrees: 'auto' never moves a camera further on average


def _choose_cameras(R2: np.ndarray, camera_model: str, smooth: float | None,
                    orbit_tolerance: float) -> tuple[np.ndarray, str, float]:
    """The camera trajectory model and the weight of the shapes' trajectory prior.

    'orbit' replaces the per-frame cameras R2 by their constant-rate orbit fit; 'auto' does
    so when the frame-to-frame rotations of R2 agree with their mean within ``orbit_tolerance``
    (relative dispersion, see ``orbit_cameras``) and the orbit lies within
    ``ORBIT_MAX_DEVIATION`` degrees of R2 on average.  The cameras of a turntable or an
    orbiting rig, estimated frame by frame, have accurate frame-to-frame rotations (dispersion
    0.015-0.045 on the Akhter mocap sets) but drift slowly by a few degrees, the part that the
    gauge (subject rotation against camera rotation) leaves undetermined; the orbit removes
    that drift.  A hand-held or free-moving camera has dispersions from 0.5 up.  Returns the
    cameras, the model used and the trajectory prior weight: ``smooth``, or by default
    ``ORBIT_SMOOTH`` with orbit cameras and 0 with free ones (the prior acts in the object
    frame, where the jitter of free per-frame cameras would be smoothed into the shapes)."""
    used = 'free'
    if camera_model != 'free' and R2.shape[0] >= 3:
        Ro, dev, dispersion = orbit_cameras(complete_rotations(R2))
        if camera_model == 'orbit' or (dispersion <= orbit_tolerance
                                       and dev <= ORBIT_MAX_DEVIATION):
            R2, used = Ro[:, :2], 'orbit'
    mu = smooth if smooth is not None else (ORBIT_SMOOTH if used == 'orbit' else 0.0)
    return R2, used, float(mu)


def check_camera_args(camera_model: str, smooth: float | None, orbit_tolerance: float) -> None:
    if camera_model not in CAMERA_MODELS:
        raise ValueError(f'camera_model={camera_model!r}: expected one of {CAMERA_MODELS}')
    if smooth is not None and not smooth >= 0:
        raise ValueError(f'smooth: expected >= 0 (or None: automatic), got {smooth}')
    if not orbit_tolerance >= 0:
        raise ValueError(f'orbit_tolerance: expected >= 0 (relative dispersion of the '
                         f'frame-to-frame rotations), got {orbit_tolerance}')


def exact_rank(Wc: np.ndarray, rel: float = 1e-11) -> int:
    """Numerical rank of W (relative threshold near float precision): 3K on noise-free
    rank-K data, full on measured tracks."""
    s = np.linalg.svd(Wc, compute_uv=False)
    return int((s > rel * s[0]).sum())


# ------------------------------------------------------------------ methods

def _finish(Wc: np.ndarray, V: np.ndarray, R2: np.ndarray, S_obj: np.ndarray, t: np.ndarray,
            method: str, rank: int, it: int, conv: bool, t0: float,
            camera_model: str = 'free') -> NRSfMResult:
    F, P = V.shape
    R = complete_rotations(R2)
    S_cam = np.einsum('fij,fjp->fpi', R, S_obj)
    pred = R2 @ S_obj
    d = np.linalg.norm(Wc.reshape(F, 2, P) - pred, axis=1)
    resid = float((d * V).sum() / max(V.sum(), 1e-12))
    return NRSfMResult(S=S_cam, R=R, scale=np.ones(F), t=t, method=method, rank=rank,
                       residual_px=resid, iterations=it, converged=conv,
                       seconds=time.perf_counter() - t0, camera_model=camera_model)


def noise_level(Wc: np.ndarray, rank: int = 12) -> float:
    """Relative RMS of W outside its best rank-``rank`` approximation: the part no low-rank
    motion explains (noise and model error), 0 on exact data."""
    s = np.linalg.svd(Wc, compute_uv=False)
    return float(np.sqrt((s[rank:] ** 2).sum() / max((s ** 2).sum(), 1e-300)))


def _gauge_rounds(Wc: np.ndarray, V: np.ndarray, R2: np.ndarray, S: np.ndarray, lam: float,
                  iterations: int, rounds: int, basis: np.ndarray | None = None,
                  camera: tuple[str, float | None, float] = ('free', None, 0.0)
                  ) -> tuple[np.ndarray, np.ndarray, str]:
    """``rounds`` x (Procrustean gauge, then the nuclear-norm shapes for the new cameras); the
    camera model ``camera`` = (camera_model, smooth, orbit_tolerance) of ``_choose_cameras``
    applies to the last round's cameras (the shapes are solved once for them).  Returns the
    cameras, the shapes and the camera model used."""
    used, mu = 'free', 0.0

    def solve(R2: np.ndarray, S: np.ndarray, mu: float) -> np.ndarray:
        if mu <= 0:
            return bmm_shapes(Wc, V, R2, lam, iterations, init=S)[0]
        # warm start from the gauged shapes: a 10x larger first penalty and 0.4x the
        # iterations give the same shapes (measured on the mocap sets: metric A within 1e-4
        # of 100 iterations from 1e-3)
        return bmm_shapes(Wc, V, R2, lam, max(1, int(0.4 * iterations)), rho=1e-2, init=S,
                          smooth=mu)[0]

    for i in range(rounds):
        S, R = procrustean_gauge(S, complete_rotations(R2), basis=basis)
        R2 = R[:, :2]
        if i == rounds - 1:
            R2, used, mu = _choose_cameras(R2, *camera)
        S = solve(R2, S, mu)
    if rounds == 0:
        R2, used, mu = _choose_cameras(R2, *camera)
        if used == 'orbit' or mu > 0:
            S = solve(R2, S, mu)
    return R2, S, used


def row_space(Wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Wc (2F, P) = Wr @ B with B (r, P) orthonormal rows spanning the row space of Wc (r <=
    2F) and Wr = Wc B^T (2F, r).

    With every track visible, the nuclear-norm shapes lie in that row space (per coordinate):
    the data term cannot see components outside it and removing them does not increase the
    nuclear norm (a right projection).  So cameras and shapes are solved for r "points" and
    mapped back by B -- the cost becomes independent of P after one pass over W.  The basis
    comes from the 2F x 2F Gram matrix (4x faster than a thin SVD at 100k points); directions
    with singular values below 1e-7 of the largest, where the Gram matrix's rounding dominates,
    are dropped (they change W by less than 1e-7 relative)."""
    lam, U = np.linalg.eigh(Wc @ Wc.T)
    if not lam[-1] > 0:
        raise ValueError('W: the centred tracks are all zero (after filling hidden entries): '
                         'the points never spread apart in the image, or no entry is visible '
                         '(V >= 0.5); nothing to factorise')
    keep = lam > 1e-14 * max(float(lam[-1]), 1e-300)
    U, s = U[:, keep][:, ::-1], np.sqrt(lam[keep])[::-1]
    B = (U.T @ Wc) / s[:, None]
    return Wc @ B.T, B


WARM_FRACTION = 0.4   # bmm_warm: this x the iterations for the shapes from the start


def _motion_and_shapes(Wc: np.ndarray, X: np.ndarray, V: np.ndarray, rank: int, lam: float,
                       iterations: int, trace_weight: float, gauge_rounds: int,
                       camera: tuple[str, float | None, float] = ('free', None, 0.0),
                       start: tuple[np.ndarray, np.ndarray] | None = None
                       ) -> tuple[np.ndarray, np.ndarray, int, bool, str]:
    """Cameras R2 and object-frame shapes S (F, 3, P) for centred tracks Wc (2F, P) with
    visibility V; X is Wc with the hidden entries imputed (the shapes' starting point);
    ``camera`` = (camera_model, smooth, orbit_tolerance) of ``_choose_cameras``; ``start`` =
    (R2, S): cameras and object-frame shapes to start from instead of the metric projection
    and X (``bmm_warm``): the first shapes then take ``WARM_FRACTION`` x ``iterations`` from a
    10x larger first penalty."""
    return _staged_motion_and_shapes(Wc, X, V, rank, lam, iterations, trace_weight,
                                     gauge_rounds, camera, start)[1]()


def _staged_motion_and_shapes(Wc: np.ndarray, X: np.ndarray, V: np.ndarray, rank: int,
                              lam: float, iterations: int, trace_weight: float,
                              gauge_rounds: int, camera: tuple[str, float | None, float],
                              start: tuple[np.ndarray, np.ndarray] | None
                              ) -> tuple[tuple[np.ndarray, np.ndarray],
                                         Callable[[], tuple[np.ndarray, np.ndarray, int, bool,
                                                           str]]]:
    """``_motion_and_shapes`` in two stages: ((R2, S) after the first nuclear-norm shapes,
    before the bias removal or the gauge rounds; a function that completes them into
    ``_motion_and_shapes``' result)."""
    F, P = V.shape
    full = bool((V >= 0.5).all())
    basis = None
    if full and P > 2 * F:
        Wc, basis = row_space(Wc)
        X, V = Wc, np.ones((F, Wc.shape[1]))
    lam_abs = lam * max(noise_level(X), 1e-4)
    if start is None:
        R2 = dai_rotations(Wc, V, rank, trace_weight) if rank else \
            averaged_rotations(Wc, V, trace_weight=trace_weight)
        init = R2.transpose(0, 2, 1) @ X.reshape(F, 2, -1)     # hidden tracks start imputed
        S, it, conv = bmm_shapes(Wc, V, R2, lam_abs, iterations, init=init)
    else:
        R2, init = start
        S, it, conv = bmm_shapes(Wc, V, R2, lam_abs, max(1, int(WARM_FRACTION * iterations)),
                                 rho=1e-2, init=init if basis is None else init @ basis.T)

    def rest() -> tuple[np.ndarray, np.ndarray, int, bool, str]:
        R2_, S_ = R2, S
        r = exact_rank(X) if full else min(X.shape)   # (imputation lowers the rank)
        used = 'free'
        if r <= 3 * max(AUTO_RANKS) and r < min(2 * F, P - 1):
            # noise-free low-rank data (centring costs one rank): remove the shrinkage bias
            S_ = depth_em(X, R2_, S_, max(1, -(-r // 3)))
        else:
            # (a warm start keeps the gauge round's cold penalty: warm-started too, 16
            # iterations, the face at 60 deg amplitude 2 on ground-truth tracks went 0.048 ->
            # 0.059, above static 0.054)
            R2_, S_, used = _gauge_rounds(Wc, V, R2_, S_, lam_abs, iterations, gauge_rounds,
                                          basis, camera)
        return R2_, (S_ if basis is None else S_ @ basis), it, conv, used
    return (R2, S if basis is None else S @ basis), rest


def bmm(W: np.ndarray, V: np.ndarray | None = None, rank: int = 0, lam: float = 4.0,
        iterations: int = 100, trace_weight: float = 1e-3, gauge_rounds: int = 1,
        camera_model: str = 'auto', smooth: float | None = None, orbit_tolerance: float = 0.1
        ) -> NRSfMResult:
    """Dai-Li-He prior-free NRSfM: trace-minimising metric projection for the cameras, then
    nuclear-norm shapes (BMM) by ADMM.  ``rank`` is K of the motion factorisation (3K), 0 to
    average the cameras over K = 2..6 (default); the shapes' rank follows from the nuclear
    norm.  ``gauge_rounds``: rounds of the Procrustean gauge (``procrustean_gauge``: each
    frame's rotation relative to the robust mean shape goes into its camera) followed by the
    shapes for the new cameras; 0 keeps the metric projection's cameras.  ``camera_model``
    ('auto', 'free', 'orbit'), ``smooth`` (trajectory prior weight; None: automatic) and
    ``orbit_tolerance``: see ``_choose_cameras``; the result's ``camera_model`` says
    which cameras were used."""
    t0 = time.perf_counter()
    W, V = check_tracks(W, V)
    if rank < 0:
        raise ValueError(f'rank: expected >= 0 (0: automatic), got {rank}')
    if lam < 0:
        raise ValueError(f'lam: expected >= 0, got {lam}')
    if gauge_rounds < 0:
        raise ValueError(f'gauge_rounds: expected >= 0, got {gauge_rounds}')
    check_camera_args(camera_model, smooth, orbit_tolerance)
    Wc, t = _centre(W, V)
    X = impute_low_rank(Wc, V, 12) if (V < 0.5).any() else Wc
    R2, S, it, conv, used = _motion_and_shapes(Wc, X, V, rank, lam, iterations, trace_weight,
                                               gauge_rounds,
                                               (camera_model, smooth, orbit_tolerance))
    return _finish(Wc, V, R2, S, t, 'bmm', rank, it, conv, t0, used)


def bmm_warm(W: np.ndarray, V: np.ndarray | None, start: NRSfMResult, lam: float = 4.0,
             iterations: int = 100, gauge_rounds: int = 1, camera_model: str = 'auto',
             smooth: float | None = None, orbit_tolerance: float = 0.1) -> NRSfMResult:
    """``bmm`` of tracks close to those ``start`` (a ``bmm`` result, either depth reflection)
    explains -- the perspective iteration's corrected measurements: its cameras and shapes
    replace the metric projection's cameras and the pseudo-inverse start, and the shapes
    take ``WARM_FRACTION`` x ``iterations`` from a 10x larger first penalty (the warm start
    of the gauge round), then the same gauge rounds and camera model as ``bmm``.  The metric
    projection (cameras over K = 2..6) is most of ``bmm``'s cost at a few thousand tracks."""
    return bmm_warm_staged(W, V, start, lam, iterations, gauge_rounds, camera_model, smooth,
                           orbit_tolerance)[1]()


def bmm_warm_staged(W: np.ndarray, V: np.ndarray | None, start: NRSfMResult,
                    lam: float = 4.0, iterations: int = 100, gauge_rounds: int = 1,
                    camera_model: str = 'auto', smooth: float | None = None,
                    orbit_tolerance: float = 0.1
                    ) -> tuple[NRSfMResult, Callable[[], NRSfMResult]]:
    """``bmm_warm`` in two stages: (its solution after the warm shapes, before the gauge
    rounds -- a proxy for choosing between starts, e.g. the perspective step's two depth
    reflections, at a fraction of the cost; a function that completes it into exactly
    ``bmm_warm``'s result)."""
    t0 = time.perf_counter()
    W, V = check_tracks(W, V)
    F, P = V.shape
    if start.S.shape != (F, P, 3) or start.R.shape != (F, 3, 3):
        raise ValueError(f'start: expected shapes (F, P, 3) = {(F, P, 3)} and cameras '
                         f'(F, 3, 3), got {start.S.shape} and {start.R.shape}')
    check_camera_args(camera_model, smooth, orbit_tolerance)
    Wc, t = _centre(W, V)
    X = impute_low_rank(Wc, V, 12) if (V < 0.5).any() else Wc
    # a reflected start carries R = diag(1, 1, -1) R (improper): the same solution with proper
    # cameras is R diag(1, 1, -1) and object shapes R^T S
    R = np.array(start.R, dtype=np.float64)
    R[np.linalg.det(R) < 0, :, 2] *= -1.0
    R2, S = np.ascontiguousarray(R[:, :2]), (start.S @ R).transpose(0, 2, 1)   # (F, 3, P)
    (R2e, Se), rest = _staged_motion_and_shapes(Wc, X, V, 0, lam, iterations, 0.0,
                                                 gauge_rounds,
                                                 (camera_model, smooth, orbit_tolerance),
                                                 (R2, S))
    early = _finish(Wc, V, R2e, Se, t, 'bmm', 0, 0, False, t0)

    def finish() -> NRSfMResult:
        R2f, Sf, it, conv, used = rest()
        return _finish(Wc, V, R2f, Sf, t, 'bmm', 0, it, conv, t0, used)
    return early, finish


def dct_smooth(Wc: np.ndarray, d: int) -> np.ndarray:
    """Project every point trajectory (each coordinate over frames) of complete tracks
    Wc (2F, P) onto the first ``d`` DCT-II vectors (impute hidden entries first)."""
    F = Wc.shape[0] // 2
    X = Wc.reshape(F, 2, -1)
    C = dct(X, norm='ortho', axis=0)
    C[d:] = 0.0
    return idct(C, norm='ortho', axis=0).reshape(2 * F, -1)


def smsr(W: np.ndarray, V: np.ndarray | None = None, rank: int = 0, lam: float = 4.0,
         dct_fraction: float = 0.3, iterations: int = 100, trace_weight: float = 1e-3
         ) -> NRSfMResult:
    """SMSR-style: DCT trajectory smoothing of W (first ``dct_fraction`` x F vectors), cameras
    by the trace-prox metric projection, nuclear-norm ADMM shapes on the smoothed tracks."""
    t0 = time.perf_counter()
    W, V = check_tracks(W, V)
    if rank < 0:
        raise ValueError(f'rank: expected >= 0 (0: automatic), got {rank}')
    if not 0 < dct_fraction <= 1:
        raise ValueError(f'dct_fraction: expected (0, 1], got {dct_fraction}')
    F = V.shape[0]
    Wc, t = _centre(W, V)
    X = impute_low_rank(Wc, V, 3 * (rank or 4)) if (V < 0.5).any() else Wc
    d = max(2, int(round(dct_fraction * F)))
    Ws = dct_smooth(X, d)
    R2, S, it, conv, _ = _motion_and_shapes(Ws, Ws, np.ones_like(V), rank, lam, iterations,
                                            trace_weight, 0)
    return _finish(Wc, V, R2, S, t, 'smsr', rank, it, conv, t0)
