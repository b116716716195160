"""Conversion and transport benchmark: build/parse time per message and node->node latency.

    .venv/bin/python bench/bench_transport.py [--json out.json]

Build: NumPy -> message with our conversion (rclpy messages, fast array('B') path) against the
naive rclpy path (assigning the NumPy byte array to msg.data), as a ratio.  Parse: message ->
NumPy (zero-copy structured view, then an (N, 3) float copy).  Latency: one process publishes at
30 Hz over the loopback Fast DDS profile (32 MiB shared memory), another receives; p50/p90 of
receive time - header stamp (same clock).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from nrsfm_ros.io import image as img_io  # noqa: E402
from nrsfm_ros.io import pointcloud2 as pc2  # noqa: E402
from nrsfm_ros.io.msgtypes import RclpyFactory  # noqa: E402
from nrsfm_ros.live import ensure_loopback_env  # noqa: E402


def timeit(fn, repeat: int) -> float:
    best = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best.append(time.perf_counter() - t)
    return statistics.median(best) * 1e3


def cloud_cols(n: int) -> dict[str, np.ndarray]:
    X = np.random.default_rng(0).normal(size=(n, 3)).astype(np.float32)
    return {'x': X[:, 0], 'y': X[:, 1], 'z': X[:, 2], 'track_id': np.arange(n, dtype=np.uint32)}


def conversion_rows() -> list[dict]:
    from sensor_msgs.msg import PointCloud2
    fac = RclpyFactory()
    rows = []
    for n in (5_000, 100_000, 1_000_000):
        cols = cloud_cols(n)
        repeat = 20 if n < 1_000_000 else 5
        build = timeit(lambda: pc2.to_msg(cols, fac, 0, 'cam'), repeat)
        msg = pc2.to_msg(cols, fac, 0, 'cam')
        packed = pc2.pack(cols).view(np.uint8)

        def naive() -> None:
            m = PointCloud2()
            m.data = packed  # rclpy's setter iterates element by element
        naive_ms = timeit(naive, 3 if n < 1_000_000 else 1)
        parse = timeit(lambda: pc2.read_xyz(msg, skip_nans=False), repeat)
        rows.append({'message': f'PointCloud2 {n:,} pts ({len(msg.data) / 1e6:.2f} MB)',
                     'build_ms': build, 'naive_build_ms': naive_ms,
                     'speedup': naive_ms / build, 'parse_ms': parse})
    img = np.random.default_rng(0).integers(0, 256, (480, 640, 3)).astype(np.uint8)
    flow = np.random.default_rng(0).normal(size=(480, 640, 2)).astype(np.float32)
    for enc, a in (('rgb8', img), ('32FC2', flow)):
        build = timeit(lambda: img_io.array_to_image(a, enc, fac, 0, 'cam'), 20)
        msg = img_io.array_to_image(a, enc, fac, 0, 'cam')
        from sensor_msgs.msg import Image

        def naive_img() -> None:
            m = Image()
            m.data = a.reshape(-1).view(np.uint8)
        naive_ms = timeit(naive_img, 3)
        parse = timeit(lambda: img_io.image_to_array(msg), 20)
        rows.append({'message': f'Image 640x480 {enc} ({len(msg.data) / 1e6:.2f} MB)',
                     'build_ms': build, 'naive_build_ms': naive_ms,
                     'speedup': naive_ms / build, 'parse_ms': parse})
    return rows


PUBLISHER = r'''
import sys, time
import numpy as np, rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
sys.path.insert(0, sys.argv[2])
from nrsfm_ros.io import pointcloud2 as pc2
from nrsfm_ros.io.msgtypes import RclpyFactory
n = int(sys.argv[1]); count = 60
rclpy.init(); node = Node('bench_pub')
qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
pub = node.create_publisher(PointCloud2, 'bench/cloud', qos)
end = time.monotonic() + 20
while pub.get_subscription_count() < 1 and time.monotonic() < end: time.sleep(0.02)
time.sleep(0.5)
X = np.random.default_rng(0).normal(size=(n, 3)).astype(np.float32)
fac = RclpyFactory()
for i in range(count):
    t = time.time_ns()
    pub.publish(pc2.to_msg({'x': X[:, 0], 'y': X[:, 1], 'z': X[:, 2]}, fac, t, 'cam'))
    time.sleep(1 / 30)
time.sleep(1.0)
node.destroy_node(); rclpy.try_shutdown()
'''


def latency_rows() -> list[dict]:
    import rclpy
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2
    ensure_loopback_env()
    rows = []
    rclpy.init()
    for n in (5_000, 100_000, 1_000_000):
        node = Node('bench_sub')
        lat: list[float] = []

        def cb(msg, lat=lat) -> None:
            now = time.time_ns()
            pc2.read_xyz(msg, skip_nans=False)  # include our parse in the latency
            lat.append((now - (msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)) / 1e6)
        node.create_subscription(PointCloud2, 'bench/cloud', cb,
                                 QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        proc = subprocess.Popen([sys.executable, '-c', PUBLISHER, str(n), str(ROOT)],
                                env=dict(os.environ))
        end = time.monotonic() + 40
        while proc.poll() is None and time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.05)
        proc.wait(10)
        node.destroy_node()
        lat.sort()
        rows.append({'message': f'PointCloud2 {n:,} pts', 'received': f'{len(lat)}/60',
                     'p50_ms': lat[len(lat) // 2] if lat else float('nan'),
                     'p90_ms': lat[int(len(lat) * 0.9)] if lat else float('nan')})
    rclpy.try_shutdown()
    return rows


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--json', default=None)
    args = p.parse_args()
    conv = conversion_rows()
    lat = latency_rows()
    print('| message | build (ms) | naive rclpy build (ms) | speed-up | parse to (N,3) (ms) |')
    print('|---|---|---|---|---|')
    for r in conv:
        print(f"| {r['message']} | {r['build_ms']:.2f} | {r['naive_build_ms']:.1f} | "
              f"{r['speedup']:.0f}x | {r['parse_ms']:.2f} |")
    print()
    print('| node -> node, 30 Hz, reliable | received | p50 latency (ms) | p90 latency (ms) |')
    print('|---|---|---|---|')
    for r in lat:
        print(f"| {r['message']} | {r['received']} | {r['p50_ms']:.1f} | {r['p90_ms']:.1f} |")
    if args.json:
        Path(args.json).write_text(json.dumps({'conversion': conv, 'latency': lat}, indent=2))
    return 0


if __name__ == '__main__':
    sys.exit(main())
