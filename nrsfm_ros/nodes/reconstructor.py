"""reconstructor node: nrsfm/tracks (+ camera/camera_info) -> nrsfm/points + nrsfm/depth +
nrsfm/object_pose (its camera of each cloud, where the solve has cameras); mode hdmnet: camera/image_raw (+ /compressed) -> the same outputs, frame by frame."""
from __future__ import annotations

import sys
from typing import Any

from ..processing import ReconstructorProcessor
from .common import RELIABLE, SENSOR, ProcessorNode, queue_depth, spin_node

# ``queue_size: 0``: the reliable tracks input of a mode that solves batches holds this many
# batches of frames, what arrives while a batch is solved (a 300-frame 256x192 stream at 10 Hz
# through the live graph on 2 cores: batch calls of up to 8.3 s, 31 of 300 frames dropped
# with the 64 of any reliable input, none with 4 batches)
BATCH_QUEUE_BATCHES = 4
BATCH_SOLVING_MODES = ('batch', 'dspr', 'spva')


def tracks_queue_depth(queue_size: int, reliable: bool, mode: str, batch_frames: int) -> int:
    """Messages the reconstructor's tracks input holds (``queue_size``; 0: by its QoS, and
    ``BATCH_QUEUE_BATCHES`` batches where ``mode`` solves batches on a reliable input)."""
    depth = queue_depth(queue_size, reliable)
    if queue_size == 0 and reliable and mode in BATCH_SOLVING_MODES:
        depth = max(depth, BATCH_QUEUE_BATCHES * batch_frames)
    return depth


class ReconstructorNode(ProcessorNode):
    idle_flush_kind = 'tracks'   # a stream that stopped before its window (or batch) filled

    def queue_depth(self, kind: str) -> int:
        if kind != 'tracks':
            return super().queue_depth(kind)
        p = self.processor.params
        # batch_seconds at a 30 frames/s camera
        frames = max(p.batch_frames, round(30 * p.batch_seconds))
        return tracks_queue_depth(p.queue_size, self._reliable.get(kind, True), p.mode,
                                  frames)

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('reconstructor', ReconstructorProcessor,
                         [('points', 'sensor_msgs/msg/PointCloud2'),
                          ('nrsfm_depth', 'sensor_msgs/msg/Image'),
                          ('object_pose', 'geometry_msgs/msg/TransformStamped')], **kwargs)
        qos = RELIABLE if self.processor.params.reliable else SENSOR
        self.subscribe('tracks', 'sensor_msgs/msg/PointCloud2', qos)
        self.subscribe('camera_info', 'sensor_msgs/msg/CameraInfo', SENSOR, latest=True)
        # mode hdmnet reconstructs each camera image alone (other modes ignore them uncounted)
        self.subscribe('image', 'sensor_msgs/msg/Image', SENSOR)
        self.subscribe('image_compressed', 'sensor_msgs/msg/CompressedImage', SENSOR)


def main(args: list[str] | None = None) -> int:
    return spin_node(ReconstructorNode, args if args is not None else sys.argv)


if __name__ == '__main__':
    sys.exit(main())
