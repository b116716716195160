"""The reconstructor's batch measured in time (``batch_seconds``): the stream's frame rate from
the first tracks' stamps sets the batch's frames, so a 30 frames/s camera's batch sees the
camera motion a 10 frames/s one does; the stream's ``set_batch`` and its limits."""
from __future__ import annotations

import numpy as np
import pytest

from nrsfm_ros.core.nrsfm.stream import StreamNRSfM
from nrsfm_ros.io import pointcloud2 as pc2
from nrsfm_ros.io.msgtypes import RosbagsFactory
from nrsfm_ros.params import ReconstructorParams
from nrsfm_ros.processing import ReconstructorProcessor

FAC = RosbagsFactory()


def _tracks(f: int, fps: float, P: int = 60):
    g = np.stack(np.meshgrid(np.arange(10), np.arange(6)), -1).reshape(-1, 2)[:P] * 3.0 + 5
    t = 0.2 * f
    uv = g + np.stack([np.sin(t + g[:, 1] * 0.2), 0.5 * np.cos(t + g[:, 0] * 0.1)], 1)
    return pc2.to_msg({'u': uv[:, 0].astype(np.float32), 'v': uv[:, 1].astype(np.float32),
                       'track_id': np.arange(P, dtype=np.uint32),
                       'visibility': np.ones(P, np.float32)},
                      FAC, 10 ** 9 + int(round(f * 1e9 / fps)), 'cam')


def _first_batch(params: ReconstructorParams, fps: float, frames: int) -> int:
    """The message at which the first clouds come out (1-based), or 0."""
    proc = ReconstructorProcessor(FAC, params)
    for f in range(frames):
        if any(t == 'nrsfm/points' for t, _, _ in proc.handle('tracks', _tracks(f, fps))):
            return f + 1
    return 0


@pytest.mark.parametrize('fps, frames', [(10.0, 60), (30.0, 180), (5.0, 30)])
def test_the_batch_spans_batch_seconds_at_any_frame_rate(fps, frames):
    assert _first_batch(ReconstructorParams(), fps, frames + 5) == frames
    proc = ReconstructorProcessor(FAC, ReconstructorParams())
    for f in range(6):
        proc.handle('tracks', _tracks(f, fps))
    assert proc.stream.batch_frames == frames
    assert proc.stream.batch_context == frames // 2     # batch_context's share of 60


def test_batch_seconds_zero_and_bad_stamps_keep_batch_frames():
    assert _first_batch(ReconstructorParams(batch_seconds=0), 30.0, 70) == 60
    proc = ReconstructorProcessor(FAC, ReconstructorParams(batch_frames=20))
    for f in range(6):      # every stamp equal: no rate
        m = _tracks(f, 30.0)
        m.header.stamp.sec, m.header.stamp.nanosec = 5, 0
        proc.handle('tracks', m)
    assert proc.stream.batch_frames == 20
    # 1000 frames/s x 6 s: capped
    proc = ReconstructorProcessor(FAC, ReconstructorParams())
    for f in range(6):
        proc.handle('tracks', _tracks(f, 1000.0))
    assert proc.stream.batch_frames == ReconstructorProcessor.MAX_BATCH_FRAMES


def test_set_batch_resizes_before_the_first_solve_only():
    s = StreamNRSfM(mode='batch', batch_frames=10, batch_context=5)
    rng = np.random.default_rng(0)
    ids = np.arange(30)
    for _ in range(4):
        assert s.push(ids, rng.normal(size=(30, 2)) * 10) == []
    s.set_batch(6, 3)
    assert s.batch_frames == 6 and s.batch_context == 3
    with pytest.raises(ValueError, match='batch_frames: expected an integer >= 3'):
        s.set_batch(2, 0)
    with pytest.raises(ValueError, match='batch_context'):
        s.set_batch(6, -1)
    s.push(ids, rng.normal(size=(30, 2)) * 10)
    assert len(s.push(ids, rng.normal(size=(30, 2)) * 10)) == 6      # the 6th frame solves
    with pytest.raises(ValueError, match='solved already'):
        s.set_batch(20, 10)
    spva = StreamNRSfM(mode='spva', batch_frames=20, spva_prior_frames=10)
    with pytest.raises(ValueError, match='below spva_prior_frames'):
        spva.set_batch(8, 0)


def test_the_streams_bmm_threshold_follows_the_batchs_frames():
    """bmm's nuclear-norm weight in the stream: its own up to 60 frames, x sqrt(F / 60) beyond
    (a 30 frames/s camera's 180-frame batch: x sqrt(3)), and it reaches the stream's solves."""
    from scipy.spatial.transform import Rotation

    from nrsfm_ros.core.nrsfm import bmm, stream
    assert stream.bmm_lam(20) == stream.bmm_lam(60) == stream.BMM_LAM == 4.0
    assert stream.bmm_lam(240) == pytest.approx(8.0)
    rng = np.random.default_rng(0)
    u, v = rng.uniform(-1, 1, (2, 60))
    X, B, F = np.stack([u, v, 0.8 * (u ** 2 + v ** 2)]), rng.normal(size=(3, 60)), 120
    Rs = Rotation.from_euler('yx', np.stack([0.5 * np.sin(np.arange(F) / 15),
                                             0.2 * np.cos(np.arange(F) / 11)], 1)).as_matrix()
    W = 100 * np.concatenate([R[:2] @ (X + 0.1 * np.sin(f / 7) * B) for f, R in enumerate(Rs)])
    W += 0.3 * rng.normal(size=W.shape)
    V = np.ones((F, 60))
    got = stream._solve_all(W, V, 'bmm', 2).S
    scaled = bmm(W, V, lam=4.0 * np.sqrt(2.0), iterations=stream.BMM_ITERATIONS).S
    plain = bmm(W, V, lam=4.0, iterations=stream.BMM_ITERATIONS).S
    assert np.abs(got - scaled).max() < 1e-3 * np.abs(got).max() < np.abs(got - plain).max()
