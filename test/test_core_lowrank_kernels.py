"""``factorization.low_rank``'s kernels (core/nrsfm/_lowrank_kernels.py) and the sliding
window's shortcuts against the NumPy forms they replaced."""
from __future__ import annotations

import numpy as np
import pytest

from nrsfm_ros.core.nrsfm import _lowrank_kernels as K
from nrsfm_ros.core.nrsfm.factorization import (complete_rotations, low_rank, rigid,
                                                scaled_orthonormal)
from nrsfm_ros.core.nrsfm.result import NRSfMResult
from nrsfm_ros.core.nrsfm.stream import StreamNRSfM, StreamShape, _depth_agreement, _Frame


def _procrustes_cameras(Wc, V, S):
    """Per frame, s_f R_f for w_fp ~= s R S_fp, shapes S (F, 3, P): the array form of the
    factorisation's camera step before it kept only the rigid case."""
    F = V.shape[0]
    Wf = Wc.reshape(F, 2, -1)
    SV = S * V[:, None, :]
    SSt = S @ SV.transpose(0, 2, 1)
    SSt = SSt + (1e-12 * np.trace(SSt, axis1=1, axis2=2) + 1e-300)[:, None, None] * np.eye(3)
    M = np.linalg.solve(SSt, (Wf @ SV.transpose(0, 2, 1)).transpose(0, 2, 1)).transpose(0, 2, 1)
    return scaled_orthonormal(M)


def _residual(Wc, V, R2, scale, S):
    """The mean image distance of the visible entries, shapes S (F, 3, P)."""
    F = V.shape[0]
    r = Wc.reshape(F, 2, -1) - (R2 * scale[:, None, None]) @ S
    return float((np.hypot(r[:, 0], r[:, 1]) * V).sum() / max(V.sum(), 1e-12))


def numpy_low_rank(W, V, rank, iterations, init=None, rho=1e-2, rho_growth=1.15, tol=1e-7):
    """The array form of ``low_rank`` before its kernels (the code of 5d251fc)."""
    F, P = V.shape
    base = rigid(W, V) if init is None else init
    R2, scale, t = base.R[:, :2], base.scale, base.t
    Z = np.einsum('fji,fpj->fip', base.R, base.S)
    unit = max(float(np.sqrt(np.mean(((W.reshape(F, 2, P) - t[:, :, None]) ** 2)))), 1e-12)
    Wf, tn, Z = W.reshape(F, 2, P) / unit, t / unit, Z / unit
    prev, it = np.inf, 0
    for it in range(1, iterations + 1):
        Wc = Wf - tn[:, :, None]
        sR = R2 * scale[:, None, None]
        lam, E = np.linalg.eigh(np.einsum('fki,fkj->fij', sR, sR))
        rhs = (sR.transpose(0, 2, 1) @ Wc) * V[:, None, :] + rho * Z
        S = E @ ((E.transpose(0, 2, 1) @ rhs) / (rho + lam[:, :, None] * V[:, None, :]))
        Ss = S.reshape(F, 3 * P)
        Ek = np.linalg.eigh(Ss @ Ss.T)[1][:, -rank:]
        Z = (Ek @ (Ek.T @ Ss)).reshape(F, 3, P)
        R2, scale = _procrustes_cameras(Wc, V, Z)
        pred = (R2 * scale[:, None, None]) @ Z
        tn = ((Wf - pred) * V[:, None, :]).sum(axis=2) / np.maximum(V.sum(axis=1), 1e-12)[:, None]
        err = float(np.sum(V[:, None, :] * (Wf - tn[:, :, None] - pred) ** 2))
        rho *= rho_growth
        if abs(prev - err) <= tol * max(err, 1e-12) and it > 5:
            break
        prev = err
    R = complete_rotations(R2)
    res = _residual((Wf - tn[:, :, None]).reshape(2 * F, P) * unit, V, R2, scale, Z * unit)
    return np.einsum('fij,fjp->fpi', R, Z * unit), tn * unit, res, it


@pytest.fixture
def window():
    """15 frames of a deforming shape (two modes) under a turning camera, soft visibility
    with some tracks nearly hidden."""
    rng = np.random.default_rng(3)
    F, P = 15, 800
    B = rng.normal(size=(3, 3, P))
    t = np.linspace(0.0, 1.0, F)
    S = B[0] + 0.1 * np.sin(3 * t)[:, None, None] * B[1] \
        + 0.05 * np.cos(2 * t)[:, None, None] * B[2]
    W = np.empty((2 * F, P))
    for f, a in enumerate(np.linspace(0.0, 0.5, F)):
        R = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0]])
        W[2 * f:2 * f + 2] = 90.0 * R @ S[f] + [[160.0], [120.0]] + rng.normal(0, 0.3, (2, P))
    V = np.clip(rng.random((F, P)) * 1.6, 1e-3, 1.0)
    V[4, :300] = 1e-3
    return W, V


def test_low_rank_equals_its_array_form_cold_and_warm(window):
    W, V = window
    S_ref, t_ref, res_ref, it_ref = numpy_low_rank(W, V, 2, 60)
    cold = low_rank(W, V, rank=2, iterations=60)
    assert cold.iterations == it_ref
    scale = np.abs(S_ref).max()
    assert np.abs(cold.S - S_ref).max() <= 1e-9 * scale
    assert np.abs(cold.t - t_ref).max() <= 1e-9 * np.abs(t_ref).max()
    assert cold.residual_px == pytest.approx(res_ref, rel=1e-9)
    S_ref, t_ref, res_ref, it_ref = numpy_low_rank(W, V, 3, 10, init=cold)
    warm = low_rank(W, V, rank=3, iterations=10, init=cold)
    assert warm.iterations == it_ref
    assert np.abs(warm.S - S_ref).max() <= 1e-9 * scale
    assert warm.residual_px == pytest.approx(res_ref, rel=1e-9)
    assert warm.residual_px < 1.0          # the tracks' noise is 0.3 px: a real fit


def test_kernels_equal_the_sums_they_replace(window):
    W, V = window
    rng = np.random.default_rng(0)
    F, P = V.shape
    Wf = np.ascontiguousarray(W.reshape(F, 2, P) / 50.0)
    tn, sR = rng.normal(size=(F, 2)), rng.normal(size=(F, 2, 3))
    lam, E = np.linalg.eigh(np.einsum('fki,fkj->fij', sR, sR))
    A, B = rng.normal(size=(F, 2)), rng.normal(size=(2, 3, P))
    Z = (A @ B.reshape(2, -1)).reshape(F, 3, P)
    u = Wf - tn[:, :, None]
    rhs = (sR.transpose(0, 2, 1) @ u) * V[:, None, :] + 0.3 * Z
    S = E @ ((E.transpose(0, 2, 1) @ rhs) / (0.3 + lam[:, :, None] * V[:, None, :]))
    np.testing.assert_allclose(K.shape_step(Wf, V, tn, sR, E, lam, Z, 0.3), S, atol=1e-11)
    n, su, suu, sz, suz, szz = K.frame_moments(Wf, V, tn, Z)
    np.testing.assert_allclose(n, V.sum(axis=1), rtol=1e-12)
    np.testing.assert_allclose(su, (u * V[:, None]).sum(axis=2), rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(suu, (u ** 2 * V[:, None]).sum(axis=(1, 2)), rtol=1e-10)
    np.testing.assert_allclose(sz, (Z * V[:, None]).sum(axis=2), rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(suz, u @ (Z * V[:, None]).transpose(0, 2, 1), rtol=1e-10,
                               atol=1e-9)
    np.testing.assert_allclose(szz, Z @ (Z * V[:, None]).transpose(0, 2, 1), rtol=1e-10,
                               atol=1e-9)
    scale = np.linalg.norm(sR, axis=2).mean(axis=1)
    R2 = sR / scale[:, None, None]
    assert K.mean_distance(Wf, V, tn, sR, Z) == pytest.approx(
        _residual(u.reshape(2 * F, P), V, R2, scale, Z), rel=1e-12)
    # the cameras, translations, error and next eigenbases from the moments
    R2k, sk, tk, Ek, lk, err = K.camera_update(n, su, suu, sz, suz, szz, tn)
    R2n, sn = _procrustes_cameras(u.reshape(2 * F, P), V, Z)
    np.testing.assert_allclose(R2k, R2n, atol=1e-10)
    np.testing.assert_allclose(sk, sn, rtol=1e-10)
    pred = (R2n * sn[:, None, None]) @ Z
    t_ref = ((Wf - pred) * V[:, None]).sum(axis=2) / V.sum(axis=1)[:, None]
    np.testing.assert_allclose(tk, t_ref, rtol=1e-9, atol=1e-9)
    assert err == pytest.approx(float((V[:, None] * (Wf - t_ref[:, :, None] - pred) ** 2).sum()),
                                rel=1e-9)
    sRn = R2n * sn[:, None, None]
    np.testing.assert_allclose(Ek @ (lk[:, :, None] * Ek.transpose(0, 2, 1)),
                               sRn.transpose(0, 2, 1) @ sRn, atol=1e-9)


def _frames(ids_per_frame, rng):
    return [_Frame(i, ids, rng.normal(size=(ids.size, 2)), 0.5 + 0.5 * rng.random(ids.size))
            for i, ids in enumerate(ids_per_frame)]


def test_window_tracks_shortcut_equals_the_general_assembly():
    rng = np.random.default_rng(1)
    ids = np.arange(5, 405, 2)
    same = _frames([ids] * 6, rng)
    # the same frames with their tracks listed in another order take the general path
    perm = rng.permutation(ids.size)
    shuffled = [_Frame(f.index, f.ids[perm], f.uv[perm], f.vis[perm]) for f in same]
    for a, b in zip(StreamNRSfM._tracks(same), StreamNRSfM._tracks(shuffled)):
        np.testing.assert_array_equal(a, b)
    # one frame missing a track: the general path, the track absent (invisible) there
    mixed = same[:3] + _frames([ids[1:]], rng) + same[4:]
    out_ids, W, V = StreamNRSfM._tracks(mixed)
    np.testing.assert_array_equal(out_ids, ids)
    assert V[3, 0] == 0.0 and W[6, 0] == 0.0


def test_depth_agreement_shortcut_equals_the_intersection():
    rng = np.random.default_rng(2)
    ids = np.arange(0, 300, 3)
    X = rng.normal(size=(ids.size, 3))
    sh = StreamShape(0, ids, X + rng.normal(0, 0.1, X.shape), np.zeros(2), 0.0)
    full = _depth_agreement(sh, ids, X)
    keep = np.sort(rng.choice(ids.size, 80, replace=False))
    sub = StreamShape(0, ids[keep], sh.X[keep], np.zeros(2), 0.0)
    part = _depth_agreement(sub, ids, X)
    za, zb = sh.X[keep, 2], X[keep, 2]
    za, zb = za - za.mean(), zb - zb.mean()
    assert part == pytest.approx((za @ zb, np.linalg.norm(za) * np.linalg.norm(zb)))
    za, zb = sh.X[:, 2] - sh.X[:, 2].mean(), X[:, 2] - X[:, 2].mean()
    assert full == pytest.approx((za @ zb, np.linalg.norm(za) * np.linalg.norm(zb)))
    assert full[0] > 0.9 * full[1]         # the same depths up to noise agree
    assert _depth_agreement(StreamShape(0, ids[:3], X[:3], np.zeros(2), 0.0), ids, X) == \
        (0.0, 0.0)
    assert _depth_agreement(sh, ids[:0], X[:0]) == (0.0, 0.0)


def test_low_rank_result_type(window):
    W, V = window
    res = low_rank(W, V, rank=2, iterations=3)
    assert isinstance(res, NRSfMResult) and res.S.shape == (15, 800, 3)
    assert np.isfinite(res.S).all() and res.iterations == 3


def test_metric_projection_fista_equals_the_array_form():
    """bmm's metric projection (its FISTA loop in numba) against the NumPy loop it replaced:
    the same steps, the same Q."""
    import importlib
    bmm = importlib.import_module('nrsfm_ros.core.nrsfm.bmm')
    rng = np.random.default_rng(3)
    for n in (6, 12):
        Phat = rng.standard_normal((40, n))
        A, c0 = bmm._constraint_matrices(Phat)
        w0 = float(A.shape[0])
        H = A.T @ A + w0 * np.outer(c0, c0)
        L = float(np.linalg.eigvalsh(H)[-1]) + 1e-12
        step, gamma = 1.0 / L, 1e-3 * L
        Q = np.eye(n).ravel() / float(c0 @ np.eye(n).ravel())
        Y, t = Q.copy(), 1.0
        for _ in range(200):
            Z = (Y - step * (H @ Y - w0 * c0)).reshape(n, n)
            lam, E = np.linalg.eigh((Z + Z.T) / 2)
            Qn = ((E * np.maximum(lam - step * gamma, 0.0)) @ E.T).ravel()
            t_next = (1 + np.sqrt(1 + 4 * t * t)) / 2
            Y = Qn + ((t - 1) / t_next) * (Qn - Q)
            Q, t = Qn, t_next
        got = bmm.metric_projection_Q(Phat, iterations=200, tol=0.0)
        np.testing.assert_allclose(got, Q.reshape(n, n), rtol=1e-9, atol=1e-12)
        assert np.linalg.eigvalsh(got).min() > -1e-9       # PSD


def test_rigid_camera_step_equals_the_per_frame_form():
    """The rigid factorisation's camera step and residual on its one shape S0 (3, P) (two
    BLAS products) against the per-frame form over the shape repeated in every frame."""
    from nrsfm_ros.core.nrsfm import factorization as fz
    rng = np.random.default_rng(5)
    F, P = 12, 300
    S0 = rng.normal(size=(3, P))
    Wc = rng.normal(size=(2 * F, P))
    V = (rng.uniform(size=(F, P)) > 0.3).astype(float)
    R2, s = fz._rigid_camera_step((Wc.reshape(F, 2, P) * V[:, None, :]).reshape(2 * F, P), V,
                                  S0)
    R2n, sn = _procrustes_cameras(Wc, V, np.broadcast_to(S0, (F, 3, P)))
    np.testing.assert_allclose(R2, R2n, atol=1e-12)
    np.testing.assert_allclose(s, sn, rtol=1e-12)
    assert fz._residual(Wc, V, R2, s, S0) == pytest.approx(
        _residual(Wc, V, R2n, sn, np.broadcast_to(S0, (F, 3, P))), rel=1e-12)
