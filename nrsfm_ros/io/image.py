"""sensor_msgs/Image, CompressedImage and CameraInfo <-> NumPy (what cv_bridge would do).

Supported encodings: rgb8, bgr8, rgba8, bgra8, mono8, mono16, 16UC1, 32FC1, 32FC2.  Row ``step``
padding and ``is_bigendian`` are honoured on read; writes are packed little-endian.
"""
from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from .errors import MessageError
from .msgtypes import MsgFactory

MAX_IMAGE_SIDE = 16384     # px: larger images (and CameraInfo sizes) are rejected

# encoding -> (numpy base type, channels)
ENCODINGS: dict[str, tuple[str, int]] = {
    'rgb8': ('u1', 3), 'bgr8': ('u1', 3), 'rgba8': ('u1', 4), 'bgra8': ('u1', 4),
    'mono8': ('u1', 1), '8UC1': ('u1', 1), '8UC3': ('u1', 3),
    'mono16': ('u2', 1), '16UC1': ('u2', 1),
    '32FC1': ('f4', 1), '32FC2': ('f4', 2),
}


def image_to_array(msg: Any) -> np.ndarray:
    """(H, W) or (H, W, C) array in native byte order; a view of ``msg.data`` where possible."""
    enc = str(msg.encoding)
    if enc not in ENCODINGS:
        raise MessageError('encoding', enc, f'unsupported (supported: {", ".join(ENCODINGS)})')
    base, channels = ENCODINGS[enc]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    dtype = np.dtype(('>' if msg.is_bigendian else '<') + base)
    row_bytes = width * channels * dtype.itemsize
    if height <= 0 or width <= 0:
        raise MessageError('height' if height <= 0 else 'width', min(height, width),
                           'image must be non-empty')
    if height > MAX_IMAGE_SIDE or width > MAX_IMAGE_SIDE:
        raise MessageError('height/width', (height, width),
                           f'larger than {MAX_IMAGE_SIDE} px a side')
    if step < row_bytes:
        raise MessageError('step', step, f'smaller than width*channels*size = {row_bytes}')
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    if buf.size < step * height:
        raise MessageError('data', f'{buf.size} bytes', f'expected step*height = {step * height}')
    rows = buf[:step * height].reshape(height, step)[:, :row_bytes]
    if step != row_bytes or dtype.itemsize > 1 and rows.ctypes.data % dtype.itemsize:
        rows = np.ascontiguousarray(rows)
    img = rows.view(dtype).reshape((height, width, channels) if channels > 1 else (height, width))
    if dtype.byteorder == '>':
        img = img.astype(dtype.newbyteorder('='))
    return img


def array_to_image(img: np.ndarray, encoding: str, factory: MsgFactory, stamp_ns: int,
                   frame_id: str) -> Any:
    """Build an Image; checks the array's dtype and channels against ``encoding``."""
    if encoding not in ENCODINGS:
        raise ValueError(f'encoding={encoding!r}: unsupported (supported: {", ".join(ENCODINGS)})')
    base, channels = ENCODINGS[encoding]
    img = np.asarray(img)
    got_channels = 1 if img.ndim == 2 else img.shape[2] if img.ndim == 3 else -1
    if got_channels != channels or img.dtype.str[1:] != base:
        raise ValueError(f'img: {encoding} needs dtype {base} with {channels} channel(s), got '
                         f'{img.dtype} with shape {img.shape}')
    img = np.ascontiguousarray(img, dtype=np.dtype('<' + base))
    h, w = img.shape[:2]
    return factory.make('sensor_msgs/msg/Image', header=factory.header(stamp_ns, frame_id),
                        height=h, width=w, encoding=encoding, is_bigendian=0,
                        step=w * channels * img.dtype.itemsize,
                        data=img.reshape(-1).view(np.uint8))


def to_mono8(img: np.ndarray, encoding: str) -> np.ndarray:
    """Grey uint8 image from any colour/mono encoding (what the tracker consumes)."""
    if encoding in ('mono8', '8UC1'):
        return img
    if encoding in ('rgb8', '8UC3'):
        return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    if encoding == 'bgr8':
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if encoding == 'rgba8':
        return cv2.cvtColor(img, cv2.COLOR_RGBA2GRAY)
    if encoding == 'bgra8':
        return cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
    if encoding in ('mono16', '16UC1'):
        return (img >> 8).astype(np.uint8)
    raise MessageError('encoding', encoding, 'not an intensity image')


def to_rgb8(img: np.ndarray, encoding: str) -> np.ndarray:
    if encoding in ('rgb8', '8UC3'):
        return img
    if encoding == 'bgr8':
        return img[..., ::-1]
    if encoding in ('rgba8', 'bgra8'):
        return img[..., :3] if encoding == 'rgba8' else img[..., 2::-1]
    grey = to_mono8(img, encoding)
    return np.repeat(grey[..., None], 3, axis=2)


def compressed_to_array(msg: Any) -> tuple[np.ndarray, str]:
    """Decode a CompressedImage -> (array, encoding of the array: 'bgr8' or 'mono8')."""
    fmt = str(msg.format).lower()
    if not any(k in fmt for k in ('jpeg', 'jpg', 'png')):
        raise MessageError('format', msg.format, 'expected a jpeg or png CompressedImage')
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    try:
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
    except cv2.error as err:
        raise MessageError('data', f'{buf.size} bytes', f'could not decode as {fmt}: {err}') \
            from err
    if img is None:
        raise MessageError('data', f'{buf.size} bytes', f'could not decode as {fmt}')
    if img.ndim == 2:
        return img, 'mono8' if img.dtype == np.uint8 else '16UC1'
    if img.dtype != np.uint8:       # 16-bit colour PNG: keep the high byte
        img = (img >> 8).astype(np.uint8) if img.dtype == np.uint16 else None
        if img is None:
            raise MessageError('data', fmt, 'decoded to an unsupported pixel type')
    if img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return img, 'bgr8'


def array_to_compressed(img: np.ndarray, encoding: str, factory: MsgFactory, stamp_ns: int,
                        frame_id: str, fmt: str = 'png', quality: int = 95) -> Any:
    """Encode rgb8/bgr8/mono8 (png also 16UC1) into a CompressedImage."""
    if fmt not in ('png', 'jpeg'):
        raise ValueError(f'fmt={fmt!r}: expected png or jpeg')
    if encoding == 'rgb8':
        img, encoding = img[..., ::-1], 'bgr8'
    params = [cv2.IMWRITE_JPEG_QUALITY, quality] if fmt == 'jpeg' else []
    ok, data = cv2.imencode('.png' if fmt == 'png' else '.jpg', np.ascontiguousarray(img), params)
    if not ok:
        raise ValueError(f'img: OpenCV could not encode {encoding} as {fmt}')
    return factory.make('sensor_msgs/msg/CompressedImage',
                        header=factory.header(stamp_ns, frame_id),
                        format=f'{encoding}; {fmt} compressed {encoding}', data=data.reshape(-1))


def camera_info_K(msg: Any) -> np.ndarray:
    """3x3 intrinsics from a CameraInfo: every entry finite, fx, fy > 0, and (when the image size
    is set) the principal point inside the image; raises MessageError naming the field."""
    k = np.asarray(msg.k, dtype=np.float64).reshape(-1)
    if k.size != 9:
        raise MessageError('k', k.size, 'expected 9 intrinsic entries')
    if not np.isfinite(k).all():
        raise MessageError('k', k.tolist(), 'intrinsics must be finite')
    if k[0] <= 0 or k[4] <= 0:
        raise MessageError('k', [k[0], k[4]], 'focal lengths fx, fy must be > 0')
    w, h = int(msg.width), int(msg.height)
    if not (0 <= w <= MAX_IMAGE_SIDE and 0 <= h <= MAX_IMAGE_SIDE):
        raise MessageError('width/height', (w, h), f'image size must be in 0..{MAX_IMAGE_SIDE}')
    if w > 0 and h > 0 and not (0 <= k[2] <= w and 0 <= k[5] <= h):
        raise MessageError('k', [k[2], k[5]], f'principal point (cx, cy) outside the {w}x{h} '
                           'image')
    return k.reshape(3, 3)


def make_camera_info(K: np.ndarray, width: int, height: int, factory: MsgFactory,
                     stamp_ns: int, frame_id: str) -> Any:
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    P = np.zeros((3, 4))
    P[:, :3] = K
    roi = factory.make('sensor_msgs/msg/RegionOfInterest', x_offset=0, y_offset=0, height=0,
                       width=0, do_rectify=False)
    return factory.make('sensor_msgs/msg/CameraInfo', header=factory.header(stamp_ns, frame_id),
                        height=height, width=width, distortion_model='plumb_bob',
                        d=np.zeros(5), k=K.reshape(-1), r=np.eye(3).reshape(-1),
                        p=P.reshape(-1), binning_x=0, binning_y=0, roi=roi)
