"""scene_flow node -> scene_flow/points (x, y, z, vx, vy, vz m/s, track_id), scene_flow/markers.

Inputs by ``method``: nrsfm (default): nrsfm/points (+ nrsfm/object_pose, the reconstructor's
cameras, for the ego-motion); msf: camera/image_raw +
camera/depth/image_raw (32FC1 m or 16UC1 mm) + camera/camera_info, paired by stamp."""
from __future__ import annotations

import sys
from typing import Any

from ..processing import SceneFlowProcessor
from .common import RELIABLE, SENSOR, ProcessorNode, spin_node


class SceneFlowNode(ProcessorNode):
    idle_flush_kind = 'points'   # clouds still waiting for their look-ahead (or object pose)

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('scene_flow', SceneFlowProcessor,
                         [('scene_flow', 'sensor_msgs/msg/PointCloud2'),
                          ('markers', 'visualization_msgs/msg/MarkerArray')], **kwargs)
        if self.processor.params.method == 'msf':
            self.subscribe('image', 'sensor_msgs/msg/Image', SENSOR)
            self.subscribe('depth', 'sensor_msgs/msg/Image', SENSOR)
            self.subscribe('camera_info', 'sensor_msgs/msg/CameraInfo', SENSOR, latest=True)
        else:
            self.subscribe('points', 'sensor_msgs/msg/PointCloud2', RELIABLE)
            self.subscribe('object_pose', 'geometry_msgs/msg/TransformStamped', RELIABLE)


def main(args: list[str] | None = None) -> int:
    return spin_node(SceneFlowNode, args if args is not None else sys.argv)


if __name__ == '__main__':
    sys.exit(main())
