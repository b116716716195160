"""One meaning of fitness and inlier RMSE for every method (issue 15)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from nrsfm_ros.core.registration import METHODS, register
from nrsfm_ros.core.registration.base import inlier_stats, resolve_threshold, robust_residual


def _case():
    """800 source points: 500 on a bumpy sheet, 300 outliers at least 3 thresholds off it; the
    target is the sheet alone, rotated 10 degrees and shifted."""
    rng = np.random.default_rng(0)
    u, v = rng.uniform(-1, 1, (2, 500))
    S = np.stack([u, v, 0.4 * np.sin(2 * u) * np.cos(1.5 * v) + 0.2 * u * v
                  + 0.5 * np.exp(-((u - 0.5) ** 2 + (v + 0.4) ** 2) / 0.05)], 1)
    R = Rotation.from_rotvec(np.radians(10) * np.array([0.3, 1.0, 0.2]) / 1.06).as_matrix()
    t = np.array([0.05, -0.1, 0.02])
    tgt = S @ R.T + t
    thr = resolve_threshold(tgt, 0.0)
    box = rng.uniform(S.min(0), S.max(0), (20000, 3))
    far = box[cKDTree(S).query(box)[0] > 3 * thr][:300]
    src = np.vstack([S, far])
    return src, tgt, R, t, thr


RIGID = ['icp', 'icp-point-to-plane', 'cpd-rigid', 'ga', 'bhrga']
KW = {'icp': dict(trim=0.6), 'icp-point-to-plane': dict(trim=0.6), 'cpd-rigid': dict(w=0.4),
      'ga': dict(polish_trim=0.6), 'bhrga': dict(polish_trim=0.6)}   # trim: about the overlap


def test_every_method_reports_the_same_fitness_and_inlier_rmse_on_a_known_case():
    src, tgt, R, t, thr = _case()
    truth = inlier_stats(src @ R.T + t, cKDTree(tgt), thr)
    assert truth[1] == pytest.approx(500 / 800) and truth[2] < 1e-12
    for method in RIGID:
        res = register(src, tgt, method=method, **KW.get(method, {}))
        assert res.inlier_threshold == pytest.approx(thr), method
        assert res.fitness == pytest.approx(500 / 800), (method, res.fitness)
        assert res.inlier_rmse < 1e-4, (method, res.inlier_rmse)
        assert res.residual == res.inlier_rmse
        assert np.array_equal(res.correspondences >= 0, truth[0] >= 0), method


def test_bounded_queries_equal_brute_force_distances():
    """inlier_stats and robust_residual stop their searches at the threshold: the same
    correspondences (mapped by ``index``), fitness, RMSE and residual as all distances."""
    rng = np.random.default_rng(3)
    tgt = rng.uniform(-1, 1, (400, 3))
    src = np.vstack([tgt[:250] + rng.normal(0, 0.02, (250, 3)), rng.uniform(-2, 2, (150, 3))])
    index = rng.permutation(1000)[:400]               # tree rows -> indices of a larger target
    D = np.linalg.norm(src[:, None] - tgt[None], axis=2)
    near, d = D.argmin(1), D.min(1)
    for thr in (0.01, 0.05, 0.3):
        corr, fit, rmse = inlier_stats(src, cKDTree(tgt), thr, index)
        ok = d <= thr
        assert 0 < ok.sum() < len(src)
        assert np.array_equal(corr, np.where(ok, index[near], -1))
        assert fit == pytest.approx(ok.mean())
        assert rmse == pytest.approx(np.sqrt(np.mean(d[ok] ** 2)))
        assert robust_residual(src, cKDTree(tgt), thr) == pytest.approx(
            np.mean(np.minimum(d, thr) ** 2))


@pytest.mark.parametrize('method', sorted(set(METHODS) - {'ecpd-rigid', 'ecpd-nonrigid'}))
def test_reported_numbers_are_the_base_evaluation_of_the_output(method):
    src, tgt, _, _, _ = _case()
    kw = dict(max_iterations=20) if method not in ('bhrga', 'nrga') else {}
    res = register(src[::4], tgt, method=method, inlier_threshold=0.05, **kw)
    corr, fit, rmse = inlier_stats(res.aligned, cKDTree(tgt), 0.05)
    assert res.fitness == fit and res.inlier_threshold == 0.05
    assert np.array_equal(res.correspondences, corr)
    assert res.inlier_rmse == pytest.approx(rmse, nan_ok=True)


def test_inlier_threshold_is_checked_by_name_and_value():
    src, tgt, _, _, _ = _case()
    for method in ('icp', 'cpd-rigid', 'ga', 'bhrga', 'nrga'):
        with pytest.raises(ValueError, match=r'inlier_threshold=-1\.0'):
            register(src, tgt, method=method, inlier_threshold=-1.0)
    with pytest.raises(ValueError, match=r'trim=0\.05: must be in \[0\.1, 1\]'):
        register(src, tgt, method='icp', trim=0.05)


def test_method_modules_import_the_base_and_no_other_method():
    import ast
    from pathlib import Path

    import nrsfm_ros.core.registration as reg
    here = Path(reg.__file__).parent
    methods = {'icp', 'cpd', 'gravitational', 'bhrga', 'nrga'}
    for name in methods | {'globalsearch'}:
        tree = ast.parse((here / f'{name}.py').read_text())
        local = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.level}
        assert 'base' in local or name == 'globalsearch', name
        assert not local & (methods - {name}), (name, local)
        assert name != 'globalsearch' or not local & methods
