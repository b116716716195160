"""ROS messages -> Foxglove message objects (``foxglove.messages``), for ``nrsfm-ros view``.

Pure functions: a ROS message (rclpy or rosbags: the same attribute names) in, one Foxglove
object out (or ``None`` where there is nothing to show); no server, no channels, no clock.
:data:`ROUTES` is the explicit table of which ROS topic goes to which Foxglove topic through
which converter; ``nrsfm_ros.view`` serves it.  Needs the optional ``foxglove-sdk`` package
(``pip install nrsfm_ros[view]``); nothing else in the package imports this module.

Every converter takes ``stamp_ns``: the timestamp to give the output (bag playback shifts the
recorded stamps to the wall clock), by default the message's own ``header.stamp``.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from foxglove import messages as fm

from . import image as img_io
from . import pointcloud2 as pc2
from .errors import MessageError

WORLD_FRAME = 'world'                     # REP-105 fixed frame of the camera pose
CAMERA_FRAME = 'camera_optical_frame'     # REP-103 optical frame: z forward, x right, y down

MAX_ARROWS = 400                  # scene-flow arrows per SceneUpdate: every k-th point above
FLOW_ARROW_SECONDS = 0.5          # an arrow shows the displacement over this long (v in m/s)
ARROW_SHAFT_DIAMETER_M = 0.004
ARROW_HEAD_FRACTION = 0.3         # of the arrow's length; head diameter 2.5x the shaft's
MIN_ARROW_M = 1e-4                # shorter displacements draw no arrow
ARROW_COLOR = (1.0, 0.3, 0.1, 1.0)
DISPLACEMENT_COLOR = (0.1, 0.6, 1.0, 1.0)

_F32 = fm.PackedElementFieldNumericType.Float32
_U8 = fm.PackedElementFieldNumericType.Uint8
XYZ_STRIDE = 12                   # bytes: x, y, z float32
XYZRGBA_STRIDE = 16               # bytes: x, y, z float32 + red, green, blue, alpha uint8
# Image encodings RawImage shows as they are (32FC2 flow has no Foxglove rendering).
RAW_ENCODINGS = ('rgb8', 'bgr8', 'rgba8', 'bgra8', 'mono8', '8UC1', '8UC3', 'mono16', '16UC1',
                 '32FC1')


def stamp_of(msg: Any) -> int:
    """header.stamp in nanoseconds."""
    st = msg.header.stamp
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


def timestamp(stamp_ns: int) -> fm.Timestamp:
    return fm.Timestamp(int(stamp_ns // 1_000_000_000), int(stamp_ns % 1_000_000_000))


def _stamp(msg: Any, stamp_ns: int | None) -> fm.Timestamp:
    return timestamp(stamp_of(msg) if stamp_ns is None else stamp_ns)


# ------------------------------------------------------------------ point clouds

def cloud_buffer(msg: Any) -> tuple[bytes, int, list[tuple[str, int, Any]]]:
    """PointCloud2 -> (packed little-endian point bytes, stride, [(field, offset, type)]).

    x, y, z float32 of every finite point, plus red, green, blue, alpha uint8 when the cloud
    has a packed ``rgb`` (or ``rgba``) field; points with a non-finite coordinate are dropped.
    """
    xyz = pc2.read_fields(msg, ('x', 'y', 'z'), np.float32)
    keep = np.isfinite(xyz).all(axis=1)
    names = set(pc2.field_names(msg))
    colour = next((n for n in ('rgb', 'rgba') if n in names), None)
    fields: list[tuple[str, int, Any]] = [('x', 0, _F32), ('y', 4, _F32), ('z', 8, _F32)]
    if colour is None:
        out = np.empty(int(keep.sum()), np.dtype([('xyz', '<f4', 3)]))
        out['xyz'] = xyz[keep]
        return out.tobytes(), XYZ_STRIDE, fields
    col = pc2.read_points(msg).reshape(-1)[colour][keep]
    if col.ndim != 1:
        raise MessageError(f'fields[{colour}].count', col.shape[1:], 'expected count 1')
    # the 0x00RRGGBB bits, whether the field is declared float32 (PCL) or uint32
    packed = (col.astype(np.uint32) if col.dtype.kind in 'iu'
              else np.ascontiguousarray(col, dtype=np.float32).view(np.uint32)).view(np.float32)
    out = np.empty(packed.shape[0], np.dtype([('xyz', '<f4', 3), ('rgba', 'u1', 4)]))
    out['xyz'] = xyz[keep]
    out['rgba'][:, :3] = pc2.unpack_rgb(packed)
    out['rgba'][:, 3] = 255
    fields += [('red', 12, _U8), ('green', 13, _U8), ('blue', 14, _U8), ('alpha', 15, _U8)]
    return out.tobytes(), XYZRGBA_STRIDE, fields


def cloud_to_pointcloud(msg: Any, stamp_ns: int | None = None) -> fm.PointCloud:
    """sensor_msgs/PointCloud2 -> foxglove PointCloud (xyz, rgba when the cloud has rgb)."""
    data, stride, fields = cloud_buffer(msg)
    return fm.PointCloud(timestamp=_stamp(msg, stamp_ns), frame_id=str(msg.header.frame_id),
                         pose=_identity_pose(), point_stride=stride,
                         fields=[fm.PackedElementField(name=n, offset=o, type=t)
                                 for n, o, t in fields],
                         data=data)


def _identity_pose() -> fm.Pose:
    return fm.Pose(position=fm.Vector3(x=0.0, y=0.0, z=0.0),
                   orientation=fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))


# ------------------------------------------------------------------ images

def image_buffer(msg: Any) -> tuple[bytes, int, int, str, int]:
    """Image -> (packed little-endian bytes, width, height, encoding, step); the encoding is
    kept (32FC1 stays metres: the layout's image panel maps its value range)."""
    enc = str(msg.encoding)
    if enc not in RAW_ENCODINGS:
        raise MessageError('encoding', enc, f'not shown as an image (shown: '
                           f'{", ".join(RAW_ENCODINGS)})')
    arr = np.ascontiguousarray(img_io.image_to_array(msg))
    arr = arr.astype(arr.dtype.newbyteorder('<'), copy=False)
    h, w = arr.shape[:2]
    return arr.tobytes(), w, h, enc, arr.nbytes // h


def image_to_rawimage(msg: Any, stamp_ns: int | None = None) -> fm.RawImage:
    """sensor_msgs/Image (rgb8, bgr8, mono8, mono16, 32FC1 depth, ...) -> foxglove RawImage."""
    data, w, h, enc, step = image_buffer(msg)
    return fm.RawImage(timestamp=_stamp(msg, stamp_ns), frame_id=str(msg.header.frame_id),
                       width=w, height=h, encoding=enc, step=step, data=data)


def camera_info_to_calibration(msg: Any, stamp_ns: int | None = None
                               ) -> fm.CameraCalibration:
    """sensor_msgs/CameraInfo -> foxglove CameraCalibration (the 3D panel's camera frustum)."""
    return fm.CameraCalibration(timestamp=_stamp(msg, stamp_ns),
                                frame_id=str(msg.header.frame_id), width=int(msg.width),
                                height=int(msg.height),
                                distortion_model=str(msg.distortion_model),
                                D=[float(v) for v in msg.d], K=[float(v) for v in msg.k],
                                R=[float(v) for v in msg.r], P=[float(v) for v in msg.p])


# ------------------------------------------------------------------ arrows

def quaternions_from_x(d: np.ndarray) -> np.ndarray:
    """(N, 4) x, y, z, w unit quaternions turning +x onto the unit directions ``d`` (N, 3)."""
    q = np.empty((d.shape[0], 4))
    q[:, 0] = 0.0
    q[:, 1] = -d[:, 2]                 # axis (1, 0, 0) x d
    q[:, 2] = d[:, 1]
    q[:, 3] = 1.0 + d[:, 0]
    back = q[:, 3] < 1e-9              # d = -x: half a turn about z
    q[back] = (0.0, 0.0, 1.0, 0.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def arrow_sample(n: int, max_arrows: int = MAX_ARROWS) -> np.ndarray:
    """Indices of every k-th of ``n`` points, k the smallest step giving <= max_arrows."""
    step = max(1, -(-n // max_arrows))
    return np.arange(0, n, step)


def cloud_arrows(msg: Any, vector: Sequence[str] = ('vx', 'vy', 'vz'),
                 scale: float = FLOW_ARROW_SECONDS, colour: tuple[float, ...] = ARROW_COLOR,
                 entity_id: str = 'scene_flow', stamp_ns: int | None = None,
                 max_arrows: int = MAX_ARROWS) -> fm.SceneUpdate:
    """A PointCloud2 with x, y, z and a vector (``vector`` fields) -> one SceneEntity of
    arrows from each sampled point along ``scale`` x the vector (at most ``max_arrows``; the
    entity replaces the previous one with its id)."""
    cols = pc2.read_fields(msg, ('x', 'y', 'z', *vector), np.float64)
    cols = cols[np.isfinite(cols).all(axis=1)]
    cols = cols[arrow_sample(cols.shape[0], max_arrows)]
    p, v = cols[:, :3], cols[:, 3:6] * scale
    length = np.linalg.norm(v, axis=1)
    p, v, length = p[length > MIN_ARROW_M], v[length > MIN_ARROW_M], length[length > MIN_ARROW_M]
    q = quaternions_from_x(v / length[:, None]) if length.size else np.zeros((0, 4))
    r, g, b, a = colour
    arrows = [fm.ArrowPrimitive(
        pose=fm.Pose(position=fm.Vector3(x=float(pi[0]), y=float(pi[1]), z=float(pi[2])),
                     orientation=fm.Quaternion(x=float(qi[0]), y=float(qi[1]), z=float(qi[2]),
                                               w=float(qi[3]))),
        shaft_length=float(li * (1 - ARROW_HEAD_FRACTION)),
        shaft_diameter=ARROW_SHAFT_DIAMETER_M, head_length=float(li * ARROW_HEAD_FRACTION),
        head_diameter=2.5 * ARROW_SHAFT_DIAMETER_M, color=fm.Color(r=r, g=g, b=b, a=a))
        for pi, qi, li in zip(p, q, length)]
    entity = fm.SceneEntity(timestamp=_stamp(msg, stamp_ns), frame_id=str(msg.header.frame_id),
                            id=entity_id, arrows=arrows)
    return fm.SceneUpdate(entities=[entity])


def flow_to_arrows(msg: Any, stamp_ns: int | None = None) -> fm.SceneUpdate:
    """scene_flow/points (x, y, z, vx, vy, vz m/s) -> arrows over FLOW_ARROW_SECONDS."""
    return cloud_arrows(msg, ('vx', 'vy', 'vz'), FLOW_ARROW_SECONDS, ARROW_COLOR, 'scene_flow',
                        stamp_ns)


def displacement_to_arrows(msg: Any, stamp_ns: int | None = None) -> fm.SceneUpdate:
    """registration/displacement (x, y, z, dx, dy, dz m) -> arrows of the displacement."""
    return cloud_arrows(msg, ('dx', 'dy', 'dz'), 1.0, DISPLACEMENT_COLOR, 'displacement',
                        stamp_ns)


# ------------------------------------------------------------------ transforms

def transform_to_frame_transform(msg: Any, stamp_ns: int | None = None
                                 ) -> fm.FrameTransform | None:
    """geometry_msgs/TransformStamped (parent header.frame_id -> child_frame_id) ->
    FrameTransform; None for a transform of a frame to itself (it has no place in a tree)."""
    parent, child = str(msg.header.frame_id), str(msg.child_frame_id)
    if not parent or not child or parent == child:
        return None
    t, r = msg.transform.translation, msg.transform.rotation
    return fm.FrameTransform(timestamp=_stamp(msg, stamp_ns), parent_frame_id=parent,
                             child_frame_id=child,
                             translation=fm.Vector3(x=float(t.x), y=float(t.y), z=float(t.z)),
                             rotation=fm.Quaternion(x=float(r.x), y=float(r.y), z=float(r.z),
                                                    w=float(r.w)))


def tf_to_frame_transforms(msg: Any, stamp_ns: int | None = None) -> fm.FrameTransforms:
    """tf2_msgs/TFMessage -> FrameTransforms (self-transforms left out)."""
    out = [transform_to_frame_transform(t, stamp_ns) for t in msg.transforms]
    return fm.FrameTransforms(transforms=[t for t in out if t is not None])


# ------------------------------------------------------------------ the table

Converter = Callable[[Any, 'int | None'], Any]


@dataclass(frozen=True)
class Route:
    """ROS ``topic`` (``msgtype``) -> Foxglove channel ``out_topic`` of ``schema`` via
    ``convert``; a route with ``yields_to`` is off where that ROS topic is present (a bag that
    has it: not advertised; live: nothing more published once a message of it arrived)."""

    topic: str
    msgtype: str
    out_topic: str
    schema: type
    convert: Converter
    yields_to: str = ''


PC2 = 'sensor_msgs/msg/PointCloud2'
IMAGE = 'sensor_msgs/msg/Image'
TRANSFORM = 'geometry_msgs/msg/TransformStamped'

# registration/transform is not routed: its parent and child are both the camera frame.
# The camera pose: ground_truth/camera_pose (world -> camera_optical_frame) where there is one,
# else the estimate registration/camera_pose (world_frame, default nrsfm_reference ->
# camera_optical_frame): both parent the clouds' frame, and a frame has one parent in a tree.
GT_POSE_TOPIC = 'ground_truth/camera_pose'
ROUTES: tuple[Route, ...] = (
    Route('camera/image_raw', IMAGE, '/camera/image_raw', fm.RawImage, image_to_rawimage),
    Route('camera/depth/image_raw', IMAGE, '/camera/depth/image_raw', fm.RawImage,
          image_to_rawimage),
    Route('camera/camera_info', 'sensor_msgs/msg/CameraInfo', '/camera/camera_info',
          fm.CameraCalibration, camera_info_to_calibration),
    Route('nrsfm/depth', IMAGE, '/nrsfm/depth', fm.RawImage, image_to_rawimage),
    Route('nrsfm/points', PC2, '/nrsfm/points', fm.PointCloud, cloud_to_pointcloud),
    Route('registration/reference', PC2, '/registration/reference', fm.PointCloud,
          cloud_to_pointcloud),
    Route('registration/aligned', PC2, '/registration/aligned', fm.PointCloud,
          cloud_to_pointcloud),
    Route('registration/displacement', PC2, '/registration/displacement', fm.SceneUpdate,
          displacement_to_arrows),
    Route('scene_flow/points', PC2, '/scene_flow/points', fm.PointCloud, cloud_to_pointcloud),
    Route('scene_flow/points', PC2, '/scene_flow/arrows', fm.SceneUpdate, flow_to_arrows),
    Route('ground_truth/points', PC2, '/ground_truth/points', fm.PointCloud,
          cloud_to_pointcloud),
    Route(GT_POSE_TOPIC, TRANSFORM, '/ground_truth/camera_pose',
          fm.FrameTransform, transform_to_frame_transform),
    Route('registration/camera_pose', TRANSFORM, '/registration/camera_pose',
          fm.FrameTransform, transform_to_frame_transform, yields_to=GT_POSE_TOPIC),
    # the reconstruction's object frame (nrsfm_object) as a child of the camera's: its axes
    # move with the surface as the reconstructor's cameras see it
    Route('nrsfm/object_pose', TRANSFORM, '/nrsfm/object_pose', fm.FrameTransform,
          transform_to_frame_transform),
    Route('tf', 'tf2_msgs/msg/TFMessage', '/tf', fm.FrameTransforms, tf_to_frame_transforms),
)


def routes_for(topics: dict[str, str]) -> list[Route]:
    """The routes whose ROS topic is in ``topics`` ({name without '/': type}) with that type,
    less those that yield to a topic in ``topics``."""
    return [r for r in ROUTES if topics.get(r.topic) == r.msgtype
            and not (r.yields_to and r.yields_to in topics)]
