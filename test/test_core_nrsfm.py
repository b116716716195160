from __future__ import annotations

import importlib
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nrsfm_ros.core.metrics import e3d_frobenius, e3d_normalized
from nrsfm_ros.core.nrsfm import reconstruct
from nrsfm_ros.core.nrsfm.stream import StreamNRSfM
from tests_helpers import low_rank_sequence


def test_rigid_exact_on_rigid_data():
    W, S, _ = low_rank_sequence(K=1)
    res = reconstruct(W, method='rigid')
    assert e3d_frobenius(res.S, S, 'global') < 1e-6
    res = reconstruct(W, method='lowrank', rank=1)
    assert e3d_frobenius(res.S, S, 'frame') < 1e-6


def test_lowrank_beats_rigid_on_deforming_data():
    W, S, _ = low_rank_sequence(K=3)
    rigid = e3d_frobenius(reconstruct(W, method='rigid').S, S, 'frame')
    low = e3d_frobenius(reconstruct(W, method='lowrank', rank=3).S, S, 'frame')
    assert low < 0.06 and low < 0.5 * rigid


def test_visibility_missing_entries_are_ignored():
    W, S, _ = low_rank_sequence(K=1)
    rng = np.random.default_rng(3)
    V = (rng.random((S.shape[0], S.shape[1])) > 0.1).astype(float)
    Wbad = W.copy()
    Wbad[np.repeat(V == 0, 2, axis=0)] += 50.0  # garbage where invisible
    res = reconstruct(Wbad, V, method='rigid')
    assert e3d_frobenius(res.S, S, 'global') < 1e-4
    nan = W.copy()
    nan[0, :5] = np.nan  # non-finite measurements count as missing
    assert np.isfinite(reconstruct(nan, method='rigid').S).all()


def test_window_emits_one_shape_per_frame():
    W, S, _ = low_rank_sequence(K=2, F=40)
    win = StreamNRSfM(mode='window', window=20, rank=2)
    ids = np.arange(W.shape[1])
    out = []
    for f in range(40):
        got = win.push(ids, W[2 * f:2 * f + 2].T)
        assert len(got) == (0 if f < 19 else 20 if f == 19 else 1)
        out += got
    assert [o.index for o in out] == list(range(40))
    S_hat = np.stack([o.X for o in out])
    assert e3d_frobenius(S_hat, S, 'frame', scale=True) < 0.12  # measured 0.089


@pytest.mark.parametrize('W, V, match', [
    (np.zeros((3, 10)), None, 'W: expected shape'),
    (np.zeros((4, 2)), None, 'at least 4 points'),
    (np.zeros((4, 10)), np.ones((3, 10)), 'V: expected shape'),
    (np.zeros((4, 10)), np.full((2, 10), 2.0), r'\[0, 1\]'),
])
def test_input_validation(W, V, match):
    with pytest.raises(ValueError, match=match):
        reconstruct(W, V)


def test_unknown_method():
    with pytest.raises(ValueError, match="method='nope'"):
        reconstruct(np.zeros((4, 10)), method='nope')


def test_metric_A_reproduces_published_PTA():
    from conftest import shared_data
    d = np.load(shared_data('nrsfm', 'drink.npz'))
    assert abs(e3d_normalized(d['S_PTA_world'], d['S_world']) - 0.0250) < 5e-4


def test_metrics_invariant_to_rotation_and_reflection():
    rng = np.random.default_rng(0)
    S = rng.normal(size=(5, 30, 3))
    R = Rotation.random(random_state=1).as_matrix() @ np.diag([1, 1, -1])
    assert e3d_frobenius(S @ R.T, S, 'global') < 1e-10
    assert e3d_frobenius(2 * S @ R.T, S, 'frame', scale=True) < 1e-10
    assert e3d_normalized(S @ R.T, S) < 1e-10


@pytest.mark.parametrize('method, kw', [('bmm', {}), ('bmm', {'rank': 1}),
                                        ('smsr', {'dct_fraction': 1.0})])
def test_prior_free_methods_exact_on_rigid_data(method, kw):
    W, S, _ = low_rank_sequence(K=1)
    res = reconstruct(W, method=method, **kw)
    assert e3d_frobenius(res.S, S, 'global') < 1e-6


def test_bmm_cameras_exact_on_noise_free_low_rank_data():
    from nrsfm_ros.core.nrsfm.bmm import dai_rotations
    from nrsfm_ros.core.nrsfm.factorization import _centre
    W, _, R = low_rank_sequence(K=3)
    Wc, _ = _centre(W, np.ones((60, 300)))
    R2 = dai_rotations(Wc, np.ones((60, 300)), 3)
    U, _, Vt = np.linalg.svd(np.einsum('fki,fkj->ij', R[:, :2], R2))
    aligned = R[:, :2] @ (U @ Vt)
    err = np.minimum(np.linalg.norm(aligned - R2, axis=(1, 2)),
                     np.linalg.norm(aligned + R2, axis=(1, 2)))
    assert err.max() < 1e-4


def test_bmm_camera_polish_stops_on_the_round_off_floor(monkeypatch):
    """Exact rank-2 tracks given to bmm's default rank leave LM a flat valley at the round-off
    floor (motion ranks 4, 5 on the imputed tracks): it crept along it to max_nfev (16,700
    evaluations, 7.6 s per solve).  It now stops once the cost is below the floor and has
    stopped halving; the cameras' accuracy where it is reachable is
    test_bmm_cameras_exact_on_noise_free_low_rank_data's."""
    import scipy.optimize
    calls = []
    least_squares = scipy.optimize.least_squares

    def counted(fun, x0, **kw):
        def f(x):
            calls.append(1)
            return fun(x)
        return least_squares(f, x0, **kw)
    monkeypatch.setattr(scipy.optimize, 'least_squares', counted)
    W, S, _ = low_rank_sequence(K=2, F=24, P=90)
    V = np.ones((24, 90))
    V[6:10, :12] = 0
    res = reconstruct(W, V, 'bmm')
    assert 0 < len(calls) < 1500
    assert res.residual_px < 0.01 and np.isfinite(res.S).all()


def test_bmm_cameras_are_reproducible_to_rounding():
    """A noisy deforming sequence under a 12-degree sway: 1e-12 changes of the tracks leave
    the averaged cameras equal to 1e-6 up to one global rotation (the upgrade's gauge).  With
    eigh/svd's arbitrary eigenvector signs and the arbitrary null-space vector of a rank-2 Q
    they moved by 0.03 (frames flipped), so results differed between machines."""
    from nrsfm_ros.core.nrsfm.bmm import averaged_rotations
    from nrsfm_ros.core.nrsfm.factorization import _centre
    rng = np.random.default_rng(0)
    F, P = 40, 500
    B = rng.normal(size=(3, 3, P))
    B[0] *= 3
    B[0, 2] *= 0.3
    t = np.linspace(0, 4, F)
    c = np.stack([np.ones(F), 0.3 * np.sin(1.3 * t), 0.2 * np.cos(0.7 * t)], 1)
    ang = np.radians(12) * np.stack([np.sin(0.8 * t), 0.4 * np.cos(0.5 * t)], 1)
    R = Rotation.from_euler('yx', ang).as_matrix()
    W = 50 * np.einsum('fij,fk,kjp->fip', R[:, :2], c, B).reshape(2 * F, P)
    W += 0.3 * rng.normal(size=W.shape)
    V = np.ones((F, P))
    Wc, _ = _centre(W, V)
    R0 = averaged_rotations(Wc, V)
    R1 = averaged_rotations(Wc + 1e-12 * rng.normal(size=Wc.shape), V)
    U, _, Vt = np.linalg.svd(np.einsum('fki,fkj->ij', R1, R0))
    assert np.abs(R1 @ (U @ Vt) - R0).max() < 1e-6


def test_bmm_warm_from_its_own_solution_keeps_it_and_its_reflection():
    """``bmm_warm`` (the perspective step's re-solve of corrected tracks) started from bmm's own
    result on the same tracks gives that solution back: the same fit and shapes as accurate;
    started from the depth-reflected result it returns that reflection; a start of other
    tracks is refused naming it."""
    from nrsfm_ros.core.nrsfm.bmm import bmm, bmm_warm
    from nrsfm_ros.core.nrsfm.perspective import _flipped
    W, S, _ = low_rank_sequence(K=3, F=40, P=250, seed=2)
    W = W + 0.02 * np.random.default_rng(2).normal(size=W.shape)   # full rank: gauge path
    V = np.ones((40, 250))
    V[5:15, :40] = 0.0                                     # and hidden entries
    cold = bmm(W, V, iterations=40)
    warm = bmm_warm(W, V, cold, iterations=40)
    e_cold = e3d_frobenius(cold.S, S, 'frame', scale=True)
    e_warm = e3d_frobenius(warm.S, S, 'frame', scale=True)
    assert warm.residual_px <= 1.1 * cold.residual_px
    assert e_warm <= 1.1 * e_cold
    z = cold.S[:, :, 2]
    assert (warm.S[:, :, 2] * z).sum() > 0
    flipped = bmm_warm(W, V, _flipped(cold), iterations=40)
    assert (flipped.S[:, :, 2] * z).sum() < 0
    assert e3d_frobenius(flipped.S * [1, 1, -1], S, 'frame', scale=True) <= 1.1 * e_cold
    with pytest.raises(ValueError, match='start'):
        bmm_warm(W[:, :100], V[:, :100], cold)


def test_bmm_admm_kernels_equal_the_numpy_expressions():
    """The fused numba kernels of bmm_shapes (core/nrsfm/_admm.py) compute exactly the ADMM's
    S-step, T = S + U / rho and dual update written as NumPy expressions."""
    from nrsfm_ros.core.nrsfm._admm import data_step, dual_step
    rng = np.random.default_rng(3)
    F, P, rho, rho_den = 7, 50, 0.37, 0.74
    Z, U, RtW = (rng.normal(size=(F, 3, P)) for _ in range(3))
    V = rng.uniform(size=(F, P))
    ev, E = np.linalg.eigh(np.einsum('fki,fkj->fij', *(2 * [rng.normal(size=(F, 2, 3))])))
    S, T = np.empty_like(Z), np.empty_like(Z)
    data_step(Z, U, RtW, E, ev, V, rho, rho_den, 1.0 / rho, S, T)
    coef = (E.transpose(0, 2, 1) @ (rho * Z - U + RtW)) / (rho_den + ev[:, :, None] * V[:, None])
    S_ref = E @ coef
    assert np.allclose(S, S_ref, rtol=1e-12, atol=1e-12)
    assert np.allclose(T, S_ref + U / rho, rtol=1e-12, atol=1e-12)
    Zn = rng.normal(size=(F, 3, P))
    U_ref = U + rho * (S - Zn)
    primal, dual = dual_step(S, Zn, Z, U, rho)
    assert np.allclose(U, U_ref, rtol=1e-12, atol=1e-12)
    assert primal == pytest.approx(np.linalg.norm(S - Zn), rel=1e-12)
    assert dual == pytest.approx(rho * np.linalg.norm(Zn - Z), rel=1e-12)


def test_bmm_shapes_float32_iterates_equal_float64_and_keep_the_caller_arrays():
    """bmm_shapes' ADMM in float32 (ADMM_DTYPE, the default) gives the float64 iterates'
    shapes to ~6e-6 relative at the stream's 40 iterations and ~2e-4 after 120 (the float32
    Gram's resolution of small singular values, which the threshold tau / rho reaches as rho
    grows), with and without hidden entries and the trajectory prior; its reused buffers leave
    the caller's start untouched; the shapes come back float64."""
    bmm_mod = __import__('sys').modules['nrsfm_ros.core.nrsfm.bmm']
    assert bmm_mod.ADMM_DTYPE == np.float32
    W, S, R = low_rank_sequence(K=2, F=30, P=300, seed=4)
    F, P = S.shape[:2]
    R2 = np.ascontiguousarray(R[:, :2])
    Wc = W - W.mean(axis=1, keepdims=True)
    V = np.ones((F, P))
    V[5:12, :40] = 0.0
    init = R2.transpose(0, 2, 1) @ Wc.reshape(F, 2, P)
    start = init.copy()
    for smooth, iterations, rel in ((0.0, 40, 3e-5), (2.0, 40, 3e-5), (0.0, 120, 1e-3)):
        out = {dt: bmm_mod.bmm_shapes(Wc, V, R2, 0.01, iterations, init=init, smooth=smooth,
                                      dtype=dt) for dt in (np.float64, np.float32)}
        Z64, Z32 = out[np.float64][0], out[np.float32][0]
        assert Z32.dtype == np.float64 and Z32.shape == (F, 3, P)
        assert out[np.float32][1] == out[np.float64][1]          # the same iterations
        assert np.linalg.norm(Z32 - Z64) < rel * np.linalg.norm(Z64)
        assert np.linalg.norm(Z64 - init) > 1e-3 * np.linalg.norm(Z64)   # it did move
    np.testing.assert_array_equal(init, start)


def test_bmm_handles_missing_entries_and_validates():
    W, S, _ = low_rank_sequence(K=1)
    rng = np.random.default_rng(3)
    V = (rng.random((S.shape[0], S.shape[1])) > 0.1).astype(float)
    Wbad = W.copy()
    Wbad[np.repeat(V == 0, 2, axis=0)] += 50.0  # garbage where invisible
    res = reconstruct(Wbad, V, method='bmm')
    assert np.isfinite(res.S).all() and e3d_frobenius(res.S, S, 'frame') < 0.2
    with pytest.raises(ValueError, match='rank=9'):
        reconstruct(W[:20], method='bmm', rank=9)
    with pytest.raises(ValueError, match='dct_fraction'):
        reconstruct(W, method='smsr', dct_fraction=0.0)


# measured metric A (world frame for the Akhter sets) with the defaults, one parameter set for
# all data (drink/pickup/stretch: orbit cameras, chosen automatically; face/walking: free).
MOCAP_A = {'drink': 0.0105, 'pickup': 0.0290, 'stretch': 0.0362, 'face': 0.0261,
           'walking': 0.1260}
TARGET_A = {'drink': 0.020, 'pickup': 0.060, 'stretch': 0.050}     # issue 3


@pytest.mark.parametrize('name', sorted(MOCAP_A))
def test_bmm_accuracy_on_mocap(name):
    from conftest import shared_data
    d = np.load(shared_data('nrsfm', f'{name}.npz'))

    def metric_a(res):
        if 'S_world' in d.files:
            return e3d_normalized(np.einsum('fji,fpj->fpi', res.R, res.S), d['S_world'])
        return e3d_normalized(res.S, d['S'])
    res = reconstruct(d['W'], method='bmm')
    err = metric_a(res)
    assert err <= MOCAP_A[name] * 1.05 + 1e-3
    assert err <= TARGET_A.get(name, 1.0)
    assert res.camera_model == ('orbit' if name in TARGET_A else 'free')
    assert err < metric_a(reconstruct(d['W'], method='rigid'))


def test_default_on_the_real_back_sequence_is_within_1_1x_of_the_best_method():
    """Issue 12: the sparse sets with defaults within 1.1x of the best method.  ``back``
    (perspective pixel tracks, stereo ground truth with missing entries stored as zeros),
    metric B per frame with scale on the entries the ground truth has (measured: bmm 0.0866,
    smsr 0.0890, rigid 0.1010)."""
    from conftest import shared_data
    from nrsfm_ros.core.metrics import frame_e3d
    d = np.load(shared_data('nrsfm', 'back.npz'))
    W, S = d['W'], d['S']
    ok = ~(S == 0).all(-1)
    assert 0 < (~ok).sum() < 0.1 * ok.size

    def score(method):
        Sh = reconstruct(W, method=method).S
        return np.mean([frame_e3d(Sh[f][ok[f]], S[f][ok[f]]) for f in range(len(S))])
    default = score('bmm')                       # reconstruct's default method
    others = {m: score(m) for m in ('rigid', 'smsr', 'cdf')}
    assert default <= 1.1 * min(others.values()), (default, others)
    assert default < 0.9 * others['rigid']


def test_trajectory_prior_with_known_cameras():
    """The shapes' trajectory prior (second differences) on drink with the true cameras:
    metric A 0.022 -> 0.008 (measured); the banded system equals the dense one."""
    from conftest import shared_data
    from scipy.linalg import solveh_banded
    bmm_mod = __import__('sys').modules['nrsfm_ros.core.nrsfm.bmm']
    F = 9
    D = np.diff(np.eye(F), 2, axis=0)
    b = np.arange(F, dtype=float) ** 2
    ab = bmm_mod.second_difference_banded(F, 3.0, 0.5)
    assert np.allclose(solveh_banded(ab, b), np.linalg.solve(3 * D.T @ D + 0.5 * np.eye(F), b))
    d = np.load(shared_data('nrsfm', 'drink.npz'))
    W, R2 = d['W'][:400], d['R'][:200, :2]
    V = np.ones((200, W.shape[1]))
    errs = [e3d_normalized(bmm_mod.bmm_shapes(W, V, R2, 0.01, 200, smooth=mu)[0]
                           .transpose(0, 2, 1), d['S_world'][:200]) for mu in (0.0, 100.0)]
    assert errs[1] < 0.6 * errs[0], errs


def _orbit(F: int, rate_deg: float, seed: int = 0) -> np.ndarray:
    axis = np.random.default_rng(seed).normal(size=3)
    axis /= np.linalg.norm(axis)
    step = Rotation.from_rotvec(np.radians(rate_deg) * axis)
    R0 = Rotation.random(random_state=seed)
    return np.stack([(step ** f * R0).as_matrix() for f in range(F)])


def test_orbit_cameras_remove_slow_drift_and_reject_free_cameras():
    bmm_mod = __import__('sys').modules['nrsfm_ros.core.nrsfm.bmm']
    R = _orbit(200, 4.0)
    Ro, dev, disp = bmm_mod.orbit_cameras(R)
    assert np.abs(Ro - R).max() < 1e-9 and dev < 1e-6 and disp < 1e-6
    # a slow 3-degree wobble (the gauge drift of per-frame estimates) is removed
    R6 = _orbit(600, 4.0, seed=2)
    f = np.arange(600)
    wob = Rotation.from_rotvec(np.radians(3) * np.stack(
        [np.sin(2 * np.pi * f / 60), np.cos(2 * np.pi * f / 45), 0 * f], 1)).as_matrix()
    Ro, dev, disp = bmm_mod.orbit_cameras(wob @ R6)
    err = np.degrees(Rotation.from_matrix(Ro @ R6.transpose(0, 2, 1)).magnitude())
    assert err.mean() < 0.2 * dev and 1.5 < dev < 4 and disp < 0.1, (err.mean(), dev, disp)
    f = np.arange(200)
    # a free camera (the test sequences' sinusoidal angles) is far from any orbit
    _, _, R_free = low_rank_sequence(K=1)
    assert bmm_mod.orbit_cameras(R_free)[2] > 0.3
    # the camera model of bmm: orbit sequence -> 'orbit', the free camera -> 'free'
    rng = np.random.default_rng(1)
    B = rng.normal(size=(2, 3, 60))
    S_obj = B[0] + 0.2 * np.sin(f[:, None, None] / 15.0) * B[1]
    W = np.einsum('fij,fjp->fip', R[:, :2], S_obj).reshape(400, 60)
    W = W + rng.normal(scale=0.01, size=W.shape)
    res = reconstruct(W, method='bmm')
    assert res.camera_model == 'orbit'
    assert reconstruct(W, method='bmm', camera_model='free').camera_model == 'free'
    W2, _, _ = low_rank_sequence(K=2)
    W2 = W2 + rng.normal(scale=0.01, size=W2.shape)
    assert reconstruct(W2, method='bmm').camera_model == 'free'
    assert reconstruct(W2, method='bmm', camera_model='orbit').camera_model == 'orbit'
    for kw, match in (({'camera_model': 'tripod'}, 'camera_model'), ({'smooth': -1.0}, 'smooth'),
                      ({'orbit_tolerance': -0.1}, 'orbit_tolerance')):
        with pytest.raises(ValueError, match=match):
            reconstruct(W, method='bmm', **kw)
        with pytest.raises(ValueError, match=match):
            reconstruct(W, method='cdf', **kw)


def test_amp_exact_on_rigid_data_and_invariant_to_frame_order():
    W, S, _ = low_rank_sequence(K=1)
    assert e3d_frobenius(reconstruct(W, method='amp', rank=1).S, S, 'global') < 1e-6
    W2, S2, _ = low_rank_sequence(K=2)
    res = reconstruct(W2, method='amp', rank=2, iterations=200)
    perm = np.random.default_rng(0).permutation(60)
    Wp = W2.reshape(60, 2, -1)[perm].reshape(120, -1)
    resp = reconstruct(Wp, method='amp', rank=2, iterations=200)
    a = e3d_frobenius(res.S, S2, 'frame')
    assert a < 0.01 and abs(e3d_frobenius(resp.S, S2[perm], 'frame') - a) < 1e-6
    with pytest.raises(ValueError, match='rank=0'):
        reconstruct(W2, method='amp', rank=0)


def test_online_emits_one_shape_per_frame_in_constant_time():
    import time

    W, S, _ = low_rank_sequence(K=2, F=60, P=2000)
    on = StreamNRSfM(mode='online', window=30, rank=2)
    ids = np.arange(W.shape[1])
    out, times = [], []
    for f in range(60):
        t = time.perf_counter()
        got = on.push(ids, W[2 * f:2 * f + 2].T)
        if f >= 30:
            times.append(time.perf_counter() - t)
        assert len(got) == (0 if f < 29 else 30 if f == 29 else 1)
        out += got
    assert [o.index for o in out] == list(range(60))
    S_hat = np.stack([o.X for o in out])
    # the online frames are as good as the initial window that gave their basis
    window = e3d_frobenius(S_hat[:30], S[:30], 'frame', scale=True)
    online = e3d_frobenius(S_hat[30:], S[30:], 'frame', scale=True)
    assert online < 0.07 and online < 1.5 * window + 0.01
    assert np.median(times) < 0.02            # one frame of 2,000 points, far below 1/30 s


def test_procrustean_gauge_moves_frame_rotations_into_the_cameras():
    from scipy.spatial.transform import Rotation

    from nrsfm_ros.core.nrsfm.bmm import procrustean_gauge
    rng = np.random.default_rng(3)
    F, P = 30, 60
    core = rng.normal(size=(3, P))
    S = np.repeat(core[None], F, axis=0)
    S[:, :, :10] += 0.5 * rng.normal(size=(F, 3, 10))       # a deforming part (the "arms")
    Qtrue = Rotation.random(F, random_state=4).as_matrix()
    Sr = np.einsum('fij,fjp->fip', Qtrue, S)                # frames rotated against the gauge
    R = Rotation.random(F, random_state=5).as_matrix()
    A, R2 = procrustean_gauge(Sr, R)
    np.testing.assert_allclose(np.einsum('fij,fjp->fip', R2, A),
                               np.einsum('fij,fjp->fip', R, Sr), atol=1e-9)  # same cameras x S
    # the rigid core ends up identical in every frame (up to one global rotation)
    core_err = np.abs(A[:, :, 10:] - A[:1, :, 10:]).max()
    assert core_err < 1e-6
    np.testing.assert_allclose(np.einsum('fij,fik->fjk', R2, R2), np.eye(3)[None].repeat(F, 0),
                               atol=1e-12)


def _dense_sheet(F: int = 30, n: int = 25):
    """Orthographic tracks (pixels) of a deforming rank-3 sheet under a smooth 2-axis camera
    motion, the camera-frame shapes, and the sheet parameter u of every point."""
    from scipy.spatial.transform import Rotation
    u, v = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n))
    u, v = u.ravel(), v.ravel()
    base = np.stack([u, v, 0.2 * np.sin(2 * u)], 1)
    m1 = np.stack([0 * u, 0 * u, np.exp(-(u ** 2 + v ** 2))], 1)
    m2 = np.stack([0.1 * v, 0 * u, u * v], 1)
    t = np.arange(F) / F * 2 * np.pi
    Sw = base[None] + 0.3 * np.sin(t)[:, None, None] * m1 \
        + 0.3 * np.cos(1.3 * t)[:, None, None] * m2
    R = Rotation.from_euler('yx', np.stack([0.5 * np.sin(t), 0.35 * np.sin(0.7 * t + 1)],
                                           1)).as_matrix()
    S = np.einsum('fij,fpj->fpi', R, Sw)
    return (100 * S[:, :, :2]).transpose(0, 2, 1).reshape(2 * F, -1), S, u


def test_cdf_fills_an_occluded_block_from_visible_neighbours():
    from nrsfm_ros.core.metrics import e3d_frobenius
    from nrsfm_ros.core.nrsfm.cdf import coherent_fill
    from nrsfm_ros.core.nrsfm.factorization import impute_low_rank
    W, S, u = _dense_sheet()
    F, P = S.shape[:2]
    Wn = W + np.random.default_rng(1).normal(0, 0.5, W.shape)
    V = np.ones((F, P))
    V[8:20][:, u < -0.4] = 0                       # 30% of the sheet hidden for 12 frames
    hidden = np.repeat(V < 0.5, 2, axis=0)
    fill = np.sqrt(((coherent_fill(Wn, V) - W)[hidden] ** 2).mean())
    hard = np.sqrt(((impute_low_rank(Wn, V, 12) - W)[hidden] ** 2).mean())
    assert fill < 6.0 and fill < 0.2 * hard        # pixels, on a ~200 px sheet
    occluded = reconstruct(Wn, V, method='cdf')
    full = reconstruct(Wn, np.ones((F, P)), method='bmm')
    e_cdf = e3d_frobenius(occluded.S, S, 'frame', scale=True)
    e_bmm = e3d_frobenius(reconstruct(Wn, V, method='bmm').S, S, 'frame', scale=True)
    assert e_cdf < 0.7 * e_bmm and e_cdf < 1.2 * e3d_frobenius(full.S, S, 'frame', scale=True)
    assert occluded.method == 'cdf' and occluded.S.shape == S.shape
    same = reconstruct(Wn, np.ones((F, P)), method='cdf')      # nothing hidden: exactly bmm
    # (equal but for the float32 ADMM's rounding, which the two paths order differently)
    np.testing.assert_allclose(same.S, full.S, rtol=1e-3, atol=0.1)
    with pytest.raises(ValueError, match='beta: expected > 0'):
        reconstruct(Wn, V, method='cdf', beta=0.0)


def test_row_space_and_dense_tracks():
    from nrsfm_ros.core.nrsfm.bmm import row_space
    from nrsfm_ros.io.synth import dense_tracks
    d = dense_tracks('face', frames=12, points=400, projection='orthographic')
    assert d['W'].shape == (24, 400) and d['S'].shape == (12, 400, 3) and d['V'].all()
    np.testing.assert_allclose(d['W'][0], 2000 / 4.0 * d['S'][0, :, 0])
    wp = dense_tracks('flag', frames=12, points=400, projection='weak-perspective')
    np.testing.assert_allclose(wp['W'][1], 2000 / wp['S'][0, :, 2].mean() * wp['S'][0, :, 1])
    Wc = d['W'] - d['W'].mean(1, keepdims=True)
    Wr, B = row_space(Wc)
    r = B.shape[0]
    assert Wr.shape == (24, r) and B.shape == (r, 400) and r <= 24
    np.testing.assert_allclose(B @ B.T, np.eye(r), atol=1e-9)
    assert np.abs(Wr @ B - Wc).max() < 1e-6 * np.abs(Wc).max()
    noisy = Wc + np.random.default_rng(0).normal(0, 1.0, Wc.shape)
    assert row_space(noisy)[1].shape == (24, 400)         # noise fills every direction
    with pytest.raises(ValueError, match="projection='pinhole'"):
        dense_tracks('face', projection='pinhole')
    g = dense_tracks('flag', frames=4, points=400, sampling='grid')    # a regular grid
    P = g['W'].shape[1]
    assert 300 <= P <= 500 and g['S'].shape == (4, P, 3)
    from scipy.spatial import cKDTree
    d1 = cKDTree(g['S_world'][0]).query(g['S_world'][0], k=2)[0][:, 1]
    assert d1.std() < 0.2 * d1.mean()                          # even spacing, unlike random
    with pytest.raises(ValueError, match="sampling='hex'"):
        dense_tracks('face', sampling='hex')


def test_hdsm_lift_is_exact_for_rigid_and_monotone_in_the_dimension():
    from nrsfm_ros.core.nrsfm.hdsm import compression_ratio, lift
    W, S, R = low_rank_sequence(K=1, F=20, P=50)
    S_obj = np.einsum('fji,fpj->fip', R, S)
    Phi, S_hat = lift(S_obj, 3)
    np.testing.assert_allclose(np.einsum('fid,dp->fip', Phi, S_hat), S_obj, atol=1e-8)
    W, S, R = low_rank_sequence(K=3, F=40, P=60)
    S_obj = np.einsum('fji,fpj->fip', R, S)
    errs = []
    for D in (3, 5, 7, 9):
        Phi, S_hat = lift(S_obj, D, iterations=60)
        np.testing.assert_allclose(Phi @ Phi.transpose(0, 2, 1),
                                   np.broadcast_to(np.eye(3), (40, 3, 3)), atol=1e-9)
        errs.append(np.linalg.norm(np.einsum('fid,dp->fip', Phi, S_hat) - S_obj))
    assert all(b <= a * (1 + 1e-9) for a, b in zip(errs, errs[1:])) and errs[-1] < 0.2 * errs[0]
    assert compression_ratio(40, 60, 9) == pytest.approx(3 * 40 * 60 / (9 * 60 + 27 * 40))
    res = reconstruct(W, method='hdsm', dim=6)
    assert res.method == 'hdsm' and res.rank == 6 and res.compression > 1
    assert res.S.shape == S.shape
    with pytest.raises(ValueError, match='dim=2'):
        reconstruct(W, method='hdsm', dim=2)


def test_va_huber_prox_grid_graph_and_tv_denoising():
    """The Huber shrink is the prox of t * h_eps; the graph of a regular grid is its
    4-connected grid; with exact cameras the TV term removes track noise from the shapes
    (the data term alone keeps it)."""
    from scipy.optimize import minimize

    from nrsfm_ros.core.nrsfm.va import grid_graph, huber_shrink, va_shapes
    rng = np.random.default_rng(0)
    for v in rng.normal(size=(5, 3)) * [[0.1], [0.5], [1.0], [2.0], [4.0]]:
        t, eps = 0.7, 0.5
        h = lambda x: (x @ x / (2 * eps) if np.linalg.norm(x) <= eps  # noqa: E731
                       else np.linalg.norm(x) - eps / 2)
        best = minimize(lambda x: t * h(x) + 0.5 * ((x - v) ** 2).sum(), v, tol=1e-12).x
        np.testing.assert_allclose(huber_shrink(v[None], t, eps)[0], best, atol=1e-5)
    n = 12
    gx, gy = np.meshgrid(np.arange(n) * 3.0, np.arange(n) * 3.0)
    pos = np.stack([gx.ravel(), gy.ravel()], 1)
    D = grid_graph(pos)
    assert D.shape[1] == n * n and np.all(abs(D).sum(1) == 2)
    inner = ((gx > 0) & (gx < 3 * (n - 1)) & (gy > 0) & (gy < 3 * (n - 1))).ravel()
    L = (D.T @ D).toarray()
    assert np.all(np.diag(L)[inner] == 4)                     # interior: the 4-connected grid
    nb = np.argwhere((L < 0) & inner[:, None])
    np.testing.assert_allclose(np.linalg.norm(pos[nb[:, 0]] - pos[nb[:, 1]], axis=1), 3.0)
    # a smooth bump seen by 6 known cameras, tracks with 3 px noise
    F, P = 6, n * n
    X = np.stack([gx.ravel() - gx.mean(), gy.ravel() - gy.mean(),
                  10 * np.exp(-((gx.ravel() - 16) ** 2 + (gy.ravel() - 16) ** 2) / 100)], 0)
    R = Rotation.from_euler('y', np.linspace(-20, 20, F)[:, None], degrees=True).as_matrix()
    R2 = R[:, :2]
    W = (R2 @ X[None]).reshape(2 * F, P)
    Wn = W + rng.normal(0, 3.0, W.shape)
    S0 = np.tile(X[None], (F, 1, 1)) + np.concatenate(
        [(R2.transpose(0, 2, 1) @ (Wn - W).reshape(F, 2, P))[:, :2], np.zeros((F, 1, P))], 1)
    V = np.ones((F, P))
    plain, _ = va_shapes(Wn, V, R2, D, S0, 1e-4, 0.0, 0.01, iterations=60)
    tv, _ = va_shapes(Wn, V, R2, D, S0, 1e-4, 0.1, 0.01, iterations=60)
    err = [np.sqrt(((S[:, :2] - X[None, :2]) ** 2).mean()) for S in (S0, plain, tv)]
    assert err[2] < 0.7 * err[1] and err[1] > 0.8 * err[0], err


def test_va_reduces_to_cdf_without_tv_and_validates(capsys):
    W, S, _ = low_rank_sequence(K=2, P=200)
    Wn = W + np.random.default_rng(1).normal(0, 0.01 * W.std(), W.shape)
    base = reconstruct(Wn, method='cdf')
    same = reconstruct(Wn, method='va', mu=0.0, iterations=50)
    assert same.method == 'va' and same.S.shape == S.shape
    assert e3d_frobenius(same.S, base.S, 'frame') < 1e-3
    smooth = reconstruct(Wn, method='va', mu=0.1, camera_rounds=1, iterations=50)
    assert np.isfinite(smooth.S).all() and smooth.iterations == 100
    for bad in ({'mu': -1.0}, {'eps': 0.0}, {'iterations': 0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            reconstruct(Wn, method='va', **bad)


def test_amp_keeps_its_initialisation_on_exact_low_rank_dense_data():
    """On noise-free dense tracks of rank < 3K the least-squares steps have unseen directions;
    the proximal terms keep them at the current iterate (before, rounding noise amplified by
    the ridge filled them), so AMP improves on (not drifts from) its bmm start."""
    from nrsfm_ros.core.nrsfm.amp import amp
    from nrsfm_ros.core.nrsfm.bmm import bmm
    from nrsfm_ros.io.synth import dense_tracks
    d = dense_tracks('face', frames=60, points=3000)
    base = bmm(d['W'])
    e0 = e3d_frobenius(base.S, d['S'], 'frame', scale=True)
    res = amp(d['W'], rank=3, init=base)       # (without the proximal centres: 0.25)
    assert e3d_frobenius(res.S, d['S'], 'frame', scale=True) < e0 < 0.02
    assert res.residual_px < 0.5
    with pytest.raises(ValueError, match='prox'):
        amp(d['W'], prox=-1.0)


def test_planar_exact_on_a_rigid_plane_and_accurate_on_the_flag():
    """planar: exact cameras and shapes for a rigid plane; on the generated flag (planar rest
    shape + travelling waves) metric B 0.015 clean / 0.033 with noise and a 30% occluded block
    (measured at 2k points; issue 3 targets 0.03 / 0.05) where bmm and rigid are at 0.07-0.12;
    a face-like surface is flagged as not planar (converged False)."""
    from nrsfm_ros.io.synth import dense_tracks
    rng = np.random.default_rng(4)
    plane = np.concatenate([rng.uniform(-1, 1, (2, 400)), np.zeros((1, 400))])
    R = Rotation.from_euler('yx', np.stack([np.radians(35) * np.sin(np.linspace(0, 3, 50)),
                                            np.radians(25) * np.cos(np.linspace(0, 2, 50))],
                                           1)).as_matrix()
    W = np.einsum('fij,jp->fip', R[:, :2], plane).reshape(100, 400)
    res = reconstruct(W, method='planar')
    S = np.einsum('fij,jp->fpi', R, plane)
    assert res.converged and e3d_frobenius(res.S, S, 'global') < 1e-6
    d = dense_tracks('flag', 60, 2000, 'orthographic')
    errs = {m: e3d_frobenius(reconstruct(d['W'], method=m).S, d['S'], 'frame', scale=True)
            for m in ('planar', 'rigid', 'bmm')}
    assert errs['planar'] < 0.02 and errs['planar'] < 0.3 * min(errs['rigid'], errs['bmm'])
    V = np.ones((60, 2000))
    V[20:40][:, d['W'][0] < np.quantile(d['W'][0], 0.3)] = 0
    Wn = d['W'] + np.random.default_rng(0).normal(0, 1.0, d['W'].shape)
    res = reconstruct(Wn, V, method='planar')
    assert res.converged and e3d_frobenius(res.S, d['S'], 'frame', scale=True) < 0.045
    # the face over 60 frames (at 30 its orthonormality misfit, 3.8e-3, is borderline)
    face = dense_tracks('face', 60, 1000, 'orthographic')
    assert not reconstruct(face['W'], method='planar').converged
    with pytest.raises(ValueError, match='beta'):
        reconstruct(W, method='planar', beta=0.0)
    with pytest.raises(ValueError, match='at least 3 frames'):
        reconstruct(W[:4], method='planar')


def test_planar_rejects_a_curved_cap_that_looks_flat_over_a_small_camera_motion():
    """The rendered sphere cap at 12 deg of camera motion passes the flat-rest test (its depth
    is barely observable), but planar explains its tracks 2x worse than rigid: not converged,
    so auto takes bmm (e3D 0.19 against planar's 0.25).  The rendered sheet, flat at rest and
    bending, stays planar (its residual is close to rigid's)."""
    from nrsfm_ros.core.nrsfm.planar import (PLANAR_REST_RATIO, PLANAR_RIGID_RATIO,
                                             rest_height_ratio)
    from nrsfm_ros.io.synth import SynthConfig, generate
    cap = generate(SynthConfig(surface='sphere', camera_motion_deg=12, frames=60, stride=4))
    V = np.maximum(cap.V, 1e-3)
    res, rig = reconstruct(cap.W, V, method='planar'), reconstruct(cap.W, V, method='rigid')
    assert rest_height_ratio(np.einsum('fji,fpj->fip', res.R, res.S)) <= PLANAR_REST_RATIO
    assert res.residual_px > PLANAR_RIGID_RATIO * rig.residual_px and not res.converged
    unchecked = reconstruct(cap.W, V, method='planar', rigid_check=False)   # flat test only
    assert unchecked.converged and unchecked.residual_px == res.residual_px
    sheet = generate(SynthConfig(surface='sheet', camera_motion_deg=30, frames=40, stride=3))
    assert reconstruct(sheet.W, np.maximum(sheet.V, 1e-3), method='planar').converged


def _rigid_body_small_rotation() -> tuple[np.ndarray, np.ndarray]:
    """A rigid, non-planar body (40 frames, 400 points) with 0.01 tracking noise seen over an
    8 x 20 degree rotation: tracks W and camera-frame shapes S."""
    rng = np.random.default_rng(0)
    F, P = 40, 400
    X = rng.normal(size=(3, P)) * [[1.0], [1.0], [0.6]]
    ang = np.stack([np.linspace(0, np.radians(8), F), np.linspace(0, np.radians(20), F)], 1)
    S = np.einsum('fij,jp->fpi', Rotation.from_euler('xy', ang).as_matrix(), X)
    W = S[:, :, :2].transpose(0, 2, 1).reshape(2 * F, P) + 0.01 * rng.normal(size=(2 * F, P))
    return W, S


def test_auto_takes_rigid_where_bmm_does_not_explain_what_rigid_leaves():
    """auto (the reconstructor's default): a rigid, non-planar body with tracking noise seen over
    a small rotation: bmm's extra freedom fits no better than one rigid shape (its residual is
    above rigid's) and its shapes are 20x worse, so auto takes rigid, as the start of its
    rank-2 shape basis (``lowrank``: on a rigid body within 20% of rigid's e3D, 0.019 against
    0.018); a strongly deforming rank-3 sequence keeps bmm (it explains the tracks exactly,
    rigid does not)."""
    from nrsfm_ros.core.nrsfm.stream import BMM_RIGID_RATIO, auto_solve
    W, S = _rigid_body_small_rotation()
    F, P = S.shape[:2]
    rig, bm = reconstruct(W, method='rigid'), reconstruct(W, method='bmm')
    assert bm.residual_px > BMM_RIGID_RATIO * rig.residual_px
    res = auto_solve(W, np.ones((F, P)))
    assert res.method == 'lowrank'
    assert e3d_normalized(res.S, S) < 0.1 * e3d_normalized(bm.S, S)
    assert e3d_normalized(res.S, S) < 1.2 * e3d_normalized(rig.S, S)
    assert auto_solve(W, np.ones((F, P)), rank=0).method == 'rigid'   # dspr / spva priors
    W2, _, _ = low_rank_sequence(K=3, F=60, P=300)
    res2 = auto_solve(W2, np.ones((60, 300)))
    assert res2.method == 'bmm'
    assert res2.residual_px < 1e-3 * reconstruct(W2, method='rigid').residual_px


def test_rotation_range_counts_a_reflected_camera_as_its_proper_partner():
    from nrsfm_ros.core.metrics import rotation_range_deg
    R = Rotation.from_euler('y', np.linspace(0, 15, 31)[:, None], degrees=True).as_matrix()
    assert rotation_range_deg(R) == pytest.approx(15.0)
    Rr = R.copy()
    Rr[5:9, 2] *= -1.0                       # Necker-reflected frames (det -1)
    assert rotation_range_deg(Rr) == pytest.approx(15.0)
    R2 = Rotation.from_euler('xy', np.stack([np.linspace(0, 10, 20),
                                             np.linspace(0, -20, 20)], 1),
                             degrees=True).as_matrix()
    assert rotation_range_deg(R2) == pytest.approx(
        Rotation.from_matrix(R2[-1]).magnitude() * 180 / np.pi)


def test_auto_takes_rigid_where_the_views_barely_observe_depth_and_rigid_turns_as_far():
    """``rigid_observed``: over a small rotation range (< SMALL_RANGE_DEG) bmm's nuclear norm
    flattens the depth the views barely observe; where the rigid factorisation's cameras turn
    as far as bmm's (within RANGE_AGREEMENT) its depth is not stretched by the bas-relief
    ambiguity and rigid is taken; where they turn less (rigid's rotation shrunk, its relief
    stretched) or the range is large, bmm stays.  On the face at 12 deg (ground-truth tracks,
    256x192, 60 frames, the camera's intrinsics given) ``auto`` then takes rigid and its rank-2
    basis (``lowrank``): e3D below the static oracle's (0.026) where bmm's is 3x it (all
    computed here)."""
    from types import SimpleNamespace

    from nrsfm_ros.core.nrsfm.stream import (RANGE_AGREEMENT, SMALL_RANGE_DEG, auto_solve,
                                             rigid_observed)
    from nrsfm_ros.io.synth import SynthConfig, generate

    def cams(deg):
        return SimpleNamespace(R=Rotation.from_euler('y', np.linspace(0, deg, 30)[:, None],
                                                     degrees=True).as_matrix())
    assert rigid_observed(cams(15.0), cams(15.5))
    assert rigid_observed(cams(RANGE_AGREEMENT * 20 + 0.1), cams(20.0))
    assert not rigid_observed(cams(8.0), cams(20.0))             # rigid's rotation shrunk
    # the tracker's face at 12 deg on one machine (0.84 of bmm's rotation), and its cap (0.63)
    assert rigid_observed(cams(16.5), cams(19.6))
    assert not rigid_observed(cams(10.3), cams(16.3))
    assert not rigid_observed(cams(SMALL_RANGE_DEG + 5), cams(SMALL_RANGE_DEG + 5))
    seq = generate(SynthConfig(surface='face', camera_motion_deg=12, frames=60))
    V = np.maximum(seq.V, 1e-3)
    res = auto_solve(seq.W, V, (float(seq.K[0, 0]), seq.K[:2, 2]))   # (planar refused)
    bm = reconstruct(seq.W, V, method='bmm')
    static = np.broadcast_to(seq.S[0], seq.S.shape)

    def e3d(S):
        return e3d_frobenius(S, seq.S, 'frame', scale=True)
    assert res.method == 'lowrank'
    assert e3d(res.S) < e3d(static) and e3d(res.S) < 0.5 * e3d(bm.S)


def test_auto_keeps_rigid_where_its_basis_cannot_run_or_fails(monkeypatch):
    """The rigid basis falls back to the rigid solve itself where ``lowrank`` refuses the
    tracks (a ValueError naming them) or returns non-finite shapes."""
    import nrsfm_ros.core.nrsfm.stream as st
    W, S = _rigid_body_small_rotation()
    V = np.ones(S.shape[:2])

    def refuses(*a, **k):
        raise ValueError('V: frame(s) [3] see no point')
    monkeypatch.setattr(st, 'low_rank', refuses)
    assert st.auto_solve(W, V).method == 'rigid'
    real = importlib.import_module('nrsfm_ros.core.nrsfm.factorization').low_rank

    def diverges(*a, **k):
        res = real(*a, **k)
        return replace(res, S=np.full_like(res.S, np.nan))
    monkeypatch.setattr(st, 'low_rank', diverges)
    res = st.auto_solve(W, V)
    assert res.method == 'rigid' and np.isfinite(res.S).all()


def test_auto_solves_its_rigid_basis_again_on_the_corrected_tracks(monkeypatch):
    """Where ``auto`` took rigid and its rank-2 basis, the perspective step solves that model
    again on the corrected tracks (rigid, then its basis: ``_auto_basis``) instead of deciding
    again; the published shapes of the face at 12 deg (ground-truth tracks, the camera's
    intrinsics) stay below the static oracle's e3D."""
    import nrsfm_ros.core.nrsfm.stream as st
    from nrsfm_ros.evaluation import score
    from nrsfm_ros.io.synth import SynthConfig, generate
    calls = {'auto': 0, 'basis': 0}
    real_auto, real_basis = st.auto_solve, st._auto_basis

    def auto(*a, **k):
        calls['auto'] += 1
        return real_auto(*a, **k)

    def basis(*a, **k):
        calls['basis'] += 1
        return real_basis(*a, **k)
    monkeypatch.setattr(st, 'auto_solve', auto)
    monkeypatch.setattr(st, '_auto_basis', basis)
    seq = generate(SynthConfig(surface='face', camera_motion_deg=12, frames=60))
    stream = st.StreamNRSfM(mode='batch', projection='perspective')
    stream.set_intrinsics(float(seq.K[0, 0]), seq.K[:2, 2])
    ids = seq.track_ids
    out = []
    for f in range(60):
        out += stream.push(ids, seq.W[2 * f:2 * f + 2].T, seq.V[f])
    out += stream.flush()
    assert [sh.index for sh in out] == list(range(60))
    assert stream.last_method == 'lowrank' and stream.perspective_solves == 1
    assert calls['auto'] == 1 and calls['basis'] >= 1
    summary = score({sh.index: (sh.X, sh.ids) for sh in out}, seq).summary()
    assert summary['e3d'] < summary['static'], summary


def test_dspr_prior_on_the_rigid_basis_tests_recurrence_against_rigid_noise():
    """``dspr``'s first batch takes ``auto``'s rigid basis too; its recurrence threshold is
    then ``BASIS_RECURRENCE`` x the usual one (the basis fits about half of the residual rigid
    leaves, the tracks' noise among it), and ``spva``'s prior keeps rigid."""
    import nrsfm_ros.core.nrsfm.stream as st
    from nrsfm_ros.io.synth import SynthConfig, generate
    seq = generate(SynthConfig(surface='face', camera_motion_deg=12, frames=64))
    ids = seq.track_ids
    for mode, method in (('dspr', 'lowrank'), ('spva', 'rigid')):
        stream = st.StreamNRSfM(mode=mode, batch_frames=60, spva_prior_frames=10,
                                projection='perspective')
        stream.set_intrinsics(float(seq.K[0, 0]), seq.K[:2, 2])
        out = []
        for f in range(64):
            out += stream.push(ids, seq.W[2 * f:2 * f + 2].T, seq.V[f])
        out += stream.flush()
        assert [sh.index for sh in out] == list(range(64)), mode
        assert stream.last_method == method, mode             # the first batch's solve
    batch = st.StreamNRSfM(mode='dspr', batch_frames=60, projection='perspective')
    batch.set_intrinsics(float(seq.K[0, 0]), seq.K[:2, 2])
    for f in range(60):
        batch.push(ids, seq.W[2 * f:2 * f + 2].T, seq.V[f])
    res = batch._batch_last[1]
    assert res.method == 'lowrank' and batch.prior is not None
    assert batch.prior.recurrence_px == pytest.approx(
        st.RECURRENCE_AUTO * st.BASIS_RECURRENCE * max(res.residual_px, st.RECURRENCE_MIN_PX))


def test_auto_decides_bmm_against_rigid_on_a_spread_subset(monkeypatch):
    """Over DECISION_TRACKS tracks the bmm / rigid decision runs on a spread subset and the full
    bmm solve only where bmm is taken, started from the subset's solution (``bmm_warm``): the
    same choices as on every track, and the bmm result covers every track as accurately."""
    import importlib
    bmm_mod = importlib.import_module('nrsfm_ros.core.nrsfm.bmm')
    stream = importlib.import_module('nrsfm_ros.core.nrsfm.stream')
    monkeypatch.setattr(stream, 'DECISION_TRACKS', 100)
    sizes, warm = [], []
    real, real_warm = bmm_mod.bmm, bmm_mod.bmm_warm

    def counted(W, V=None, **kw):
        sizes.append(W.shape[1])
        return real(W, V, **kw)

    def counted_warm(W, V, start, **kw):
        warm.append(W.shape[1])
        return real_warm(W, V, start, **kw)
    monkeypatch.setattr(bmm_mod, 'bmm', counted)
    monkeypatch.setattr(bmm_mod, 'bmm_warm', counted_warm)
    W, S = _rigid_body_small_rotation()
    F, P = S.shape[:2]
    res = stream.auto_solve(W, np.ones((F, P)))
    assert res.method == 'lowrank' and res.S.shape == (F, P, 3)     # rigid, then its basis
    assert sizes == [100] and warm == []        # the full bmm solve was never paid
    sizes.clear()
    W2, S2, _ = low_rank_sequence(K=3, F=60, P=300)
    W2 = W2 + 0.01 * np.random.default_rng(0).normal(size=W2.shape)
    res2 = stream.auto_solve(W2, np.ones((60, 300)))
    assert res2.method == 'bmm' and res2.S.shape == (60, 300, 3)
    assert sizes == [100] and warm == [300]
    cold = real(W2, np.ones((60, 300)), iterations=stream.BMM_ITERATIONS)
    assert e3d_frobenius(res2.S, S2, 'frame', scale=True) <= \
        1.1 * e3d_frobenius(cold.S, S2, 'frame', scale=True)


def test_stream_bmm_solves_run_fewer_iterations_with_the_same_shapes(monkeypatch):
    """The stream's bmm solves (auto's decision and full solve, a chosen ``bmm``) run
    BMM_ITERATIONS ADMM iterations, fewer than bmm's own default, and give the same shapes
    as the default on a deforming rank-3 sequence (e3D within 1e-3 of it)."""
    import importlib
    bmm_mod = importlib.import_module('nrsfm_ros.core.nrsfm.bmm')
    stream = importlib.import_module('nrsfm_ros.core.nrsfm.stream')
    import inspect
    default = inspect.signature(bmm_mod.bmm).parameters['iterations'].default
    assert stream.BMM_ITERATIONS < default
    seen = []
    real = bmm_mod.bmm

    def counted(W, V=None, **kw):
        seen.append(kw.get('iterations', default))
        return real(W, V, **kw)
    monkeypatch.setattr(bmm_mod, 'bmm', counted)
    monkeypatch.setitem(importlib.import_module('nrsfm_ros.core.nrsfm').METHODS, 'bmm', counted)
    W, S, _ = low_rank_sequence(K=3, F=60, P=300)
    V = np.ones((60, 300))
    res = stream.auto_solve(W, V)
    chosen = stream._solve_all(W, V, 'bmm', 0)
    assert res.method == 'bmm' and seen == [stream.BMM_ITERATIONS] * 2
    full = real(W, V)
    for r in (res, chosen):
        assert abs(e3d_normalized(r.S, S) - e3d_normalized(full.S, S)) < 1e-3


@pytest.mark.parametrize('method', ['bmm', 'smsr', 'cdf', 'va'])
def test_tracks_without_spread_are_a_clear_error(method):
    """Every point at the same place (or nothing visible to fill from): a ValueError naming W,
    not an IndexError from an empty row space deep in the camera estimate."""
    with pytest.raises(ValueError, match='W: the centred tracks are all zero'):
        reconstruct(np.full((24, 60), 5.0), method=method)
    W, _, _ = low_rank_sequence(K=2)
    F, P = W.shape[0] // 2, W.shape[1]
    with pytest.raises(ValueError, match='no entry is visible'):
        reconstruct(W, np.full((F, P), 1e-3), method='smsr')
    assert np.isfinite(reconstruct(W, method=method).S).all()
