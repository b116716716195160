from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nrsfm_ros.core.metrics import e3d_frobenius, e3d_normalized
from nrsfm_ros.core.nrsfm import WindowNRSfM, reconstruct
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
    win = WindowNRSfM(window=20, rank=2)
    out = []
    for f in range(40):
        got = win.push(W[2 * f:2 * f + 2].T)
        assert len(got) == (0 if f < 19 else 20 if f == 19 else 1)
        out += got
    assert [o.index for o in out] == list(range(40))
    S_hat = np.stack([o.S * o.scale for o in out])
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
