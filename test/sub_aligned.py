"""Helper process for test_multihost: subscribes to registration/aligned, prints 'ready' once a
publisher is matched (discovery across the namespaces done), then writes the xyz of the first N
clouds it receives to an .npz and exits (1 when fewer came within the timeout)."""
from __future__ import annotations

import sys
import time

import numpy as np
import rclpy
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2

from nrsfm_ros.io import pointcloud2 as pc2


def main() -> int:
    out, n, timeout = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
    rclpy.init()
    node = Node('sub_aligned')
    got: list[np.ndarray] = []
    sub = node.create_subscription(
        PointCloud2, 'registration/aligned',
        lambda m: got.append(pc2.read_xyz(m, skip_nans=False)),
        QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                   reliability=ReliabilityPolicy.RELIABLE))
    end = time.monotonic() + timeout
    ready = False
    while time.monotonic() < end and len(got) < n:
        rclpy.spin_once(node, timeout_sec=0.05)
        if not ready and sub.get_publisher_count() >= 1:
            print('ready', flush=True)
            ready = True
    np.savez(out, *got)
    print(f'received {len(got)}', flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0 if len(got) >= n else 1


if __name__ == '__main__':
    sys.exit(main())
