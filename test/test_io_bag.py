from __future__ import annotations

import threading

import numpy as np
import pytest

from nrsfm_ros.io import pointcloud2 as pc2
from nrsfm_ros.io.bag import BagWriter, bag_info, deserialize, read_messages
from nrsfm_ros.io.msgtypes import RosbagsFactory


def write_bag(path, n=20):
    fac = RosbagsFactory()
    with BagWriter(path) as w:
        for i in range(n):
            stamp = 1_000_000_000 + i * 20_000_000
            cloud = pc2.to_msg({'x': np.full(100, i, np.float32)}, fac, stamp, 'cam')
            w.write('nrsfm/points', 'sensor_msgs/msg/PointCloud2', cloud, stamp)
            w.write('registration/reference', 'sensor_msgs/msg/PointCloud2', cloud, stamp) \
                if i == 0 else None
    return path


def test_write_read_identity(tmp_path):
    bag = write_bag(tmp_path / 'b')
    info = bag_info(bag)
    assert info['topics']['nrsfm/points']['count'] == 20
    msgs = list(read_messages(bag, ['nrsfm/points']))
    assert [m.stamp_ns for m in msgs] == sorted(m.stamp_ns for m in msgs)
    for i, m in enumerate(msgs):
        cloud = deserialize(m.raw, m.msgtype)
        assert pc2.read_points(cloud)['x'][0, 0] == i
    with pytest.raises(FileExistsError):
        BagWriter(bag)


def test_replay_into_recorder_is_byte_identical(tmp_path, rclpy_context):
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from nrsfm_ros.live import Recorder, replay
    bag = write_bag(tmp_path / 'in')
    node = Node('bag_test', context=rclpy_context)
    rec = Recorder(node, ['nrsfm/points', 'registration/reference'], tmp_path / 'out',
                   known_types={'nrsfm/points': 'sensor_msgs/msg/PointCloud2',
                                'registration/reference': 'sensor_msgs/msg/PointCloud2'})
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    t = threading.Thread(target=ex.spin, daemon=True)
    t.start()
    try:
        counts = replay(node, bag, rate=4.0, wait_subscribers={'nrsfm/points': 1})
        assert counts['nrsfm/points'] == 20
        import time
        end = time.monotonic() + 5
        while rec.counts['/nrsfm/points'] < 20 and time.monotonic() < end:
            time.sleep(0.05)
    finally:
        ex.shutdown()
        got = rec.close()
        node.destroy_node()
    assert got['/nrsfm/points'] == 20 and got['/registration/reference'] == 1
    a = [m.raw for m in read_messages(bag, ['nrsfm/points'])]
    b = [m.raw for m in read_messages(tmp_path / 'out', ['nrsfm/points'])]
    assert a == b
