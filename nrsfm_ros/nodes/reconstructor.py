"""reconstructor node: nrsfm/tracks (+ camera/camera_info) -> nrsfm/points + nrsfm/depth +
nrsfm/object_pose (its camera of each cloud, where the solve has cameras); mode hdmnet: camera/image_raw (+ /compressed) -> the same outputs, frame by frame."""
from __future__ import annotations

import sys

from ..processing import ReconstructorProcessor
from .common import RELIABLE, SENSOR, ProcessorNode, spin_node


class ReconstructorNode(ProcessorNode):
    idle_flush_kind = 'tracks'   # a stream that stopped before its window (or batch) filled

    def __init__(self) -> None:
        super().__init__('reconstructor', ReconstructorProcessor,
                         [('points', 'sensor_msgs/msg/PointCloud2'),
                          ('nrsfm_depth', 'sensor_msgs/msg/Image'),
                          ('object_pose', 'geometry_msgs/msg/TransformStamped')])
        qos = RELIABLE if self.processor.params.reliable else SENSOR
        self.subscribe('tracks', 'sensor_msgs/msg/PointCloud2', qos)
        self.subscribe('camera_info', 'sensor_msgs/msg/CameraInfo', SENSOR)
        # mode hdmnet reconstructs each camera image alone (other modes ignore them uncounted)
        self.subscribe('image', 'sensor_msgs/msg/Image', SENSOR)
        self.subscribe('image_compressed', 'sensor_msgs/msg/CompressedImage', SENSOR)


def main(args: list[str] | None = None) -> int:
    return spin_node(ReconstructorNode, args if args is not None else sys.argv)


if __name__ == '__main__':
    sys.exit(main())
