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


def test_tracker_processor_downsample_returns_full_image_tracks(seq):
    """downsample 2: tracked on the half image, published in full-image pixels with the ids
    of the full image's pixels (the ground truth's), about as accurate, same density."""
    from nrsfm_ros.io import pointcloud2 as pc2
    from nrsfm_ros.io.image import array_to_image, image_to_array
    from nrsfm_ros.io.msgtypes import RosbagsFactory
    from nrsfm_ros.params import TrackerParams
    from nrsfm_ros.processing import TrackerProcessor, full_image_ids
    fac = RosbagsFactory()
    runs = {}
    for n in (1, 2):
        proc = TrackerProcessor(fac, TrackerParams(downsample=n))
        uv, flow = [], None
        for f, im in enumerate(seq.images):
            out = dict((t, m) for t, _, m in proc.handle(
                'image', array_to_image(im, 'rgb8', fac, int(seq.stamps_ns[f]), 'cam')))
            tr = out['nrsfm/tracks']
            uv.append(pc2.read_fields(tr, ('u', 'v'), np.float64).T)
            ids = pc2.read_fields(tr, ('track_id',), np.uint32)[:, 0]
            flow = image_to_array(out['nrsfm/flow'])
        common, ia, ib = np.intersect1d(ids, seq.track_ids, return_indices=True)
        assert flow.shape == (144, 192, 2)
        runs[n] = (ids.size, common.size, track_error_px(np.concatenate(uv)[:, ia],
                                                         seq.W[:, ib], seq.V[:, ib]))
    (n1, c1, e1), (n2, c2, e2) = runs[1], runs[2]
    assert c2 > 0.9 * c1                       # ids name ground-truth (full-image) pixels
    assert 0.6 * n1 < n2 < 1.4 * n1            # stride counted in full-image pixels
    assert e2 < max(2.5 * e1, 1.0), (e1, e2)   # positions in full-image pixels
    # the renaming: epoch 1, pixel (x 3, y 2) of a 10 x 8 half image -> (6, 4) of 20 x 16
    assert full_image_ids(np.array([80 + 2 * 10 + 3]), (8, 10), (16, 20), 2)[0] == \
        320 + 4 * 20 + 6


def test_tracker_processor_chain_check_reaches_the_tracker_and_diagnostics(seq):
    """``chain_check_px`` goes from the node's parameters to the MFOF tracker, and the
    observations it rejected are counted on the processor's status; off: no such key."""
    from nrsfm_ros.io.image import array_to_image
    from nrsfm_ros.io.msgtypes import RosbagsFactory
    from nrsfm_ros.params import TrackerParams
    from nrsfm_ros.processing import TrackerProcessor
    fac = RosbagsFactory()
    off = TrackerProcessor(fac, TrackerParams())
    on = TrackerProcessor(fac, TrackerParams(chain_check_px=0.05))   # strict: some rejected
    assert on.tracker.config.chain_check_px == 0.05 and 'chain_rejected' not in off.status()
    for f, im in enumerate(seq.images[:6]):
        for proc in (off, on):
            proc.handle('image', array_to_image(im, 'rgb8', fac, int(seq.stamps_ns[f]), 'cam'))
    assert int(on.status()['chain_rejected']) > 0 and off.chain_rejected == 0


def test_noise_std_reads_the_noise_of_flat_areas_not_the_texture(seq):
    from nrsfm_ros.core.tracking.reference_flow import noise_std
    rng = np.random.default_rng(0)
    flat = np.full((96, 128), 100.0)
    for sigma in (2.0, 5.0, 10.0):
        img = np.clip(np.rint(flat + rng.normal(0, sigma, flat.shape)), 0, 255).astype(np.uint8)
        assert abs(noise_std(img) - sigma) < 0.15 * sigma
    assert noise_std(flat.astype(np.uint8)) == 0.0
    # a textured surface on a flat background: the background's noise, not the texture's
    grey = cv2.cvtColor(seq.images[0], cv2.COLOR_RGB2GRAY)
    assert noise_std(grey) == 0.0
    noisy = np.clip(grey + rng.normal(0, 6.0, grey.shape), 0, 255).astype(np.uint8)
    assert 5.0 < noise_std(noisy) < 7.5


def test_texture_mask_leaves_a_noisy_flat_background_out(seq):
    """min_std 4 on a camera's noise (sigma 6 here): the flat background's local std is ~6,
    above min_std, yet it is no texture; the threshold follows the noise."""
    from nrsfm_ros.core.tracking.reference_flow import texture_mask
    grey = cv2.cvtColor(seq.images[0], cv2.COLOR_RGB2GRAY)
    seen = np.isfinite(seq.surface_st[0][..., 0])
    noisy = np.clip(grey + np.random.default_rng(1).normal(0, 6.0, grey.shape), 0, 255
                    ).astype(np.uint8)
    clean, m = texture_mask(grey), texture_mask(noisy)
    assert m[~seen].mean() < 1.5 * clean[~seen].mean() + 0.01     # background stays out
    assert m[seen].mean() > 0.9 * clean[seen].mean()               # the surface stays in


def test_check_trackable_agrees_with_reference_pixels(seq):
    """The tracker node's per-frame check raises exactly where a reference could not be set
    on the frame, with the same message."""
    from nrsfm_ros.core.tracking.reference_flow import check_trackable, reference_pixels
    grey = cv2.cvtColor(seq.images[0], cv2.COLOR_RGB2GRAY)
    flat = np.full_like(grey, 90)
    dot = flat.copy()
    dot[40:44, 50:54] = 200             # a few textured pixels: a handful on the grid
    for g in (grey, flat, dot, grey[:5, :5]):
        for mask, stride in (('texture', 2), ('texture', 7), ('full', 3)):
            try:
                reference_pixels(g, mask, stride, 4.0)
                want = None
            except ValueError as err:
                want = str(err)
            try:
                check_trackable(g, mask, stride, 4.0)
                got = None
            except ValueError as err:
                got = str(err)
            assert got == want, (g.shape, mask, stride)
    with pytest.raises(ValueError, match='only 0 trackable pixels'):
        check_trackable(flat, 'texture', 2, 4.0)
