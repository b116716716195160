from __future__ import annotations

import cv2
import numpy as np
import pytest

from nrsfm_ros.core.metrics import track_error_px
from nrsfm_ros.core.tracking import ReferenceFlowTracker
from nrsfm_ros.io.synth import SynthConfig, generate


@pytest.fixture(scope='module')
def seq():
    return generate(SynthConfig(surface='face', width=192, height=144, frames=25))


def test_tracks_synthetic_sequence_subpixel(seq):
    tr = ReferenceFlowTracker(stride=2)
    uv = [tr.step(cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)).uv.T for im in seq.images]
    common, ia, ib = np.intersect1d(tr.ids, seq.track_ids, return_indices=True)
    assert common.size > 0.8 * seq.track_ids.size
    err = track_error_px(np.concatenate(uv)[:, ia], seq.W[:, ib], seq.V[:, ib])
    assert err < 0.8


def test_rejects_bad_frames(seq):
    tr = ReferenceFlowTracker()
    tr.step(cv2.cvtColor(seq.images[0], cv2.COLOR_RGB2GRAY))
    with pytest.raises(ValueError, match='differs from the reference'):
        tr.step(np.zeros((10, 10), np.uint8))
    with pytest.raises(ValueError, match='uint8'):
        tr.step(np.zeros((144, 192), np.float32))
    with pytest.raises(ValueError, match='trackable pixels'):
        ReferenceFlowTracker().step(np.zeros((50, 50), np.uint8))


def test_synth_ground_truth_is_consistent(seq):
    # W is the projection of S; the same config gives the same sequence
    K = seq.K
    u = seq.S[:, :, 0] / seq.S[:, :, 2] * K[0, 0] + K[0, 2]
    np.testing.assert_allclose(u, seq.W[0::2], atol=1e-9)
    again = generate(SynthConfig(surface='face', width=192, height=144, frames=25))
    np.testing.assert_array_equal(again.images, seq.images)
    assert np.isnan(seq.depth[0]).any() and np.nanmin(seq.depth) > 0
