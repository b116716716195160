"""reconstructor node: nrsfm/tracks (+ camera/camera_info) -> nrsfm/points."""
from __future__ import annotations

import sys

from ..processing import ReconstructorProcessor
from .common import RELIABLE, SENSOR, ProcessorNode, spin_node


class ReconstructorNode(ProcessorNode):
    def __init__(self) -> None:
        super().__init__('reconstructor', ReconstructorProcessor,
                         [('points', 'sensor_msgs/msg/PointCloud2')])
        qos = RELIABLE if self.processor.params.reliable else SENSOR
        self.subscribe('tracks', 'sensor_msgs/msg/PointCloud2', qos)
        self.subscribe('camera_info', 'sensor_msgs/msg/CameraInfo', SENSOR)


def main(args: list[str] | None = None) -> int:
    return spin_node(ReconstructorNode, args if args is not None else sys.argv)


if __name__ == '__main__':
    sys.exit(main())
