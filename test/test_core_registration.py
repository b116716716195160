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
    (np.ones((10, 3)), 'all 10 points coincide'),     # CPD divided by its zero variance
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
    sf = scene_flow(X, ids, Y[::-1], ids[::-1], dt=0.5, frame='object',
                    shrinkage='none')   # two clouds: no jitter estimate, zero flow
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


def test_sparse_estep_equals_dense_with_all_pairs_and_sparse_stages_refine():
    """The k-nearest-pairs E-step is the dense one when every pair is a candidate; on a noisy
    warp larger than max_points the fine and sparse stages (all points, narrower kernel) beat
    the coarse stage alone."""
    from nrsfm_ros.core.registration.cpd import estep, estep_pairs
    rng = np.random.default_rng(5)
    X, TY = rng.normal(size=(60, 3)), rng.normal(size=(40, 3))
    dense = estep(X, TY, 0.7, 0.2)
    pairs = np.tile(np.arange(40), (60, 1))
    for a, b in zip(dense, estep_pairs(X, TY, 0.7, 0.2, pairs)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)
    X = surface(3000, seed=1)
    C = X[rng.choice(3000, 6, replace=False)]
    warped = X + 0.08 * np.exp(-((X[:, None] - C[None]) ** 2).sum(-1) / (2 * 0.4 ** 2)) \
        @ rng.normal(size=(6, 3))
    tgt = (warped + rng.normal(0, 0.01, X.shape))[rng.permutation(3000)]
    kw = dict(w=0.0, max_points=500, max_iterations=100)
    coarse = register(X, tgt, method='cpd-nonrigid', refine_points=0, sparse_points=0, **kw)
    staged = register(X, tgt, method='cpd-nonrigid', **kw)
    rmse = [np.sqrt(((r.aligned - warped) ** 2).sum(1).mean()) for r in (coarse, staged)]
    assert rmse[1] < 0.3 * rmse[0] and rmse[1] < 0.01, rmse
    with pytest.raises(ValueError, match='sparse_knn'):
        register(X, tgt, method='cpd-nonrigid', sparse_knn=-1)


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


def test_cell_tree_masses_and_barnes_hut_energy():
    from nrsfm_ros.core.registration.bhrga import CellTree, interaction_lists
    rng = np.random.default_rng(6)
    X = surface(4000)
    m = np.full(len(X), 1.0 / len(X))
    tree = CellTree(X, m, levels=6, lo=X.min(0), size=float(np.ptp(X, 0).max()) * 1.0001)
    assert len(tree.levels) == 7 and len(tree.levels[0].mass) == 1
    np.testing.assert_allclose(tree.levels[0].com[0], X.mean(0), atol=1e-12)
    for L in tree.levels:
        assert np.isclose(L.mass.sum(), 1.0)
    for L, nxt in zip(tree.levels[:-1], tree.levels[1:]):      # children partition the next
        assert L.child_count.sum() == len(nxt.mass)
        np.testing.assert_allclose(np.add.reduceat(nxt.mass, L.child_start), L.mass)
    Q = rng.uniform(-1.5, 1.5, (200, 3))
    leaf = tree.levels[-1]
    exact = (leaf.mass[None] / np.sqrt(((Q[:, None] - leaf.com[None]) ** 2).sum(-1)
                                       + 0.01)).sum(1)
    for theta, tol in ((1e-9, 1e-12), (0.5, 1e-2)):
        pi, xc, xm = interaction_lists(tree, Q, theta, leaf=6)
        approx = np.bincount(pi, xm / np.sqrt(((Q[pi] - xc) ** 2).sum(1) + 0.01), len(Q))
        assert np.abs(approx / exact - 1).max() < tol
        if theta > 0.1:
            assert len(pi) < 0.5 * len(Q) * len(leaf.mass)   # far cells were taken whole


def test_bhrga_recovers_large_rotations_and_uses_prior_masses():
    rng = np.random.default_rng(7)
    X = surface(3000)
    X[:, 2] += 0.6 * np.exp(-((X[:, 0] - 0.5) ** 2 + (X[:, 1] + 0.4) ** 2) / 0.05)
    for deg in (30, 60, 120):
        R, t = _pose(deg)
        perm = rng.permutation(3000)
        src = ((X - t) @ R)[perm] + rng.normal(0, 0.002, X.shape)
        res = register(src, X, method='bhrga')
        if deg < 90:
            assert rotation_error_deg(res.T_target_source[:3, :3], R) < 0.5, deg
            assert np.allclose(res.T_target_source[:3, 3], t, atol=0.01)
            assert res.method == 'bhrga' and res.fitness > 0.9
        else:                      # the sheet's flipped pose is the nearer energy minimum ...
            assert rotation_error_deg(res.T_target_source[:3, :3], R) > 90
            k = rng.choice(3000, 30, replace=False)      # ... until 1% prior matches weigh in
            pri = register(src, X, method='bhrga', priors=np.stack([k, perm[k]], 1))
            assert rotation_error_deg(pri.T_target_source[:3, :3], R) < 0.5
    with pytest.raises(ValueError, match='eps_end=1.0 > eps_start=0.5'):
        register(src, X, method='bhrga', eps_end=1.0)
    with pytest.raises(ValueError, match=r"unknown parameter\(s\) \['trim'\]"):
        register(src, X, method='bhrga', trim=0.5)
    with pytest.raises(ValueError, match='priors'):
        register(src, X, method='bhrga', priors=np.array([[0, 99999]]))


def test_voxel_downsample_and_coarse_to_fine_icp():
    from nrsfm_ros.core.registration.icp import voxel_downsample
    P = np.array([[0.0, 0, 0], [0.02, 0.04, 0], [1.0, 1.0, 1.0], [1.04, 1.0, 1.0]])
    V = voxel_downsample(P, 0.1)
    np.testing.assert_allclose(V[np.argsort(V[:, 0])], [[0.01, 0.02, 0], [1.02, 1.0, 1.0]])
    rng = np.random.default_rng(8)
    X = surface(20000) + rng.normal(0, 0.01, (20000, 3))
    R, t = _pose(30)
    src = (surface(20000, seed=9) - t) @ R + rng.normal(0, 0.01, (20000, 3))
    for method in ('icp', 'icp-point-to-plane'):
        vox = register(src, X, method=method, max_iterations=100, voxel=0.04)
        assert rotation_error_deg(vox.T_target_source[:3, :3], R) < 0.5, method
        assert np.allclose(vox.T_target_source[:3, 3], t, atol=0.05)   # slides on the sheet
        assert vox.correspondences.max() < len(X) and vox.fitness > 0.9
    with pytest.raises(ValueError, match='voxel=-1'):
        register(src, X, method='icp', voxel=-1.0)


def test_nrga_undoes_a_smooth_warp_and_validates():
    rng = np.random.default_rng(2)
    X = surface(2000)
    C = X[rng.choice(2000, 6, replace=False)]
    g = np.exp(-((X[:, None] - C[None]) ** 2).sum(-1) / (2 * 0.4 ** 2))
    warped = X + 0.15 * g @ rng.normal(size=(6, 3))
    start = np.sqrt(((warped - X) ** 2).sum(1).mean())
    res = register(X, warped[rng.permutation(2000)], method='nrga')
    end = np.sqrt(((res.aligned - warped) ** 2).sum(1).mean())
    assert end < 0.2 * start and res.method == 'nrga' and res.fitness > 0.9
    assert np.allclose(res.displacement, res.aligned - X)
    sub = register(X, warped, method='nrga', max_points=500)   # field extended to all points
    assert np.sqrt(((sub.aligned - warped) ** 2).sum(1).mean()) < 0.5 * start
    with pytest.raises(ValueError, match='damping=1.0'):
        register(X, warped, method='nrga', damping=1.0)
    with pytest.raises(ValueError, match=r"unknown parameter\(s\) \['w'\]"):
        register(X, warped, method='nrga', w=0.1)


def test_so3_samples_cover_rotations_and_distance_field_is_exact():
    from nrsfm_ros.core.registration.globalsearch import DistanceField, so3_samples
    Rs = so3_samples(600)
    assert np.allclose(np.einsum('rij,rkj->rik', Rs, Rs), np.eye(3), atol=1e-12)
    probe = Rotation.random(300, random_state=1).as_matrix()
    cos = (np.einsum('pij,rij->pr', probe, Rs) - 1) / 2
    gap = np.degrees(np.arccos(np.clip(cos.max(1), -1, 1)))
    assert gap.max() < 27 and np.median(gap) < 17     # every rotation has a sample nearby
    X = surface(2000)
    field = DistanceField(X, 0.02, 0.3)
    Q = np.random.default_rng(0).uniform(-1.2, 1.2, (500, 3))
    near = field.nearest(Q)
    exact = np.sqrt(((Q[:, None] - X[None]) ** 2).sum(-1)).min(1)
    assert np.all(np.isin(near, X).all(1))               # answers are target points
    got = np.linalg.norm(near - Q, axis=1)
    assert np.all(got >= exact - 1e-12) and np.all(got <= exact + 0.02 * np.sqrt(3) * 2)
    with pytest.raises(ValueError, match='rotations'):
        so3_samples(0)


def test_global_init_finds_any_rotation_through_outliers_and_a_missing_part():
    """Where trimmed ICP from the centroid lands in a wrong minimum, init='global' (SO(3)
    search + density filter) recovers the pose; the density filter drops the uniform
    clutter."""
    from nrsfm_ros.core.registration.globalsearch import density_inliers, global_pose
    rng = np.random.default_rng(3)
    u, v = rng.uniform(-1, 1, (2, 6000))
    X = np.stack([u, v, 0.5 * np.sin(2 * u) * np.cos(1.5 * v) + 0.3 * u * v + 0.2 * u ** 2], 1)
    for deg, axis in ((120, [0.3, 1.0, 0.2]), (170, [1.0, -0.4, 0.5])):
        R = Rotation.from_rotvec(np.radians(deg) * np.array(axis) / np.linalg.norm(axis))
        R = R.as_matrix()
        part = X[X[:, 0] > -0.4]                           # 30% missing
        clutter = rng.uniform(part.min(0), part.max(0), (len(part) // 2, 3))
        tgt = np.vstack([part + rng.normal(0, 0.005, part.shape), clutter]) @ R.T + [0.3, 0, 0]
        src = X + rng.normal(0, 0.005, X.shape)
        keep = density_inliers(tgt)
        assert keep[:len(part)].mean() > 0.95 and keep[len(part):].mean() < 0.25
        local = register(src, tgt, method='icp-point-to-plane', trim=0.6, voxel=0.05)
        assert rotation_error_deg(local.T_target_source[:3, :3], R) > 10
        res = register(src, tgt, method='icp-point-to-plane', trim=0.6, voxel=0.05,
                       init='global')
        assert rotation_error_deg(res.T_target_source[:3, :3], R) < 1.0
        assert np.allclose(res.T_target_source[:3, 3], [0.3, 0, 0], atol=0.02)
        g = global_pose(src, tgt, candidates=3)
        assert g.candidate_scores.shape == (3,) and g.score == g.candidate_scores.max()
    with pytest.raises(ValueError, match="init='bad'"):
        register(src, tgt, method='icp', init='bad')


def _box_surface(n: int, size, rng) -> np.ndarray:
    """``n`` points spread by area over the faces of a box with edges ``size``."""
    a = np.asarray(size, float)
    areas = np.array([a[1] * a[2], a[0] * a[2], a[0] * a[1]]).repeat(2)
    face = rng.choice(6, n, p=areas / areas.sum())
    P = rng.uniform(-0.5, 0.5, (n, 3)) * a
    axis = face // 2
    P[np.arange(n), axis] = np.where(face % 2, 0.5, -0.5) * a[axis]
    return P


def _sheet(n: int, rng) -> np.ndarray:
    u, v = rng.uniform(-1, 1, (2, n))
    return 0.5 * np.stack([u, v, 0.5 * np.sin(2 * u) * np.cos(1.5 * v) + 0.3 * u * v
                           + 0.2 * u ** 2], 1)


def _hard_pair(draw, R: np.ndarray, rng) -> tuple[np.ndarray, np.ndarray]:
    """source: ``draw(rng)`` with noise; target: an independent draw with 30% cut away by a
    plane, noise, 50% uniform outliers, rotated by R and shifted."""
    src = draw(rng)
    src = src + rng.normal(0, 0.005, src.shape)
    X = draw(rng)
    h = X @ np.array([0.6, 0.0, 0.8])
    part = X[h > np.quantile(h, 0.3)]
    part = part + rng.normal(0, 0.005, part.shape)
    clutter = rng.uniform(part.min(0), part.max(0), (len(part) // 2, 3))
    return src, np.vstack([part, clutter]) @ R.T + [0.2, -0.1, 0.05]


def test_global_start_flags_a_symmetric_box_and_trusts_an_asymmetric_shape():
    """Failure detection (issue 15): a box with three different edges looks the same after a
    half turn about any of its axes, so the best two hypotheses of the search are distinct
    rotations with near-equal scores: converged False (the pose found is still one of the
    symmetric answers).  A shape without symmetry under the same clutter: converged True and
    the right pose."""
    from nrsfm_ros.core.registration.globalsearch import global_pose
    rng = np.random.default_rng(7)
    R = Rotation.from_rotvec(np.radians(140) * np.array([0.3, 1.0, 0.2]) / 1.06).as_matrix()
    src, tgt = _hard_pair(lambda g: _box_surface(8000, (1.0, 0.7, 0.45), g), R, rng)
    g = global_pose(src, tgt)
    assert g.ambiguous
    res = register(src, tgt, method='icp-point-to-plane', init='global', trim=0.6)
    assert not res.converged
    halves = [np.eye(3), *(Rotation.from_rotvec(np.pi * e).as_matrix() for e in np.eye(3))]
    err = min(rotation_error_deg(res.T_target_source[:3, :3], R @ H) for H in halves)
    assert err < 1.0                                    # a symmetric answer, not a wrong pose
    # a curved sheet without symmetry, same clutter and cut
    src, tgt = _hard_pair(lambda g: _sheet(8000, g), R, rng)
    g = global_pose(src, tgt)
    assert not g.ambiguous
    res = register(src, tgt, method='icp-point-to-plane', init='global', trim=0.6)
    assert res.converged
    assert rotation_error_deg(res.T_target_source[:3, :3], R) < 1.0


def test_fine_levels_finish_a_pose_on_a_partial_cluttered_target():
    """Started 3 degrees off on a target with 30% missing and 50% outliers (density-filtered),
    the robust symmetric point-to-plane passes (4, 2, 1 x 1 cm grids) land within 0.5 degrees
    and 5 mm, and stop by their step test."""
    from nrsfm_ros.core.registration.globalsearch import density_inliers
    from nrsfm_ros.core.registration.refine import fine_levels
    rng = np.random.default_rng(4)
    R = Rotation.from_rotvec(np.radians(50) * np.array([1.0, -0.4, 0.5]) / 1.17).as_matrix()
    src, tgt = _hard_pair(lambda g: _sheet(12000, g), R, rng)
    tgt = tgt[density_inliers(tgt)]
    T0 = np.eye(4)
    T0[:3, :3] = Rotation.from_rotvec(np.radians(3) * np.array([0, 0, 1.0])).as_matrix() @ R
    T0[:3, 3] = [0.21, -0.1, 0.06]
    T, it, converged = fine_levels(src, tgt, T0, 0.01, iterations=15)
    assert rotation_error_deg(T[:3, :3], R) < 0.5
    assert np.allclose(T[:3, 3], [0.2, -0.1, 0.05], atol=0.005)
    assert converged and it < 45


def _bumpy_cap(n: int, rng) -> np.ndarray:
    """The front half of an ellipsoid with three smooth radial bumps (like the corpus' z-buffer
    view of a blob): a smooth shape whose rotation only its bumps pin down."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:, 2] = np.abs(d[:, 2])
    C = np.array([[0.3, 0.2, 0.9], [-0.5, 0.4, 0.7], [0.2, -0.6, 0.7]])
    C /= np.linalg.norm(C, axis=1, keepdims=True)
    r = 1 + (np.array([0.3, 0.2, 0.25]) * np.exp(-(1 - d @ C.T) / 0.25)).sum(1)
    return 0.4 * d * r[:, None] * [1.0, 0.8, 0.7]


def test_fine_levels_answer_does_not_depend_on_the_source_frame():
    """Regression (issue 15): the corpus' hard cases blob 2, sheet saddle and view of blob 1
    ended 1.35, 1.03 and 2.19 deg off reported converged.  The fine passes voxelised each cloud
    in its own frame; grids at another relative rotation cut the noisy surface differently, so
    the optimum moved with the frame the source came in and the coarse levels pulled a good
    start away.  Here, started at the true pose of a bumpy cap with 30% missing and 50%
    outliers: that answer was 1.69 deg off and moved 0.36 / 0.73 deg when the same source was
    given in two other frames; with one grid in the target frame it is 0.61 deg off and the
    same in every frame."""
    from nrsfm_ros.core.registration.globalsearch import density_inliers
    from nrsfm_ros.core.registration.refine import fine_levels
    rng = np.random.default_rng(0)
    R = Rotation.random(random_state=rng).as_matrix()
    src, tgt = _hard_pair(lambda g: _bumpy_cap(12000, g), R, rng)
    tgt = tgt[density_inliers(tgt)]
    T0 = np.eye(4)
    T0[:3, :3] = R
    T0[:3, 3] = [0.2, -0.1, 0.05]
    T, _, converged = fine_levels(src, tgt, T0, 0.01)
    assert converged and rotation_error_deg(T[:3, :3], R) < 1.0
    for rotvec in ([0.0, 0.0, 0.6], [1.0, -2.0, 0.5]):
        Q = np.eye(4)
        Q[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
        Tq = fine_levels(src @ Q[:3, :3].T, tgt, T0 @ np.linalg.inv(Q), 0.01)[0] @ Q
        assert rotation_error_deg(Tq[:3, :3], T[:3, :3]) < 0.01
        assert np.allclose(Tq[:3, 3], T[:3, 3], atol=1e-5)



def _bumpy_blob(n: int, rng) -> np.ndarray:
    """A closed ellipsoid with four smooth radial bumps: asymmetric, every rotation pinned."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    C = np.array([[0.3, 0.2, 0.9], [-0.5, 0.4, 0.7], [0.2, -0.6, 0.7], [0.1, 0.9, -0.4]])
    C /= np.linalg.norm(C, axis=1, keepdims=True)
    r = 1 + (np.array([0.3, 0.2, 0.25, 0.3]) * np.exp(-(1 - d @ C.T) / 0.25)).sum(1)
    return 0.4 * d * r[:, None] * [1.0, 0.8, 0.6]


def test_surface_pass_removes_the_voxel_grid_bias():
    """Twin noisy samples of one smooth asymmetric shape (noise 5 mm on ~1 m), 30 degrees apart:
    point-to-plane with voxel 1 cm ends on local planes of the raw points (refine.surface_pass)
    and lands at least 1.7x closer than the 4-2-1 x grid levels it replaced (their centroids
    are cut by the grid differently in each pose; measured 0.05-0.18 against 0.30-0.35 deg)."""
    from nrsfm_ros.core.registration.refine import icp_iterate, icp_levels, surface_pass
    rng = np.random.default_rng(5)
    R, t = _pose(30)
    errs_grid, errs_surface = [], []
    for _ in range(3):
        X = _bumpy_blob(30000, rng) + rng.normal(0, 0.005, (30000, 3))
        src = (_bumpy_blob(30000, rng) + rng.normal(0, 0.005, (30000, 3)) - t) @ R
        T0 = np.eye(4)
        T0[:3, 3] = X.mean(0) - src.mean(0)
        Tg = icp_iterate(icp_levels(src, X, 'point_to_plane', 0.01, 5000), T0,
                         'point_to_plane', 100, 1e-6, np.inf, 0.9, 0.01)[0]
        res = register(src, X, method='icp-point-to-plane', max_iterations=100, voxel=0.01)
        errs_grid.append(rotation_error_deg(Tg[:3, :3], R))
        errs_surface.append(rotation_error_deg(res.T_target_source[:3, :3], R))
        assert res.converged and np.allclose(res.T_target_source[:3, 3], t, atol=0.002)
    assert max(errs_surface) < 0.25 and np.mean(errs_surface) < 0.6 * np.mean(errs_grid)
    # started 0.5 deg and 1 cm off, the pass alone converges to within 0.25 deg
    T1 = res.T_target_source @ _pose_matrix(0.5, [0.01, 0, 0])
    T2, it, converged = surface_pass(src, X, T1, 0.01, iterations=15)
    assert converged and rotation_error_deg(T2[:3, :3], R) < 0.25
    far = np.eye(4)                       # no pair within 3 voxels: the pose is returned as is
    far[:3, 3] = 100.0
    assert np.array_equal(surface_pass(src, X, far, 0.01)[0], far)


def test_smallest_eigenvector_matches_eigh():
    from nrsfm_ros.core.registration.refine import smallest_eigenvector
    rng = np.random.default_rng(2)
    A = rng.normal(size=(500, 20, 3)) * [1.0, 0.6, 0.03]
    A = A @ np.linalg.qr(rng.normal(size=(3, 3)))[0]
    C = A.transpose(0, 2, 1) @ A
    v = smallest_eigenvector(C)
    e = np.linalg.eigh(C)[1][:, :, 0]
    np.testing.assert_allclose(np.abs((v * e).sum(1)), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0)
    # a repeated smallest eigenvalue / the zero matrix: some unit vector, never NaN
    out = smallest_eigenvector(np.stack([np.eye(3), np.zeros((3, 3)), np.diag([3.0, 2, 1])]))
    assert np.isfinite(out).all() and np.allclose(np.linalg.norm(out, axis=1), 1.0)
    assert np.allclose(np.abs(out[2]), [0, 0, 1])


def _pose_matrix(deg: float, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(deg) * np.array([0.3, 1.0, -0.2])
                                     / np.linalg.norm([0.3, 1.0, -0.2])).as_matrix()
    T[:3, 3] = t
    return T


def _knobbed_cylinder(n: int, rng) -> np.ndarray:
    """A capped cylinder (radius 0.5, height 2) with one small knob on its side, scaled to
    diagonal 1: symmetric but for the knob (~1% of the points, 3% of the diagonal high)."""
    u = rng.uniform(-np.pi, np.pi, n)
    v = rng.uniform(-1, 1, n)
    knob = 0.15 * np.exp(-((u - 1.0) ** 2 + (v - 0.5) ** 2) / 0.03)
    side = np.stack([0.5 * np.cos(u) * (1 + knob), 0.5 * np.sin(u) * (1 + knob), v], 1)
    m = n // 6
    r, a = 0.5 * np.sqrt(rng.uniform(0, 1, (2, m))), rng.uniform(0, 2 * np.pi, (2, m))
    caps = [np.stack([r[i] * np.cos(a[i]), r[i] * np.sin(a[i]), np.full(m, z)], 1)
            for i, z in enumerate((-1.0, 1.0))]
    X = np.vstack([side, *caps])[rng.permutation(n + 2 * m)[:n]]
    return (X - X.mean(0)) / np.linalg.norm(X.max(0) - X.min(0))


def test_symmetry_sweep_takes_its_feature_from_the_source_not_the_cut_target():
    """The knobbed cylinder with 30% of the target cut away by a plane (the knob kept) and 50%
    uniform clutter: the target's cut and clutter are off the aligned source at most turns as
    well, so a feature read from the target mixes them with the knob; read from the source's
    own asymmetry it is the knob, and the sweep lands within 1.5 degrees on three draws
    (measured 0.62 / 0.69 / 1.03; with the feature read from the target the first ended
    171 degrees off, flipped end over end)."""
    rng = np.random.default_rng(5)
    knob_dir = np.array([np.cos(1.0), np.sin(1.0), 0.0])
    errs = []
    for _ in range(3):
        src = _knobbed_cylinder(35000, rng) + rng.normal(0, 0.005, (35000, 3))
        tgt = _knobbed_cylinder(35000, rng) + rng.normal(0, 0.005, (35000, 3))
        d = rng.normal(size=3)
        d = d / np.linalg.norm(d) * (1 if d @ knob_dir >= 0 else -1)   # the knob stays
        tgt = tgt[tgt @ d > np.quantile(tgt @ d, 0.3)]
        tgt = np.vstack([tgt, rng.uniform(tgt.min(0), tgt.max(0), (len(tgt) // 2, 3))])
        R = Rotation.random(random_state=rng).as_matrix()
        res = register(src, tgt @ R.T + 0.1, method='icp-point-to-plane', init='global',
                       voxel=0.01, trim=0.6)
        errs.append(rotation_error_deg(res.T_target_source[:3, :3], R))
        assert not res.converged            # the poses were ambiguous: still reported
    assert max(errs) < 1.5, errs


def test_global_start_turns_a_near_symmetric_shape_onto_its_feature():
    """A cylinder with a knob, turned at random: the search's poses are ambiguous (every turn
    about the axis explains nearly all points), and the symmetry sweep finds the turn that puts
    the knob on the target's knob: within 1.5 degrees on three draws (without the sweep one
    of them ends 12 degrees off, at a turn about the axis; measured 0.6 / 12.3 / 0.7)."""
    import nrsfm_ros.core.registration.globalsearch as gs
    import importlib
    icp_mod = importlib.import_module('nrsfm_ros.core.registration.icp')  # (the function
    rng = np.random.default_rng(11)                                 # icp shadows the module)
    errs, unswept = [], []
    starts = []         # the global starts register made (their ambiguity, without a re-run)

    def recorded(*a, **k):
        starts.append(gs.global_pose(*a, **k))
        return starts[-1]
    for _ in range(3):
        src = _knobbed_cylinder(35000, rng) + rng.normal(0, 0.005, (35000, 3))
        R = Rotation.random(random_state=rng).as_matrix()
        tgt = (_knobbed_cylinder(35000, rng) + rng.normal(0, 0.005, (35000, 3))) @ R.T + 0.1
        icp_mod.global_pose, starts[:] = recorded, []
        try:
            res = register(src, tgt, method='icp-point-to-plane', init='global', voxel=0.01)
        finally:
            icp_mod.global_pose = gs.global_pose
        errs.append(rotation_error_deg(res.T_target_source[:3, :3], R))
        assert not res.converged            # still reported: the poses were ambiguous
        assert len(starts) == 1 and starts[0].ambiguous
        sweep, gs.symmetry_sweep = gs.symmetry_sweep, lambda Y, T, *a: (T, -np.inf)
        try:
            unswept.append(rotation_error_deg(gs.global_pose(src, tgt).T_target_source[:3, :3],
                                              R))
        finally:
            gs.symmetry_sweep = sweep
    assert max(errs) < 1.5, errs
    assert max(unswept) > 5.0, unswept


def test_ray_normal_equations_equal_the_array_form():
    """ray_pose's per-point kernel against the NumPy expressions it replaced."""
    from nrsfm_ros.core.registration._rays_kernel import ray_normal_equations
    from nrsfm_ros.core.registration.base import apply
    rng = np.random.default_rng(11)
    n, c, thr = 300, 0.9, 0.05
    x = np.c_[rng.uniform(-0.5, 0.5, (n, 2)), 2 + 0.2 * rng.normal(size=n)]
    d = x / np.linalg.norm(x, axis=1, keepdims=True)
    p = x + rng.normal(0, 0.03, (n, 3))
    G = np.eye(4)
    G[:3, :3] = Rotation.from_rotvec([0.02, -0.03, 0.01]).as_matrix()
    G[:3, 3] = [0.01, 0.0, -0.02]
    y = apply(G, p)
    v = y - x
    e = v - c * d * (d * v).sum(1, keepdims=True)
    r = np.linalg.norm(e, axis=1)
    w = 1.0 / (1.0 + (r / thr) ** 2)
    A = np.zeros((n, 3, 6))
    A[:, 0, 3] = A[:, 1, 4] = A[:, 2, 5] = 1.0
    A[:, 0, 1], A[:, 0, 2], A[:, 1, 2] = y[:, 2], -y[:, 1], y[:, 0]
    A[:, 1, 0], A[:, 2, 0], A[:, 2, 1] = -y[:, 2], y[:, 1], -y[:, 0]
    J = A - c * d[:, :, None] * np.einsum('ni,nij->nj', d, A)[:, None, :]
    Js = (J * np.sqrt(w)[:, None, None]).reshape(-1, 6)
    H, g, rk = ray_normal_equations(G, p, x, d, c, thr)
    np.testing.assert_allclose(rk, r, rtol=1e-12)
    np.testing.assert_allclose(H, Js.T @ Js, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(g, Js.T @ (e * np.sqrt(w)[:, None]).ravel(), rtol=1e-10,
                               atol=1e-14)
