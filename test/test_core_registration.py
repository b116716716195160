from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nrsfm_ros.core.metrics import rotation_error_deg
from nrsfm_ros.core.registration import register
from nrsfm_ros.core.sceneflow import scene_flow


def surface(n: int = 3000, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(-1, 1, (2, n))
    return np.stack([u, v, 0.4 * np.sin(2 * u) * np.cos(1.5 * v) + 0.2 * u * v], axis=1)


@pytest.mark.parametrize('method', ['icp', 'icp-point-to-plane'])
def test_recovers_30_degrees(method):
    X = surface()
    R = Rotation.from_rotvec(np.radians(30) * np.array([0.3, 1.0, 0.2]) /
                             np.linalg.norm([0.3, 1.0, 0.2])).as_matrix()
    t = np.array([0.1, -0.2, 0.05])
    src = (X - t) @ R  # target = R src + t
    res = register(src, X, method=method, max_iterations=100, trim=1.0)
    assert rotation_error_deg(res.T_target_source[:3, :3], R) < 0.5
    assert np.allclose(res.T_target_source[:3, 3], t, atol=0.02)
    assert res.residual < 1e-3


@pytest.mark.parametrize('bad, match', [
    (np.zeros((10, 2)), r'source: expected shape \(N, 3\)'),
    (np.zeros((2, 3)), 'at least 3 points'),
    (np.full((10, 3), np.nan), 'NaN'),
])
def test_validation(bad, match):
    with pytest.raises(ValueError, match=match):
        register(bad, surface(100))


def test_scene_flow_removes_rigid_motion():
    X = surface(500)
    ids = np.arange(500, dtype=np.uint32)
    R = Rotation.from_rotvec([0, 0.1, 0]).as_matrix()
    warp = np.zeros_like(X)
    bump = 0.1 * (X[:, 0] ** 2 + X[:, 1] ** 2)
    warp[:, 2] = bump - bump.mean()  # non-rigid: no rotation or translation explains it
    Y = (X + warp) @ R.T
    sf = scene_flow(X, ids, Y[::-1], ids[::-1], dt=0.5, frame='object')
    order = np.argsort(sf.ids)
    # the recovered velocity is the non-rigid part, in the current frame
    expected = (warp @ R.T) / 0.5
    err = np.abs(sf.velocity[order] - expected).mean() / np.abs(expected).mean()
    assert err < 0.3
    raw = scene_flow(X, ids, Y, ids, dt=0.5, frame='camera')
    np.testing.assert_allclose(raw.velocity, (Y - X) / 0.5)


def _pose(deg: float):
    R = Rotation.from_rotvec(np.radians(deg) * np.array([0.3, 1.0, 0.2]) /
                             np.linalg.norm([0.3, 1.0, 0.2])).as_matrix()
    return R, np.array([0.1, -0.2, 0.05])


@pytest.mark.parametrize('method', ['cpd-rigid', 'cpd-affine'])
def test_cpd_recovers_30_degrees(method):
    X = surface(1500)
    R, t = _pose(30)
    src = (X - t) @ R
    res = register(src, X, method=method, w=0.0)
    A = res.T_target_source[:3, :3]
    assert np.abs(A - R).max() < 0.01 and np.allclose(res.T_target_source[:3, 3], t, atol=0.01)
    assert res.residual < 1e-2 and res.method == method


def test_cpd_rigid_survives_large_rotation_and_outliers_where_icp_fails():
    rng = np.random.default_rng(1)
    X = surface(1500)
    X[:, 2] += 0.6 * np.exp(-((X[:, 0] - 0.5) ** 2 + (X[:, 1] + 0.4) ** 2) / 0.05)  # no symmetry
    R, t = _pose(60)
    src = (X - t) @ R
    noisy = np.vstack([X, rng.uniform(X.min(0), X.max(0), (500, 3))])   # 25% outliers
    icp = register(src, noisy, method='icp', max_iterations=100)
    cpd = register(src, noisy, method='cpd-rigid', w=0.3)
    assert rotation_error_deg(cpd.T_target_source[:3, :3], R) < 1.0
    assert rotation_error_deg(icp.T_target_source[:3, :3], R) > 10.0


def test_cpd_nonrigid_undoes_a_smooth_warp():
    rng = np.random.default_rng(2)
    X = surface(1000)
    C = X[rng.choice(1000, 6, replace=False)]
    g = np.exp(-((X[:, None] - C[None]) ** 2).sum(-1) / (2 * 0.4 ** 2))
    warped = X + 0.15 * g @ rng.normal(size=(6, 3))
    start = np.sqrt(((warped - X) ** 2).sum(1).mean())
    res = register(X, warped[rng.permutation(1000)], method='cpd-nonrigid', w=0.0)
    end = np.sqrt(((res.aligned - warped) ** 2).sum(1).mean())
    rigid = register(X, warped, method='cpd-rigid', w=0.0)
    assert end < 0.2 * start and end < np.sqrt(((rigid.aligned - warped) ** 2).sum(1).mean())
    assert np.allclose(res.displacement, res.aligned - X)


def test_register_rejects_unknown_method_and_parameters():
    with pytest.raises(ValueError, match="method='gravity'"):
        register(surface(50), surface(50), method='gravity')
    with pytest.raises(ValueError, match=r"unknown parameter\(s\) \['trim'\]"):
        register(surface(50), surface(50), method='cpd-rigid', trim=0.5)
    with pytest.raises(ValueError, match='w=1.0'):
        register(surface(50), surface(50), method='cpd-rigid', w=1.0)


def test_ecpd_priors_pull_a_wrong_minimum_right():
    rng = np.random.default_rng(4)
    X = surface(1500)
    X[:, 2] += 0.6 * np.exp(-((X[:, 0] - 0.5) ** 2 + (X[:, 1] + 0.4) ** 2) / 0.05)
    R = Rotation.from_rotvec(np.radians(150) * np.array([0.3, 1.0, 0.2]) /
                             np.linalg.norm([0.3, 1.0, 0.2])).as_matrix()
    perm = rng.permutation(1500)
    src = ((X - [0.1, -0.2, 0.05]) @ R)[perm]          # target = R src + t, shuffled
    noisy = np.vstack([X, rng.uniform(X.min(0), X.max(0), (500, 3))])
    plain = register(src, noisy, method='cpd-rigid', w=0.3)
    k = rng.choice(1500, 15, replace=False)              # 1% correct prior matches
    priors = np.stack([k, perm[k]], axis=1)
    ecpd = register(src, noisy, method='ecpd-rigid', w=0.3, priors=priors)
    assert rotation_error_deg(plain.T_target_source[:3, :3], R) > 10.0
    assert rotation_error_deg(ecpd.T_target_source[:3, :3], R) < 1.0
    assert ecpd.method == 'ecpd-rigid'
    with pytest.raises(ValueError, match='needs priors'):
        register(src, noisy, method='ecpd-rigid')
    with pytest.raises(ValueError, match='out of range'):
        register(src, noisy, method='ecpd-rigid', priors=np.array([[0, 99999]]))


def test_ga_recovers_a_large_rotation_and_uses_prior_masses():
    rng = np.random.default_rng(5)
    X = surface(1200)
    X[:, 2] += 0.6 * np.exp(-((X[:, 0] - 0.5) ** 2 + (X[:, 1] + 0.4) ** 2) / 0.05)
    R, t = _pose(60)
    perm = rng.permutation(1200)
    src = ((X - t) @ R)[perm]
    res = register(src, X, method='ga')
    assert rotation_error_deg(res.T_target_source[:3, :3], R) < 2.0 and res.method == 'ga'
    k = rng.choice(1200, 12, replace=False)
    pri = register(src, X, method='ga', priors=np.stack([k, perm[k]], 1))
    assert rotation_error_deg(pri.T_target_source[:3, :3], R) < 1.0
    assert pri.iterations < res.iterations          # the cues speed convergence up
    with pytest.raises(ValueError, match='damping=1.5'):
        register(src, X, method='ga', damping=1.5)
