"""Metric upgrade and rigid factorisation: exact on well-posed data, bounded when degenerate."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nrsfm_ros.core.metrics import e3d_frobenius
from nrsfm_ros.core.nrsfm import reconstruct
from nrsfm_ros.core.nrsfm.factorization import (_centre, _rank3_factors, _rank_project,
                                                _solve_rigid_shape, _upgrade_system,
                                                depth_ratio, impute_low_rank, metric_upgrade,
                                                rigid)
from tests_helpers import low_rank_sequence


def _factors(W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    Wc, _ = _centre(W, np.ones((W.shape[0] // 2, W.shape[1])))
    return _rank3_factors(Wc)


def _wave_sheet(deg: float, amp: float, F: int = 40, n: int = 20
                ) -> tuple[np.ndarray, np.ndarray]:
    """Orthographic tracks (pixels) of a flag-like sheet with a travelling wave, seen by a
    camera swaying by +-deg degrees, and its camera-frame shapes (F, P, 3)."""
    u, v = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-0.7, 0.7, n))
    u, v = u.ravel(), v.ravel()
    t = np.arange(F) / 10
    z = amp * (u + 1) / 2 * np.sin(2 * np.pi * (0.55 * u - 0.45 * t[:, None]) + 1.3 * v)
    S_obj = np.stack([np.broadcast_to(u, z.shape), np.broadcast_to(v, z.shape), z], 1)
    ang = np.radians(deg) * np.stack([np.sin(0.75 * t), 0.5 * np.sin(0.57 * t + 1)], 1)
    R = Rotation.from_euler('yx', ang).as_matrix()
    S = np.einsum('fij,fjp->fpi', R, S_obj)
    return 100 * S[:, :, :2].transpose(0, 2, 1).reshape(2 * F, -1), S


def _linear_q(M_hat: np.ndarray) -> np.ndarray:
    C, d = _upgrade_system(M_hat)
    q = np.linalg.lstsq(C, d, rcond=None)[0]
    i, j = np.triu_indices(3)
    Q = np.zeros((3, 3))
    Q[i, j] = q
    return Q + np.triu(Q, 1).T


def test_upgrade_exact_on_rigid_data():
    W, S, _ = low_rank_sequence(K=1)
    M_hat, S_hat = _factors(W)
    A = metric_upgrade(M_hat, S_hat)
    MA = (M_hat @ A).reshape(-1, 2, 3)
    G = MA @ MA.transpose(0, 2, 1)                          # s_f^2 I per frame
    np.testing.assert_allclose(G, G[:, :1, :1] * np.eye(2), atol=1e-9 * G.max())
    np.testing.assert_allclose(A, metric_upgrade(M_hat), atol=1e-12)  # bound inactive
    assert e3d_frobenius(rigid(W).S, S, 'global') < 1e-6


def _hard_impute_reference(W, V, rank, iterations=20):
    """The hard imputation written plainly: every iteration the rank-K projection of all of
    the centred tracks, its values copied into the hidden entries."""
    M = np.repeat(V >= 0.5, 2, axis=0)
    X = W.copy()
    mean = (W * M).sum(axis=1, keepdims=True) / np.maximum(M.sum(axis=1, keepdims=True), 1)
    X[~M] = np.broadcast_to(mean, X.shape)[~M]
    for _ in range(iterations):
        mu = X.mean(axis=1, keepdims=True)
        X[~M] = (_rank_project(X - mu, rank) + mu)[~M]
    return X


@pytest.mark.parametrize('tracks, hidden_tracks', [(400, 30), (400, 400), (20, 20)])
def test_impute_low_rank_equals_the_plain_hard_imputation(tracks, hidden_tracks):
    """Few tracks with hidden entries (the Gram matrix updated by their change), hidden entries
    everywhere, and tall tracks (more rows than tracks): the same imputation as the plain
    iteration, and the visible entries untouched."""
    W, _, _ = low_rank_sequence(K=2, F=30, P=tracks)
    rng = np.random.default_rng(2)
    V = np.ones((30, tracks))
    cols = rng.choice(tracks, hidden_tracks, replace=False)
    V[:, cols] = rng.uniform(size=(30, hidden_tracks)) > 0.3
    V[0, cols] = 1.0                         # every track seen at least once
    for rank in (3, 6):
        X = impute_low_rank(W, V, rank)
        ref = _hard_impute_reference(W, V, rank)
        np.testing.assert_allclose(X, ref, rtol=0, atol=1e-9 * np.abs(W).max())
        M = np.repeat(V >= 0.5, 2, axis=0)
        assert np.array_equal(X[M], W[M])


def test_robust_rigid_discounts_gross_track_errors():
    """Rigid data, 5% of the entries dragged 8x the shape's spread off (an occluder's dragged
    tracks): the plain factorisation bends its shape towards them, the Huber-reweighted one
    (``robust``) recovers it; on clean data both are exact; bad arguments are named."""
    W, S, _ = low_rank_sequence(K=1)
    F, P = W.shape[0] // 2, W.shape[1]
    rng = np.random.default_rng(1)
    bad = rng.uniform(size=(F, P)) < 0.05
    Wo = W.reshape(F, 2, P) + 8 * W.std() * bad[:, None] * rng.normal(size=(F, 2, P))
    Wo = Wo.reshape(2 * F, P)
    plain, rob = rigid(Wo), rigid(Wo, robust=1.5)
    e_plain = e3d_frobenius(plain.S, S, 'frame', scale=True)
    e_rob = e3d_frobenius(rob.S, S, 'frame', scale=True)
    assert e_rob < 0.2 * e_plain and e_rob < 0.02, (e_plain, e_rob)
    assert rob.residual_px > 0 and np.isfinite(rob.residual_px)
    assert e3d_frobenius(rigid(W, robust=1.5).S, S, 'global') < 1e-6
    # Cauchy's redescending weights leave the dragged entries next to no pull at all: 14x
    # closer than Huber's here (measured 0.0005 against 0.0075 on three draws)
    cau = rigid(Wo, robust=2.0, loss='cauchy')
    e_cau = e3d_frobenius(cau.S, S, 'frame', scale=True)
    assert e_cau < 0.2 * e_rob, (e_rob, e_cau)
    assert e3d_frobenius(rigid(W, robust=2.0, loss='cauchy').S, S, 'global') < 1e-6
    with pytest.raises(ValueError, match='robust'):
        rigid(W, robust=-1.0)
    with pytest.raises(ValueError, match='robust_rounds'):
        rigid(W, robust=1.0, robust_rounds=-1)
    with pytest.raises(ValueError, match="loss: expected one of .*'tukey'"):
        rigid(W, robust=1.0, loss='tukey')


def test_rigid_factorises_few_fully_visible_tracks_instead_of_imputing():
    """Rigid data where a tenth of the tracks is seen in every frame and the rest in only one
    half of the sequence or the other (a tracker's pattern once its doubtful observations are
    hidden): the fully visible tenth pins the cameras, so the shape is exact; imputing the
    hidden halves first, which the factorisation did below a fifth of the tracks, is not."""
    F, P = 60, 1000
    rng = np.random.default_rng(3)
    X = rng.normal(size=(P, 3)) * [1.0, 0.7, 0.4]
    R = Rotation.from_euler('yx', np.stack([np.linspace(0, 60, F), np.linspace(0, 15, F)], 1),
                            degrees=True).as_matrix()
    W = np.einsum('fij,pj->fip', R[:, :2], X).reshape(2 * F, P)
    V = np.ones((F, P))
    half = rng.permutation(P)
    V[35:, half[100:550]] = 0            # seen in frames 0-34 only
    V[:25, half[550:]] = 0               # seen in frames 25-59 only
    res = rigid(W, V)
    S = np.einsum('fij,pj->fpi', R, X)
    assert e3d_frobenius(res.S, S, 'frame', scale=True) < 1e-6


def test_upgrade_bounded_when_the_linear_q_is_indefinite():
    """1-degree sway, wave of amplitude 0.2: the linear Q has a negative eigenvalue.  Clipping
    it to 1e-9 x max (the former rule) stretched the depth ~1000x; the PSD fit plus the bound
    keeps depth <= the in-plane extent, and the rigid fit stays finite and sane."""
    W, S = _wave_sheet(1.0, 0.2)
    M_hat, S_hat = _factors(W)
    lam, E = np.linalg.eigh(_linear_q(M_hat))
    assert lam[0] < 0 < lam[1]
    clipped = E * np.sqrt(np.maximum(lam, 1e-9 * lam.max()))
    assert depth_ratio(M_hat, S_hat, clipped) > 100            # measured 1150
    A = metric_upgrade(M_hat, S_hat)
    assert np.isfinite(A).all() and depth_ratio(M_hat, S_hat, A) <= 1.0 + 1e-6
    assert depth_ratio(M_hat, S_hat, metric_upgrade(M_hat, S_hat, max_depth_ratio=0.3)) \
        <= 0.3 + 1e-6
    res = rigid(W)
    Sc = res.S - res.S.mean(axis=1, keepdims=True)
    depth, inplane = Sc[..., 2].std(axis=1), np.sqrt((Sc[..., :2] ** 2).mean(axis=(1, 2)))
    assert np.isfinite(res.S).all() and np.median(depth / inplane) < 1.5
    old_rule = np.linalg.solve(clipped, S_hat)
    assert np.abs(res.S).max() < 0.01 * np.abs(old_rule).max()
    assert e3d_frobenius(res.S, S, 'frame', scale=True) < 0.55    # measured 0.507 (was 0.974)


def test_well_posed_sway_keeps_its_depth():
    """5-degree sway: well conditioned, the bound is inactive and depth comes from the data."""
    W, S = _wave_sheet(5.0, 0.2)
    M_hat, S_hat = _factors(W)
    A = metric_upgrade(M_hat, S_hat)
    np.testing.assert_allclose(A, metric_upgrade(M_hat), atol=1e-12)
    assert e3d_frobenius(rigid(W).S, S, 'frame', scale=True) < 0.11    # measured 0.099


def test_identical_cameras_do_not_blow_up_the_rigid_shape():
    """No camera motion at all, noisy tracks: depth is unobservable; it must stay bounded."""
    rng = np.random.default_rng(0)
    F, P = 30, 200
    X = np.stack([rng.uniform(-1, 1, P), rng.uniform(-0.7, 0.7, P), 0.3 * rng.normal(size=P)])
    W = np.tile(100 * X[:2], (F, 1)) + rng.normal(0, 0.3, (2 * F, P)) + 40.0
    for method in ('rigid', 'lowrank'):
        res = reconstruct(W, method=method)
        Sc = res.S - res.S.mean(axis=1, keepdims=True)
        assert np.isfinite(Sc).all()
        assert np.abs(Sc[..., 2]).max() < 10 * np.abs(Sc[..., :2]).max()
    # the depth prior of the shape solve: with a single repeated camera it keeps the prior's
    # depth; with well-spread cameras it is a fixed point of exact data
    R2 = np.broadcast_to(np.eye(3)[:2], (F, 2, 3))
    Wc = np.tile(X[:2], (F, 1))
    prior = X + [[0.0], [0.0], [0.5]]
    S0 = _solve_rigid_shape(Wc, np.ones((F, P)), R2, np.ones(F), prior=prior)
    np.testing.assert_allclose(S0[2], prior[2], atol=1e-9)
    np.testing.assert_allclose(S0[:2], X[:2], atol=1e-3)
    Wr, Sr, Rr = low_rank_sequence(K=1, F=F, P=P)
    Xr = np.einsum('fji,fpj->fip', Rr, Sr)[0]
    Wrc = Wr - 5.0
    S1 = _solve_rigid_shape(Wrc, np.ones((F, P)), Rr[:, :2], np.ones(F), prior=Xr)
    np.testing.assert_allclose(S1, Xr, atol=1e-9)


def test_upgrade_validates_its_input():
    with pytest.raises(ValueError, match='M_hat: expected shape'):
        metric_upgrade(np.zeros((5, 3)))
    with pytest.raises(ValueError, match='max_depth_ratio'):
        metric_upgrade(np.eye(3)[:2].repeat(3, 0).reshape(6, 3), max_depth_ratio=0.0)


def test_factorisations_name_a_frame_that_sees_nothing():
    """A frame with every weight 0 leaves its camera undetermined: rigid and lowrank say which
    frame (they used to fail in NumPy's SVD on its NaN translation), bmm fills it."""
    W, _ = _wave_sheet(20.0, 0.1)
    V = np.ones((W.shape[0] // 2, W.shape[1]))
    V[7] = 0.0
    for method in ('rigid', 'lowrank'):
        with pytest.raises(ValueError, match=r'V: frame\(s\) \[7\] see no point'):
            reconstruct(W, V, method=method)
    res = reconstruct(W, V, method='bmm')
    assert np.isfinite(res.S).all()
    V[7, :5] = 1.0                         # a few points seen: solved
    assert np.isfinite(reconstruct(W, V, method='rigid').S).all()
