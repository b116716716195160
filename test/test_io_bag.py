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


def test_large_messages_get_their_own_chunks_and_read_back(tmp_path):
    # messages >= LARGE_MESSAGE skip rosbags' buffer copies (io.bag._write_own_chunk): mixed
    # with small ones, out of stamp order, as bytes, memoryview and message objects, the bag
    # reads back the same through rosbags' own Reader, ours and the metadata's counts
    from rosbags.rosbag2 import Reader

    from nrsfm_ros.io.bag import LARGE_MESSAGE
    rng = np.random.default_rng(0)
    fac = RosbagsFactory()
    sizes = [10, LARGE_MESSAGE - 1, LARGE_MESSAGE, 3 * LARGE_MESSAGE + 5, 200]
    written = []
    with BagWriter(tmp_path / 'b') as w:
        for f in range(6):
            for k, n in enumerate(sizes):
                stamp = 1_000 + 10 * f + (7 * k) % 5
                raw = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
                w.write(f't{k}', 'std_msgs/msg/String', memoryview(raw) if k % 2 else raw,
                        stamp)
                written.append((f't{k}', stamp, raw))
            cloud = pc2.to_msg({'x': np.arange(LARGE_MESSAGE // 4, dtype=np.float32)}, fac,
                               5_000 + f, 'cam')
            w.write('cloud', 'sensor_msgs/msg/PointCloud2', cloud, 5_000 + f)
    with Reader(tmp_path / 'b') as r:
        got = [(c.topic, t, bytes(raw)) for c, t, raw in r.messages()]
        counts = {c.topic: c.msgcount for c in r.connections}
    assert [t for _, t, _ in got] == sorted(t for _, t, _ in got)
    assert sorted(x for x in got if x[0] != 'cloud') == sorted(written)
    assert counts == {**{f't{k}': 6 for k in range(len(sizes))}, 'cloud': 6}
    ours = list(read_messages(tmp_path / 'b'))
    assert sorted((m.topic, m.stamp_ns, bytes(m.raw)) for m in ours) == sorted(got)
    clouds = [deserialize(m.raw, m.msgtype) for m in ours if m.topic == 'cloud']
    assert [int(c.header.stamp.nanosec) for c in clouds] == [5_000 + f for f in range(6)]
    assert all(pc2.read_points(c)['x'][0, -1] == LARGE_MESSAGE // 4 - 1 for c in clouds)
    # the file's top-level chunk records: one per large message at least
    data = next((tmp_path / 'b').glob('*.mcap')).read_bytes()
    pos, chunks = 8, 0
    while data[pos] != 0x02:                    # up to the footer
        chunks += data[pos] == 0x06
        pos += 9 + int.from_bytes(data[pos + 1:pos + 9], 'little')
    assert chunks >= 6 * 3


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
