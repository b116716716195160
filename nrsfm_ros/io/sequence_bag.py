"""Write a synthetic sequence (io.synth) as an MCAP bag, ground truth on its own topics."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from . import image as img_io
from . import pointcloud2 as pc2
from .bag import BagWriter
from .msgtypes import RosbagsFactory
from .synth import SynthSequence

FRAME_ID = 'camera_optical_frame'
GT_TOPICS = {'points': 'ground_truth/points', 'tracks': 'ground_truth/tracks',
             'pose': 'ground_truth/camera_pose'}


def write_sequence_bag(seq: SynthSequence, path: str | Path, storage: str = 'mcap') -> dict:
    """Topics: camera/image_raw (rgb8), camera/camera_info, camera/depth/image_raw (32FC1, m),
    camera/mask (mono8, 255 where the surface is seen; renders with a background only),
    registration/reference (frame 0 ground truth, once), ground_truth/points (x, y, z,
    track_id), ground_truth/tracks (u, v, track_id, visibility), ground_truth/camera_pose
    (TransformStamped world -> camera).  Returns the message counts."""
    from ..processing import transform_msg
    fac = RosbagsFactory()
    F = seq.images.shape[0]
    H, W = seq.images.shape[1:3]
    ids = seq.track_ids
    with BagWriter(path, storage) as w:
        s0 = int(seq.stamps_ns[0])
        X0 = seq.S[0].astype(np.float32)
        w.write('registration/reference', 'sensor_msgs/msg/PointCloud2',
                pc2.to_msg({'x': X0[:, 0], 'y': X0[:, 1], 'z': X0[:, 2], 'track_id': ids}, fac,
                           s0, FRAME_ID), s0)
        for f in range(F):
            st = int(seq.stamps_ns[f])
            w.write('camera/camera_info', 'sensor_msgs/msg/CameraInfo',
                    img_io.make_camera_info(seq.K, W, H, fac, st, FRAME_ID), st)
            if seq.config.background:       # a perfect segmenter's mask of the surface
                seen = np.isfinite(seq.surface_st[f][..., 0]) if seq.surface_st is not None \
                    else np.isfinite(seq.depth[f])
                w.write('camera/mask', 'sensor_msgs/msg/Image',
                        img_io.array_to_image(np.where(seen, 255, 0).astype(np.uint8), 'mono8',
                                              fac, st, FRAME_ID), st)
            w.write('camera/image_raw', 'sensor_msgs/msg/Image',
                    img_io.array_to_image(seq.images[f], 'rgb8', fac, st, FRAME_ID), st)
            w.write('camera/depth/image_raw', 'sensor_msgs/msg/Image',
                    img_io.array_to_image(seq.depth[f], '32FC1', fac, st, FRAME_ID), st)
            X = seq.S[f].astype(np.float32)
            w.write(GT_TOPICS['points'], 'sensor_msgs/msg/PointCloud2',
                    pc2.to_msg({'x': X[:, 0], 'y': X[:, 1], 'z': X[:, 2], 'track_id': ids}, fac,
                               st, FRAME_ID), st)
            w.write(GT_TOPICS['tracks'], 'sensor_msgs/msg/PointCloud2',
                    pc2.to_msg({'u': seq.W[2 * f].astype(np.float32),
                                'v': seq.W[2 * f + 1].astype(np.float32), 'track_id': ids,
                                'visibility': seq.V[f].astype(np.float32)}, fac, st, FRAME_ID),
                    st)
            T_world_camera = np.linalg.inv(seq.T_camera_world[f])
            w.write(GT_TOPICS['pose'], 'geometry_msgs/msg/TransformStamped',
                    transform_msg(fac, T_world_camera, st, 'world', FRAME_ID), st)
        return dict(w.counts)
