"""reconstructor node: nrsfm/tracks (+ camera/camera_info) -> nrsfm/points + nrsfm/depth +
nrsfm/object_pose (its camera of each cloud, where the solve has cameras); mode hdmnet: camera/image_raw (+ /compressed) -> the same outputs, frame by frame."""
from __future__ import annotations

import sys
import time

from ..processing import ReconstructorProcessor
from .common import RELIABLE, SENSOR, ProcessorNode, spin_node


class ReconstructorNode(ProcessorNode):
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
        self._last_tracks = time.monotonic()

    def _on_message(self, kind: str, msg: object) -> None:
        if kind == 'tracks':
            self._last_tracks = time.monotonic()
        super()._on_message(kind, msg)

    def on_idle(self) -> None:
        """A stream that stopped before its window (or batch) filled still gets its clouds."""
        idle = self.processor.params.idle_flush_s
        if idle > 0 and time.monotonic() - self._last_tracks >= idle:
            assert isinstance(self.processor, ReconstructorProcessor)
            try:
                with self.lock:
                    outputs = self.processor.flush()
            except Exception as err:  # noqa: BLE001 -- contained like every message
                self._failed('flush', err)
                return
            self.publish_outputs(outputs)


def main(args: list[str] | None = None) -> int:
    return spin_node(ReconstructorNode, args if args is not None else sys.argv)


if __name__ == '__main__':
    sys.exit(main())
