"""scene_flow node: nrsfm/points -> scene_flow/points (vx, vy, vz m/s), scene_flow/markers."""
from __future__ import annotations

import sys

from ..processing import SceneFlowProcessor
from .common import RELIABLE, ProcessorNode, spin_node


class SceneFlowNode(ProcessorNode):
    def __init__(self) -> None:
        super().__init__('scene_flow', SceneFlowProcessor,
                         [('scene_flow', 'sensor_msgs/msg/PointCloud2'),
                          ('markers', 'visualization_msgs/msg/MarkerArray')])
        self.subscribe('points', 'sensor_msgs/msg/PointCloud2', RELIABLE)


def main(args: list[str] | None = None) -> int:
    return spin_node(SceneFlowNode, args if args is not None else sys.argv)


if __name__ == '__main__':
    sys.exit(main())
