"""registrar node: nrsfm/points + registration/reference (transient local) ->
registration/aligned, registration/transform, registration/displacement,
registration/camera_pose (world_frame -> the clouds' camera optical frame)."""
from __future__ import annotations

import sys

from ..processing import RegistrarProcessor
from .common import LATCHED, RELIABLE, ProcessorNode, spin_node


class RegistrarNode(ProcessorNode):
    def __init__(self) -> None:
        super().__init__('registrar', RegistrarProcessor,
                         [('aligned', 'sensor_msgs/msg/PointCloud2'),
                          ('transform', 'geometry_msgs/msg/TransformStamped'),
                          ('displacement', 'sensor_msgs/msg/PointCloud2'),
                          ('camera_pose', 'geometry_msgs/msg/TransformStamped')])
        self.subscribe('reference', 'sensor_msgs/msg/PointCloud2', LATCHED)
        self.subscribe('points', 'sensor_msgs/msg/PointCloud2', RELIABLE)


def main(args: list[str] | None = None) -> int:
    return spin_node(RegistrarNode, args if args is not None else sys.argv)


if __name__ == '__main__':
    sys.exit(main())
