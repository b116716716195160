"""Helper process for test_nodes: publishes one 100k-point cloud built by our conversion."""
from __future__ import annotations

import sys
import time

import numpy as np
import rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2

from nrsfm_ros.io import pointcloud2 as pc2
from nrsfm_ros.io.msgtypes import RclpyFactory


def cloud() -> PointCloud2:
    rng = np.random.default_rng(42)
    X = rng.normal(size=(100_000, 3)).astype(np.float32)
    return pc2.to_msg({'x': X[:, 0], 'y': X[:, 1], 'z': X[:, 2],
                       'track_id': np.arange(100_000, dtype=np.uint32)},
                      RclpyFactory(), 42, 'cam')


def main() -> int:
    rclpy.init()
    node = Node('pub_cloud')
    pub = node.create_publisher(PointCloud2, 'test/cloud',
                                QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    end = time.monotonic() + 20
    while pub.get_subscription_count() < 1 and time.monotonic() < end:
        time.sleep(0.05)
    time.sleep(0.3)
    msg = cloud()
    for _ in range(3):
        pub.publish(msg)
        time.sleep(0.2)
    time.sleep(1.0)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
