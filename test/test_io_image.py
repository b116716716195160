from __future__ import annotations

import numpy as np
import pytest

from nrsfm_ros.io import image as img_io
from nrsfm_ros.io.errors import MessageError
from nrsfm_ros.io.msgtypes import RclpyFactory, RosbagsFactory

rng = np.random.default_rng(1)
CASES = {
    'rgb8': rng.integers(0, 256, (7, 9, 3)).astype(np.uint8),
    'bgr8': rng.integers(0, 256, (7, 9, 3)).astype(np.uint8),
    'mono8': rng.integers(0, 256, (7, 9)).astype(np.uint8),
    '16UC1': rng.integers(0, 65535, (7, 9)).astype(np.uint16),
    '32FC1': rng.normal(size=(7, 9)).astype(np.float32),
    '32FC2': rng.normal(size=(7, 9, 2)).astype(np.float32),
}


@pytest.mark.parametrize('fac', [RosbagsFactory(), RclpyFactory()], ids=lambda f: f.backend)
@pytest.mark.parametrize('enc', list(CASES))
def test_round_trip(fac, enc):
    msg = img_io.array_to_image(CASES[enc], enc, fac, 1, 'cam')
    np.testing.assert_array_equal(img_io.image_to_array(msg), CASES[enc])


@pytest.mark.parametrize('enc', list(CASES))
def test_row_padding(enc):
    fac = RosbagsFactory()
    a = CASES[enc]
    msg = img_io.array_to_image(a, enc, fac, 1, 'cam')
    pad = 5
    rows = np.frombuffer(msg.data, np.uint8).reshape(a.shape[0], -1)
    padded = np.concatenate([rows, np.zeros((a.shape[0], pad), np.uint8)], axis=1)
    msg.data = padded.reshape(-1)
    msg.step = rows.shape[1] + pad
    np.testing.assert_array_equal(img_io.image_to_array(msg), a)


def test_big_endian_16UC1():
    fac = RosbagsFactory()
    a = CASES['16UC1']
    msg = img_io.array_to_image(a, '16UC1', fac, 1, 'cam')
    msg.data = np.frombuffer(a.astype('>u2').tobytes(), np.uint8)
    msg.is_bigendian = 1
    np.testing.assert_array_equal(img_io.image_to_array(msg), a)


@pytest.mark.parametrize('fmt', ['png', 'jpeg'])
def test_compressed(fmt):
    fac = RosbagsFactory()
    a = np.tile(np.linspace(0, 255, 32, dtype=np.uint8), (24, 1))
    rgb = np.stack([a, a[::-1], a], axis=2)
    msg = img_io.array_to_compressed(rgb, 'rgb8', fac, 1, 'cam', fmt)
    out, enc = img_io.compressed_to_array(msg)
    assert enc == 'bgr8'
    tol = 0 if fmt == 'png' else 12
    assert np.abs(out[..., ::-1].astype(int) - rgb).max() <= tol


@pytest.mark.parametrize('mutate, name', [
    (lambda m: setattr(m, 'encoding', 'yuv422'), 'encoding'),
    (lambda m: setattr(m, 'step', 1), 'step'),
    (lambda m: setattr(m, 'data', m.data[:10]), 'data'),
    (lambda m: setattr(m, 'height', 0), 'height'),
])
def test_malformed(mutate, name):
    msg = img_io.array_to_image(CASES['rgb8'], 'rgb8', RosbagsFactory(), 1, 'cam')
    mutate(msg)
    with pytest.raises(MessageError) as err:
        img_io.image_to_array(msg)
    assert err.value.field == name


def test_corrupt_compressed():
    fac = RosbagsFactory()
    msg = fac.make('sensor_msgs/msg/CompressedImage', header=fac.header(0, ''), format='png',
                   data=np.frombuffer(b'not a png', np.uint8))
    with pytest.raises(MessageError, match='could not decode'):
        img_io.compressed_to_array(msg)


def test_wrong_array_for_encoding():
    with pytest.raises(ValueError, match='rgb8 needs dtype u1 with 3'):
        img_io.array_to_image(np.zeros((4, 4), np.uint8), 'rgb8', RosbagsFactory(), 0, '')


def test_flo_round_trip_and_errors(tmp_path):
    from nrsfm_ros.io.flo import endpoint_error, read_flo, write_flo
    rng = np.random.default_rng(0)
    flow = rng.normal(size=(7, 9, 2)).astype(np.float32)
    flow[2, 3] = np.nan
    write_flo(tmp_path / 'a.flo', flow)
    back = read_flo(tmp_path / 'a.flo')
    np.testing.assert_array_equal(np.isnan(back), np.isnan(flow))
    np.testing.assert_array_equal(back[~np.isnan(back)], flow[~np.isnan(flow)])
    assert endpoint_error(back + [3.0, 4.0], flow) == pytest.approx(5.0)
    (tmp_path / 'b.flo').write_bytes(b'\x00' * 20)
    with pytest.raises(ValueError, match='magic'):
        read_flo(tmp_path / 'b.flo')
    (tmp_path / 'c.flo').write_bytes((tmp_path / 'a.flo').read_bytes()[:-8])
    with pytest.raises(ValueError, match='header says 9x7'):
        read_flo(tmp_path / 'c.flo')


def test_middlebury_ground_truth_reads():
    from conftest import shared_data

    from nrsfm_ros.io.flo import read_flo
    gt = read_flo(shared_data('flow', 'middlebury', 'Venus', 'flow10.flo'))
    assert gt.shape[2] == 2 and np.isfinite(gt).mean() > 0.9
