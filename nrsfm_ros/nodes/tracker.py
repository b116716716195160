"""tracker node: camera/image_raw (+ /compressed) -> nrsfm/tracks, nrsfm/flow; with
``roi_mask``, camera/mask limits the tracked surface."""
from __future__ import annotations

import sys

from ..processing import TrackerProcessor
from .common import RELIABLE, SENSOR, ProcessorNode, spin_node


class TrackerNode(ProcessorNode):
    def __init__(self) -> None:
        super().__init__('tracker', TrackerProcessor,
                         [('tracks', 'sensor_msgs/msg/PointCloud2'),
                          ('flow', 'sensor_msgs/msg/Image')])
        qos = RELIABLE if self.processor.params.reliable else SENSOR
        self.subscribe('image', 'sensor_msgs/msg/Image', qos)
        self.subscribe('image_compressed', 'sensor_msgs/msg/CompressedImage', qos)
        self.subscribe('mask', 'sensor_msgs/msg/Image', qos)     # used with roi_mask


def main(args: list[str] | None = None) -> int:
    return spin_node(TrackerNode, args if args is not None else sys.argv)


if __name__ == '__main__':
    sys.exit(main())
