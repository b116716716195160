from __future__ import annotations

import array

import numpy as np
import pytest

from nrsfm_ros.io import pointcloud2 as pc2
from nrsfm_ros.io.bag import deserialize, serialize
from nrsfm_ros.io.errors import MessageError
from nrsfm_ros.io.msgtypes import RclpyFactory, RosbagsFactory

FACTORIES = [RosbagsFactory(), RclpyFactory()]


def field(fac, name, offset, datatype, count=1):
    return fac.make('sensor_msgs/msg/PointField', name=name, offset=offset, datatype=datatype,
                    count=count)


def cloud(fac, fields, data, height, width, point_step, row_step=None, big=False):
    return fac.make('sensor_msgs/msg/PointCloud2', header=fac.header(5, 'f'), height=height,
                    width=width, fields=fields, is_bigendian=big, point_step=point_step,
                    row_step=row_step if row_step is not None else point_step * width,
                    data=np.frombuffer(bytes(data), np.uint8), is_dense=False)


@pytest.mark.parametrize('fac', FACTORIES, ids=lambda f: f.backend)
def test_round_trip_columns(fac):
    rng = np.random.default_rng(0)
    x = rng.normal(size=1000).astype(np.float32)
    x[3] = np.nan
    ids = np.arange(1000, dtype=np.uint32)
    rgb = pc2.pack_rgb(rng.integers(0, 256, (1000, 3)).astype(np.uint8))
    msg = pc2.to_msg({'x': x, 'y': x * 2, 'z': x * 3, 'rgb': rgb, 'track_id': ids}, fac, 7, 'cam')
    assert msg.is_dense is False and msg.point_step == 20 and msg.width == 1000
    pts = pc2.read_points(msg)
    assert pts.shape == (1, 1000)
    np.testing.assert_array_equal(pts['track_id'][0], ids)
    np.testing.assert_array_equal(pc2.unpack_rgb(pts['rgb'][0]), pc2.unpack_rgb(rgb))
    xyz = pc2.read_xyz(msg)
    assert xyz.shape == (999, 3)  # the NaN point is skipped
    assert pc2.read_xyz(msg, skip_nans=False).shape == (1000, 3)


def test_rclpy_data_is_array_fast_path():
    fac = RclpyFactory()
    msg = pc2.to_msg({'x': np.zeros(10, np.float32)}, fac, 0, 'f')
    assert isinstance(msg.data, array.array) and msg.data.typecode == 'B'


def test_zero_copy_view():
    fac = RosbagsFactory()
    msg = pc2.to_msg({'x': np.arange(5, dtype=np.float32)}, fac, 0, 'f')
    pts = pc2.read_points(msg)
    assert np.shares_memory(pts, msg.data)


def test_organised_padding_big_endian_and_count():
    fac = RosbagsFactory()
    # point_step 16 with padding; x at 0 (f4 BE), xyz-normal triple at 4 as count=3 int16
    h, w, step = 2, 3, 16
    row_step = w * step + 8  # row padding
    buf = bytearray(row_step * h)
    vals = np.arange(h * w, dtype='>f4')
    for r in range(h):
        for c in range(w):
            o = r * row_step + c * step
            buf[o:o + 4] = vals[r * w + c:r * w + c + 1].tobytes()
            buf[o + 4:o + 10] = np.array([1, 2, 3], '>i2').tobytes()
    msg = cloud(fac, [field(fac, 'x', 0, pc2.FLOAT32), field(fac, 'n', 4, pc2.INT16, 3)],
                buf, h, w, step, row_step, big=True)
    pts = pc2.read_points(msg)
    assert pts.shape == (2, 3)
    np.testing.assert_array_equal(pts['x'].ravel(), vals)
    np.testing.assert_array_equal(pts['n'][1, 2], [1, 2, 3])
    np.testing.assert_array_equal(pc2.read_fields(msg, ['x'])[:, 0], vals.astype(np.float32))


@pytest.mark.parametrize('mutate, field_name', [
    (lambda m: setattr(m, 'point_step', 2), 'fields[0].offset'),
    (lambda m: setattr(m, 'row_step', 1), 'row_step'),
    (lambda m: setattr(m, 'width', 1000), 'row_step'),
    (lambda m: setattr(m, 'data', m.data[:5]), 'data'),
    (lambda m: setattr(m.fields[0], 'datatype', 42), 'fields[0].datatype'),
    (lambda m: setattr(m.fields[1], 'name', 'x'), 'fields[1].name'),
])
def test_malformed_messages_name_the_field(mutate, field_name):
    fac = RosbagsFactory()
    msg = pc2.to_msg({'x': np.zeros(4, np.float32), 'y': np.zeros(4, np.float32)}, fac, 0, 'f')
    mutate(msg)
    with pytest.raises(MessageError) as err:
        pc2.read_points(msg)
    assert err.value.field == field_name


def test_missing_field_error():
    msg = pc2.to_msg({'x': np.zeros(4, np.float32)}, RosbagsFactory(), 0, 'f')
    with pytest.raises(MessageError, match="missing required field 'y'"):
        pc2.read_xyz(msg)


def test_rclpy_and_rosbags_messages_agree():
    # CDR padding bytes are unspecified, so compare decoded content, both directions
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import PointCloud2
    cols = {'x': np.linspace(0, 1, 50, dtype=np.float32),
            'track_id': np.arange(50, dtype=np.uint32)}
    a = pc2.to_msg(cols, RosbagsFactory(), 123456789, 'cam')
    b = pc2.to_msg(cols, RclpyFactory(), 123456789, 'cam')
    from_rclpy = deserialize(serialize_message(b), 'sensor_msgs/msg/PointCloud2')
    from_rosbags = deserialize_message(serialize(a, 'sensor_msgs/msg/PointCloud2'), PointCloud2)
    for m in (from_rclpy, from_rosbags):
        assert bytes(m.data) == bytes(a.data)
        assert pc2.field_names(m) == ['x', 'track_id']
        assert m.header.stamp.sec == 0 and m.header.stamp.nanosec == 123456789


def legacy_bytes(cols):
    """The layout to_msg wrote before issue 17: one packed little-endian structured array, fields
    in mapping order, no padding (the reference the in-place packing must reproduce)."""
    arrays = {k: np.asarray(v) for k, v in cols.items()}
    ref = np.empty(len(next(iter(arrays.values()))),
                   np.dtype([(k, v.dtype.newbyteorder('<')) for k, v in arrays.items()]))
    for k, v in arrays.items():
        ref[k] = v
    offsets = [ref.dtype.fields[k][1] for k in ref.dtype.names]
    return ref.tobytes(), offsets, ref.dtype.itemsize


def node_layouts(n, rng):
    X = rng.normal(size=(n, 3)).astype(np.float32)
    if n:
        X[rng.integers(0, n, max(1, n // 50)), 1] = np.nan
    V = rng.normal(size=(n, 3)).astype(np.float32)
    ids = rng.permutation(n).astype(np.uint32)
    rgb = pc2.pack_rgb(rng.integers(0, 256, (n, 3)).astype(np.uint8))
    vis = (rng.random(n) > 0.2).astype(np.float32)
    return {
        'tracks': {'u': X[:, 0], 'v': X[:, 1], 'track_id': ids, 'visibility': vis, 'rgb': rgb,
                   'occlusion': 1 - vis},
        'points': {'x': X[:, 0], 'y': X[:, 1], 'z': X[:, 2], 'rgb': rgb, 'track_id': ids},
        'scene_flow': {'x': X[:, 0], 'y': X[:, 1], 'z': X[:, 2], 'vx': V[:, 0], 'vy': V[:, 1],
                       'vz': V[:, 2], 'track_id': ids},
        'mixed': {'a': rng.integers(0, 255, n).astype(np.uint8), 'b': X[:, 2].astype('>f8'),
                  'c': rng.integers(-9, 9, n).astype('>i2'), 'd': ids.astype(np.int32),
                  'e': V[:, 0].astype(np.float64)},
    }


# 70_001 points: several packing blocks with a ragged last one; 1 and 0: the edge cases
@pytest.mark.parametrize('n', [0, 1, 1000, 70_001])
@pytest.mark.parametrize('fac', FACTORIES, ids=lambda f: f.backend)
def test_packed_bytes_identical_to_legacy_layout(fac, n):
    rng = np.random.default_rng(n)
    for name, cols in node_layouts(n, rng).items():
        msg = pc2.to_msg(cols, fac, 7, 'cam')
        data, offsets, step = legacy_bytes(cols)
        assert bytes(msg.data) == data, name
        assert [f.name for f in msg.fields] == list(cols), name
        assert [f.offset for f in msg.fields] == offsets, name
        assert all(f.count == 1 for f in msg.fields), name
        assert (msg.point_step, msg.row_step, msg.width, msg.height) == (step, step * n, n, 1)
        assert msg.is_dense == (n == 0 or name == 'mixed'), name
        assert msg.is_bigendian is False
        # and the same bytes the structured-array input and pack() give
        packed = pc2.pack(cols)
        assert packed.tobytes() == data
        assert bytes(pc2.to_msg(packed, fac, 7, 'cam').data) == data
        back = pc2.read_points(msg).reshape(-1)
        for k, v in cols.items():
            np.testing.assert_array_equal(back[k], v, err_msg=f'{name}.{k}')
    if fac.backend == 'rclpy':
        assert isinstance(msg.data, array.array) and msg.data.typecode == 'B'


@pytest.mark.parametrize('fac', FACTORIES, ids=lambda f: f.backend)
def test_structured_input_copied_byte_for_byte(fac):
    # padding bytes, an organised cloud, count 3 and a non-contiguous input
    dt = np.dtype({'names': ['x', 'n'], 'formats': ['<f4', ('<i2', (3,))], 'offsets': [0, 4],
                   'itemsize': 16})
    raw = np.random.default_rng(1).integers(0, 256, 16 * 24, dtype=np.uint8)
    pts = raw.view(dt)[::2].reshape(3, 4)          # 12 points, every second one
    msg = pc2.to_msg(pts, fac, 0, 'cam', height=3)
    assert bytes(msg.data) == np.ascontiguousarray(pts).tobytes()
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (3, 4, 16, 64)
    assert [(f.name, f.offset, f.count) for f in msg.fields] == [('x', 0, 1), ('n', 4, 3)]


@pytest.mark.parametrize('cols, text', [
    ({}, 'at least one field'),
    ({'x': np.zeros(3, np.float32), 'y': np.zeros(4, np.float32)}, 'same length'),
    ({'x': np.zeros((3, 2), np.float32)}, "columns['x']: expected a 1-D array"),
    ({'x': np.zeros(3, np.complex64)}, "columns['x']: dtype complex64"),
])
def test_bad_columns_name_the_column(cols, text):
    with pytest.raises(ValueError, match=text.replace('[', r'\[').replace(']', r'\]')):
        pc2.to_msg(cols, RclpyFactory(), 0, 'cam')
    with pytest.raises(ValueError, match='height: 4 does not divide'):
        pc2.to_msg({'x': np.zeros(6, np.float32)}, RosbagsFactory(), 0, 'cam', height=4)


def test_factories_build_point_lists_as_make_does():
    """MsgFactory.points (the scene-flow markers' segments) equals one make per row, for both
    backends."""
    from nrsfm_ros.io.msgtypes import MsgFactory, RclpyFactory, RosbagsFactory
    xyz = np.array([[0.5, -1.25, 3.0], [1e-3, 2.0, -0.0]], np.float32)
    for fac in (RosbagsFactory(), RclpyFactory()):
        got = fac.points(xyz)
        want = MsgFactory.points(fac, xyz)      # the generic form: make per row
        assert len(got) == 2 and type(got[0]) is type(want[0])
        for g, w in zip(got, want):
            assert (g.x, g.y, g.z) == (w.x, w.y, w.z)
        assert (got[0].x, got[0].y, got[0].z) == (0.5, -1.25, 3.0)
    assert RosbagsFactory().points(np.zeros((0, 3))) == []
