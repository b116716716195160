"""The registrar's parameters come from the core's checks, and its output is never worse than
the identity on the same robust residual (issue 15)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from nrsfm_ros.core.registration.base import resolve_threshold, robust_residual
from nrsfm_ros.io import pointcloud2 as pc2
from nrsfm_ros.io.msgtypes import RosbagsFactory
from nrsfm_ros.params import RegistrarParams
from nrsfm_ros.processing import RegistrarProcessor

FAC = RosbagsFactory()


def _cloud(P, stamp):
    P = P.astype(np.float32)
    return pc2.to_msg({'x': P[:, 0], 'y': P[:, 1], 'z': P[:, 2]}, FAC, stamp, 'cam')


def _sheet(n=600, seed=0):
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(-1, 1, (2, n))
    return np.stack([u, v, 0.3 * np.sin(2 * u) * np.cos(1.5 * v)], 1)


@pytest.mark.parametrize('name, value, match', [
    ('trim', 0.05, r'trim=0\.05: must be in \[0\.1, 1\]'),
    ('w', 1.0, r'w=1\.0: must be in \[0, 1\)'),
    ('voxel', -0.1, r'voxel=-0\.1'),
    ('inlier_threshold', -1.0, r'inlier_threshold=-1\.0')])
def test_registrar_params_use_the_core_checks(name, value, match):
    with pytest.raises(ValueError, match=match):
        RegistrarParams().updated({name: value})


def test_registrar_accepts_the_smallest_trim_the_core_takes():
    X = _sheet()
    proc = RegistrarProcessor(FAC, RegistrarParams(trim=0.1, try_reflection=False))
    proc.handle('reference', _cloud(X, 0))
    assert len(proc.handle('points', _cloud(X + [0.05, 0, 0], 1))) == 3


def test_registrar_never_worse_than_the_identity_on_deforming_clouds():
    X = _sheet()
    thr = resolve_threshold(X, 0.0)
    tree = cKDTree(X)
    proc = RegistrarProcessor(FAC, RegistrarParams(max_iterations=1, try_reflection=False))
    proc.handle('reference', _cloud(X, 0))
    for k, amp in enumerate((0.0, 0.1, 0.3, 0.6)):
        # a flapping sheet plus a dense blob off to one side: the blob drags the centroid
        # start away and one iteration does not bring it back
        flap = X.copy()
        flap[:, 2] += amp * np.maximum(X[:, 0], 0) ** 2
        blob = np.random.default_rng(k).normal([2.5, 0, 0], 0.05, (300, 3))
        src = np.vstack([flap, blob])
        out = {t: m for t, _, m in proc.handle('points', _cloud(src, k + 1))}
        aligned = pc2.read_xyz(out['registration/aligned'])
        assert robust_residual(aligned, tree, thr) <= robust_residual(src, tree, thr) + 1e-9
    assert proc.identity_kept >= 1
    np.testing.assert_allclose(aligned, src, atol=1e-6)      # the identity was published
    off = RegistrarProcessor(FAC, RegistrarParams(max_iterations=1, try_reflection=False,
                                                  identity_guard=False))
    off.handle('reference', _cloud(X, 0))
    out = {t: m for t, _, m in off.handle('points', _cloud(src, 9))}
    moved = pc2.read_xyz(out['registration/aligned'])
    assert robust_residual(moved, tree, thr) > robust_residual(src, tree, thr)
