"""Batch solves on a spread subset of the tracks, extended to every track (core/nrsfm/extend)."""
from __future__ import annotations

import numpy as np
import pytest

from nrsfm_ros.core.metrics import e3d_frobenius
from nrsfm_ros.core.nrsfm import reconstruct
from nrsfm_ros.core.nrsfm.extend import extend, spread_subset, subset_solve
from tests_helpers import low_rank_sequence


def test_spread_subset_covers_the_tracks_evenly():
    idx = spread_subset(10000, 1000)
    assert idx.size == 1000 and idx[0] == 0 and idx[-1] == 9999
    assert np.all(np.diff(idx) >= 9) and np.all(np.diff(idx) <= 11)
    np.testing.assert_array_equal(spread_subset(50, 1000), np.arange(50))
    with pytest.raises(ValueError, match='max_tracks'):
        spread_subset(100, 3)


def test_extension_of_an_exact_subset_solve_recovers_every_track():
    """Given the true cameras and shapes of a rank-3 sequence on a subset, every other track
    is recovered (its basis coordinates are determined by its 2F measurements; the ridge and
    the basis' energy cut leave < 1e-3 of the shape's size)."""
    W, S, R = low_rank_sequence(K=3, F=40, P=600)
    F, P = 40, 600
    rng = np.random.default_rng(1)
    V = (rng.random((F, P)) > 0.2).astype(float)            # a fifth of the entries hidden
    V[:, :5] = 1.0
    idx = spread_subset(P, 150)
    from nrsfm_ros.core.nrsfm.result import NRSfMResult
    t = np.full((F, 2), 5.0)
    sub = NRSfMResult(S=S[:, idx], R=R, scale=np.ones(F), t=t, method='truth', rank=3,
                      residual_px=0.0, iterations=0, converged=True, seconds=0.0)
    full = extend(sub, idx, W, V)
    np.testing.assert_allclose(full.S[:, idx], S[:, idx])
    assert np.abs(full.S - S).max() < 1e-3 * np.abs(S).max()


def test_subset_solve_is_close_to_the_full_solve_and_far_below_a_flat_answer():
    W, S, _ = low_rank_sequence(K=3, F=60, P=1200)
    full = reconstruct(W, method='bmm')
    capped = subset_solve(lambda W, V: reconstruct(W, V, method='bmm'), W,
                          np.ones((60, 1200)), 300)
    assert capped.S.shape == full.S.shape and np.isfinite(capped.S).all()
    flat = S * np.array([1.0, 1.0, 0.0])
    e_full, e_cap = e3d_frobenius(full.S, S), e3d_frobenius(capped.S, S)
    assert e_cap < 1.1 * e_full + 0.01 and e_cap < 0.5 * e3d_frobenius(flat, S)


def test_the_stream_solves_large_batches_on_a_subset_and_publishes_every_track(monkeypatch):
    """Over BATCH_MAX_TRACKS tracks the reconstructor's batch solve runs on a spread subset:
    every pushed track still gets a finite shape in every frame, close to the full solve's."""
    import nrsfm_ros.core.nrsfm.stream as stream
    W, S, _ = low_rank_sequence(K=2, F=20, P=800)

    def run() -> list:
        st = stream.StreamNRSfM(mode='batch', batch_frames=20)
        ids = np.arange(800)
        out = []
        for f in range(20):
            out += st.push(ids, W[2 * f:2 * f + 2].T, np.ones(800))
        return out + st.flush()
    full = run()
    monkeypatch.setattr(stream, 'BATCH_MAX_TRACKS', 200)
    capped = run()
    assert len(capped) == len(full) == 20
    assert all(c.X.shape == (800, 3) and np.isfinite(c.X).all() for c in capped)
    e_full = e3d_frobenius(np.stack([c.X for c in full]), S)
    e_cap = e3d_frobenius(np.stack([c.X for c in capped]), S)
    assert e_cap < 1.1 * e_full + 0.01, (e_cap, e_full)
