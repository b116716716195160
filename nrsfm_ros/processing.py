"""Per-message processing shared by the live nodes and offline ``nrsfm-ros process``.

Each processor takes a message (rclpy or rosbags: both expose the same attributes) and returns
``(topic, msgtype, message)`` outputs built with its :class:`MsgFactory`.  Malformed input raises
:class:`MessageError`; the caller counts, logs once and skips it (see :class:`Stats`).
"""
from __future__ import annotations

import importlib
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from .core.nrsfm.stream import StreamNRSfM, StreamShape
from .core.nrsfm.spva import ShapePrior
from .core.arrays import duplicates
from .core.depth import depth_image
from .core import hdmnet as hdmnet_core
from .core.registration import register
from .core.registration.base import (RegistrationResult, apply, make_result, resolve_threshold,
                                     robust_residual)
from .core.registration.rays import (MIN_INLIER_FRACTION, MIN_MATCHES, invert,
                                     mirror_along_rays, ray_cost, ray_pose, ray_residuals)
from .core.sceneflow import scene_flow
from .core.tracking import MFOFFrame, MFOFTracker, ReferenceFlowTracker
from .core.tracking.reference_flow import MIN_SIDE, black_out, check_trackable, roi_region
from .io import image as img_io
from .io import pointcloud2 as pc2
from .io.errors import MessageError
from .io.msgtypes import MsgFactory, stamp_ns
from .params import (Params, ReconstructorParams, RegistrarParams, SceneFlowParams,
                     TrackerParams)

Output = tuple[str, str, Any]
Handler = Callable[[Any], list[Output]]     # one input kind's message -> outputs

MIN_IMAGE_SIDE = MIN_SIDE     # px: smaller camera images are rejected by the tracker
HDMNET_ENCODINGS = ('rgb8', 'bgr8', 'rgba8', 'bgra8', '8UC3')

PC2 = 'sensor_msgs/msg/PointCloud2'
IMAGE = 'sensor_msgs/msg/Image'
TRANSFORM = 'geometry_msgs/msg/TransformStamped'

TOPICS = {
    'image': 'camera/image_raw', 'image_compressed': 'camera/image_raw/compressed',
    'mask': 'camera/mask',
    'camera_info': 'camera/camera_info', 'depth': 'camera/depth/image_raw',
    'tracks': 'nrsfm/tracks', 'flow': 'nrsfm/flow', 'points': 'nrsfm/points',
    'nrsfm_depth': 'nrsfm/depth', 'object_pose': 'nrsfm/object_pose',
    'reference': 'registration/reference', 'aligned': 'registration/aligned',
    'transform': 'registration/transform', 'displacement': 'registration/displacement',
    'camera_pose': 'registration/camera_pose',
    'scene_flow': 'scene_flow/points', 'markers': 'scene_flow/markers',
    'diagnostics': '/diagnostics',
}


@dataclass
class Timing:
    """Processing time of one input kind's callbacks (those that processed their message).

    ``count``, ``total_s``, ``cpu_s`` and ``max_s`` cover every call; the percentiles cover the
    last ``window`` calls (all of them with ``window=None``, as ``nrsfm-ros process`` reports).
    ``cpu_s``: the process' CPU time (user + system, every thread) spent in the calls, which
    other work on the machine does not inflate as it does the wall time ``total_s``."""

    window: int | None = 1000
    count: int = 0
    total_s: float = 0.0
    cpu_s: float = 0.0
    max_s: float = 0.0
    recent: deque = field(default_factory=deque)

    def add(self, seconds: float, cpu_seconds: float = 0.0) -> None:
        self.count += 1
        self.total_s += seconds
        self.cpu_s += cpu_seconds
        self.max_s = max(self.max_s, seconds)
        self.recent.append(seconds)
        if self.window is not None and len(self.recent) > self.window:
            self.recent.popleft()

    def summary(self) -> dict[str, float]:
        """calls, total_s, cpu_s and mean/p50/p90/max (wall) in milliseconds."""
        if not self.count:
            return {'calls': 0, 'total_s': 0.0, 'cpu_s': 0.0, 'mean_ms': 0.0, 'p50_ms': 0.0,
                    'p90_ms': 0.0, 'max_ms': 0.0}
        # list(): one C-level copy, safe while the worker thread appends (diagnostics timer)
        p50, p90 = np.percentile(list(self.recent), [50, 90])
        return {'calls': self.count, 'total_s': round(self.total_s, 4),
                'cpu_s': round(self.cpu_s, 4),
                'mean_ms': round(1e3 * self.total_s / self.count, 3),
                'p50_ms': round(1e3 * float(p50), 3), 'p90_ms': round(1e3 * float(p90), 3),
                'max_ms': round(1e3 * self.max_s, 3)}


@dataclass
class Stats:
    """Counters reported on /diagnostics."""

    received: int = 0
    processed: int = 0
    published: int = 0
    malformed: int = 0
    failed: int = 0
    dropped: int = 0
    fallbacks: int = 0      # outputs published by a fallback estimate (reconstructor)
    last_error: str = ''
    errors: dict[str, int] = field(default_factory=dict)   # '<input kind>:<field or type>'
    latencies: deque = field(default_factory=lambda: deque(maxlen=100))
    stamps: deque = field(default_factory=lambda: deque(maxlen=100))
    timing: dict[str, Timing] = field(default_factory=dict)     # input kind -> its callbacks
    timing_window: int | None = 1000    # percentiles over the last N calls (None: all)

    def rate_hz(self) -> float:
        if len(self.stamps) < 2:
            return 0.0
        span = self.stamps[-1] - self.stamps[0]
        return (len(self.stamps) - 1) / span if span > 0 else 0.0

    def latency_ms(self) -> float:
        return 1000.0 * float(np.mean(self.latencies)) if self.latencies else 0.0

    def add_time(self, kind: str, seconds: float, cpu_seconds: float = 0.0) -> None:
        """Record one callback's processing time (wall, and the process' CPU time) under input
        ``kind``."""
        if kind not in self.timing:
            self.timing[kind] = Timing(window=self.timing_window)
        self.timing[kind].add(seconds, cpu_seconds)

    def count_error(self, key: str, text: str) -> bool:
        """Count one error of kind ``key``; True the first time that kind is seen."""
        first = key not in self.errors
        self.errors[key] = self.errors.get(key, 0) + 1
        self.last_error = text
        return first


class ProcessingError(MessageError):
    """Any exception other than MessageError raised while processing one input message,
    contained by :meth:`Processor.handle` (``field`` is the input kind, ``value`` the
    exception type)."""


def error_key(kind: str, err: MessageError) -> str:
    """The kind an error is counted under: ``<input>:<field>`` or ``<input>:<exception type>``."""
    return f'{kind}:{err.value}' if isinstance(err, ProcessingError) else f'{kind}:{err.field}'


# The input rule of every cloud a stage reads (pointcloud2.check_cloud): required fields, and
# optional ones checked when present.
CLOUD_INPUTS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    'tracks': (('u', 'v', 'visibility', 'track_id'), ('rgb', 'occlusion')),
    'points': (('x', 'y', 'z'), ('track_id', 'rgb', 'visibility')),
    'reference': (('x', 'y', 'z'), ('track_id',)),
}
# positions beyond this (pixels or metres) are not sensor data: such clouds are rejected
MAX_COORDINATE = 1e6
MAX_POSES = 4096          # scene_flow: object poses kept ahead of their clouds at most
MAX_HELD = 128            # scene_flow: clouds waiting for their object poses at most
ALL_POINTS = 10 ** 9      # a registration point budget no cloud reaches (max_points 0: all)
# visualization_msgs/Marker type and action of the scene-flow arrows
MARKER_LINE_LIST = 5      # Marker.LINE_LIST: each pair of points is one segment
MARKER_ADD = 0            # Marker.ADD


class Processor:
    """Base: holds the factory, the parameter set (``params_cls`` defaults) and the stats."""

    name = 'processor'
    params_cls: type[Params] = Params

    def __init__(self, factory: MsgFactory, params: Params | None = None) -> None:
        self.factory = factory
        self.params: Any = params or self.params_cls()
        self.stats = Stats()

    def set_params(self, params: Params) -> None:
        """Apply a validated parameter set (subclasses rebuild state where it depends on it)."""
        self.params = params

    def recover(self, kind: str, err: Exception) -> None:
        """After an unexpected exception in the handler of ``kind``: put the state back in order
        (subclasses whose state a half-done update could corrupt override this)."""

    def status(self) -> dict[str, str]:
        """Method-specific values for /diagnostics and the process report (none here)."""
        return {}

    def handlers(self) -> dict[str, Handler]:
        """The input kinds this processor takes and the method that handles each."""
        return {}

    def accepts(self, kind: str) -> bool:
        """Whether input ``kind`` is used in the current parameters (others are ignored
        uncounted: e.g. the reconstructor's camera images outside mode hdmnet)."""
        return True

    def handle(self, kind: str, msg: Any) -> list[Output]:
        """Dispatch ``msg`` of input ``kind``; counts, times and records errors.

        Raises only MessageError: a rejected input (counted ``malformed``) or a
        :class:`ProcessingError` wrapping any other exception (counted ``failed``); both are
        counted by kind in ``stats.errors`` and the processor stays usable."""
        handler = self.handlers().get(kind)
        if handler is None:
            raise ValueError(f'{self.name}: no input {kind!r} (inputs: '
                             f'{sorted(self.handlers())})')
        if not self.accepts(kind):
            return []
        self.stats.received += 1
        self.stats.stamps.append(time.monotonic())
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            if kind in CLOUD_INPUTS:
                pc2.check_cloud(msg, *CLOUD_INPUTS[kind], limit=MAX_COORDINATE)
            out = handler(msg)
        except MessageError as err:
            self.stats.malformed += 1
            self.stats.count_error(error_key(kind, err), str(err))
            raise
        except Exception as err:  # contained: one bad message never takes the node down
            self.stats.failed += 1
            wrapped = ProcessingError(kind, type(err).__name__, str(err) or repr(err))
            self.stats.count_error(error_key(kind, wrapped), str(wrapped))
            self.recover(kind, err)
            raise wrapped from err
        seconds = time.perf_counter() - t0
        self.stats.latencies.append(seconds)
        self.stats.add_time(kind, seconds, time.process_time() - c0)
        self.stats.processed += 1
        self.stats.published += len(out)
        return out


class TrackerProcessor(Processor):
    """camera image -> nrsfm/tracks (u, v, track_id, visibility, rgb) + nrsfm/flow; with
    ``roi_mask``, camera/mask (the surface's segmentation) limits what a new reference
    tracks."""

    name = 'tracker'
    params_cls = TrackerParams
    MASKS_KEPT = 16             # camera/mask messages kept to match an image's stamp

    def handlers(self) -> dict[str, Handler]:
        return {'image': self.on_image, 'image_compressed': self.on_image_compressed,
                'mask': self.on_mask}

    def __init__(self, factory: MsgFactory, params: TrackerParams | None = None) -> None:
        super().__init__(factory, params)
        self.tracker = self._make_tracker()
        self._rgb: np.ndarray | None = None
        self.chain_rejected = 0     # observations the chained check reported not visible
        self._masks: dict[int, np.ndarray] = {}     # stamp -> bool (H, W), newest last

    def status(self) -> dict[str, str]:
        """With ``chain_check_px`` > 0 (mfof): the track observations its chained check
        reported not visible so far (``chain_rejected``)."""
        if self.params.method == 'mfof' and self.params.chain_check_px > 0:
            return {'chain_rejected': str(self.chain_rejected)}
        return {}

    def _make_tracker(self) -> ReferenceFlowTracker | MFOFTracker:
        p = self.params
        if p.downsample > 1:        # stride and support_radius count full-image pixels
            p = replace(p, stride=max(1, p.stride // p.downsample),
                        support_radius=-(-p.support_radius // p.downsample))
        if p.method == 'mfof':
            return MFOFTracker(p.mfof_config())
        return ReferenceFlowTracker(preset=p.preset, stride=p.stride, mask=p.mask,
                                    min_std=p.min_std, occlusion_threshold=p.occlusion_threshold)

    def set_params(self, params: TrackerParams) -> None:
        self.params = params
        self.tracker = self._make_tracker()

    def restart(self) -> None:
        """A fresh tracker whose next frame becomes a new reference; MFOF ids continue with the
        next epoch, so no id of the old reference is reused."""
        epoch = getattr(self.tracker, 'epoch', None)
        self.tracker = self._make_tracker()
        if epoch is not None and hasattr(self.tracker, 'epoch'):
            self.tracker.epoch = epoch
        self._rgb = None

    def recover(self, kind: str, err: Exception) -> None:
        self.restart()     # a half-done step or reference change leaves no usable state

    def _check_trackable(self, grey: np.ndarray) -> None:
        """Skip (as malformed) frames too small or without >= 4 trackable pixels: they would
        leave the tracker without a reference or force a re-selection onto them."""
        h, w = grey.shape
        if h < MIN_IMAGE_SIDE or w < MIN_IMAGE_SIDE:
            raise MessageError('height/width', (h, w), f'image smaller than {MIN_IMAGE_SIDE} px'
                               + (f' after downsample {self.params.downsample}'
                                  if self.params.downsample > 1 else ''))
        p = self.params
        try:
            check_trackable(grey, p.mask, max(1, p.stride // p.downsample), p.min_std)
        except ValueError as err:
            raise MessageError('data', 'untrackable frame', f'skipped: {err}') from err

    def accepts(self, kind: str) -> bool:
        return kind != 'mask' or self.params.roi_mask

    def on_mask(self, msg: Any) -> list[Output]:
        """camera/mask (with ``roi_mask``): kept, the newest ``MASKS_KEPT``."""
        if str(msg.encoding) not in ('mono8', '8UC1'):
            raise MessageError('camera/mask encoding', str(msg.encoding),
                               'expected mono8 or 8UC1 (nonzero: the surface)')
        stamp = stamp_ns(msg.header)
        self._masks.pop(stamp, None)
        self._masks[stamp] = img_io.image_to_array(msg) > 0
        while len(self._masks) > self.MASKS_KEPT:
            del self._masks[next(iter(self._masks))]
        return []

    def _frame_mask(self, stamp: int, shape: tuple[int, int]) -> np.ndarray:
        """The surface's mask (H, W) for the image of ``stamp``: its own, else the latest."""
        if not self._masks:
            raise MessageError('camera/mask', 'none received', 'skipped: roi_mask is on and '
                               'no mask has arrived yet')
        m = self._masks.get(stamp)
        if m is None:
            m = self._masks[next(reversed(self._masks))]
        if m.shape != shape:
            raise MessageError('camera/mask height/width', m.shape,
                               f'differs from the image {shape}: skipped')
        return m

    def _roi(self, m: np.ndarray, small: tuple[int, int]) -> np.ndarray:
        """The region a new reference may track: the mask ``m`` eroded by ``roi_margin``, on
        the tracked image (``small``; after ``downsample`` a block whose pixels all are)."""
        region = roi_region(m, self.params.roi_margin)
        n = self.params.downsample
        if n > 1:
            region = shrink(region.astype(np.uint8) * 255, n) == 255
        return region[:small[0], :small[1]]

    def on_image(self, msg: Any) -> list[Output]:
        return self._track(img_io.image_to_array(msg), str(msg.encoding), msg.header)

    def on_image_compressed(self, msg: Any) -> list[Output]:
        arr, enc = img_io.compressed_to_array(msg)
        return self._track(arr, enc, msg.header)

    def _track(self, arr: np.ndarray, encoding: str, header: Any) -> list[Output]:
        full = np.ascontiguousarray(img_io.to_mono8(arr, encoding), np.uint8)
        mask = None
        if self.params.roi_mask:    # what lies behind the surface is blacked out
            mask = self._frame_mask(stamp_ns(header), full.shape)
            full = black_out(full, mask)
        n = self.params.downsample
        grey = shrink(full, n)
        self._check_trackable(grey)
        ref = self.tracker.reference
        if ref is not None and grey.shape != ref.shape:
            self.restart()          # a new image size starts a new reference
        self.tracker.roi = None if mask is None else self._roi(mask, grey.shape)
        tf = self.tracker.step(grey)
        self.chain_rejected += getattr(self.tracker, 'chain_rejected', 0)
        ids = self.tracker.ids
        if n > 1:
            tf = replace(tf, uv=n * tf.uv + 0.5 * (n - 1),
                         flow=enlarge_flow(tf.flow, n, full.shape))
            ids = full_image_ids(ids, grey.shape, full.shape, n)
        if self._rgb is None or self._rgb.size != ids.size or tf.index == 0 \
                or getattr(tf, 'reselected', False):
            # colour of each track where it is in this (reference) frame: carried tracks
            # sit at sub-pixel positions, new ones on the pixel grid
            rgb = img_io.to_rgb8(arr, encoding)
            h, w = full.shape
            x = np.clip(np.rint(tf.uv[:, 0]).astype(np.int64), 0, w - 1)
            y = np.clip(np.rint(tf.uv[:, 1]).astype(np.int64), 0, h - 1)
            self._rgb = pc2.pack_rgb(rgb[y, x])
        stamp, frame = stamp_ns(header), str(header.frame_id)
        fields = {'u': tf.uv[:, 0].astype(np.float32), 'v': tf.uv[:, 1].astype(np.float32),
                  'track_id': ids, 'visibility': tf.visibility.astype(np.float32),
                  'rgb': self._rgb}
        if isinstance(tf, MFOFFrame):
            fields['occlusion'] = tf.occlusion.astype(np.float32)
        tracks = pc2.to_msg(fields, self.factory, stamp, frame)
        out: list[Output] = [(TOPICS['tracks'], PC2, tracks)]
        if self.params.publish_flow:
            out.append((TOPICS['flow'], IMAGE,
                        img_io.array_to_image(np.ascontiguousarray(tf.flow, np.float32),
                                              '32FC2', self.factory, stamp, frame)))
        return out


def shrink(grey: np.ndarray, n: int) -> np.ndarray:
    """``grey`` shrunk by the integer factor ``n`` (the mean of each n x n block; a last
    partial row or column of blocks is dropped)."""
    if n == 1:
        return grey
    import cv2
    h, w = grey.shape[0] // n, grey.shape[1] // n
    return cv2.resize(grey[:h * n, :w * n], (w, h), interpolation=cv2.INTER_AREA)


def enlarge_flow(flow: np.ndarray, n: int, shape: tuple[int, ...]) -> np.ndarray:
    """A flow image (h, w, 2) of the image shrunk by ``n`` -> full-image pixels (H, W, 2): values
    x n, resampled bilinearly at the full image's pixel centres (edge values beyond the last
    whole block)."""
    import cv2
    H, W = shape[:2]
    h, w = flow.shape[:2]
    out = cv2.resize(np.ascontiguousarray(flow, np.float32), (w * n, h * n),
                     interpolation=cv2.INTER_LINEAR) * np.float32(n)
    return np.pad(out, ((0, H - h * n), (0, W - w * n), (0, 0)), mode='edge')


def full_image_ids(ids: np.ndarray, small: tuple[int, int], full: tuple[int, int], n: int
                   ) -> np.ndarray:
    """The tracker's ids on the shrunk image (``epoch * h * w + y * w + x``) renamed as the
    ids of the same epoch on the full image: the first pixel of each n x n block
    (``epoch * H * W + n y * W + n x``), so that one pixel has one id whatever the factor."""
    h, w = small
    H, W = full[:2]
    ids = np.asarray(ids, np.int64)
    epoch, rem = np.divmod(ids, h * w)
    y, x = np.divmod(rem, w)
    return ((epoch * H * W + n * y * W + n * x) % 2 ** 32).astype(np.uint32)


def to_metric(X: np.ndarray, t: np.ndarray, K: np.ndarray | None, mean_depth: float
              ) -> np.ndarray:
    """Shape X (P, 3) in image units (camera frame, centred on the image point ``t``) -> camera
    optical frame in metres by weak-perspective back-projection with the centroid at
    ``mean_depth`` (monocular reconstruction fixes shape up to one global scale: this is the
    stream's gauge); without K the image units stay."""
    if K is None:
        return X + np.array([t[0], t[1], 0.0])
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    x = (X[:, 0] + t[0] - cx) * mean_depth / fx
    y = (X[:, 1] + t[1] - cy) * mean_depth / fy
    z = mean_depth + X[:, 2] * mean_depth / fx
    return np.stack([x, y, z], axis=1)


def project(X: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pinhole projection (P, 2) px of camera-frame points X (P, 3) with intrinsics K."""
    z = np.where(X[:, 2] > 0, X[:, 2], np.nan)
    return np.stack([K[0, 0] * X[:, 0] / z + K[0, 2], K[1, 1] * X[:, 1] / z + K[1, 2]], axis=1)


def make_stream(params: ReconstructorParams, **overrides: Any) -> StreamNRSfM:
    """The reconstructor's streaming NRSfM for a parameter set (``overrides`` win)."""
    kw = dict(mode=params.mode, window=params.window, rank=params.rank,
              iterations=params.iterations, method=params.method,
              batch_frames=params.batch_frames, batch_context=params.batch_context,
              min_seen=params.min_seen,
              projection=params.projection,
              dspr_recurrence_px=params.dspr_recurrence_px, dspr_distinct=params.dspr_distinct,
              dspr_prior_weight=params.dspr_prior_weight,
              spva_prior_frames=params.spva_prior_frames, spva_weighting=params.spva_weighting,
              spva_prior_weight=params.spva_prior_weight,
              spva_smoothness=params.spva_smoothness, spva_refresh=params.spva_refresh,
              spva_iterations=params.spva_iterations)
    return StreamNRSfM(**{**kw, **overrides})


_WARMING = threading.Event()


def warm_in_background() -> None:
    """Import :mod:`.warm` (the numba kernels loaded with the solvers' argument types) in a
    daemon thread, once a process: their loading (~0.3-0.5 s) then runs beside the tracker's
    first frames instead of inside the first batch solve (numba's compiler lock keeps a
    kernel called meanwhile from loading twice)."""
    if _WARMING.is_set() or f'{__package__}.warm' in sys.modules:
        return
    _WARMING.set()
    threading.Thread(target=importlib.import_module, args=(f'{__package__}.warm',),
                     name='nrsfm-warm', daemon=True).start()


class ReconstructorProcessor(Processor):
    """nrsfm/tracks -> nrsfm/points (x, y, z, rgb, track_id, visibility: the tracker's for that
    track and frame, 0 where the frame's tracks lack it) + nrsfm/depth (32FC1 metres, NaN
    off the surface), one of each per tracks message (the first window's frames come out
    together once it is full; ``flush`` publishes whatever is pending at the end of a stream)."""

    name = 'reconstructor'
    params_cls = ReconstructorParams

    def handlers(self) -> dict[str, Handler]:
        return {'camera_info': self.on_camera_info, 'tracks': self.on_tracks,
                'image': self.on_image, 'image_compressed': self.on_image_compressed}

    def __init__(self, factory: MsgFactory, params: ReconstructorParams | None = None) -> None:
        super().__init__(factory, params)
        self.K: np.ndarray | None = None
        self.image_size: tuple[int, int] | None = None
        self._reset()
        warm_in_background()

    def _reset(self) -> None:
        p = self.params
        if p.mode == 'hdmnet':
            self._load_hdmnet()
        self.stream = make_stream(p if p.mode != 'hdmnet' else replace(p, mode='batch'))
        self._rate_stamps: list[int] | None = [] if p.batch_seconds > 0 else None
        self._apply_intrinsics()
        self._pending: dict[int, tuple[int, str, np.ndarray]] = {}   # stamp, frame, uv
        self._vis: dict[int, tuple[np.ndarray, np.ndarray]] = {}      # track ids, visibility
        # each track's first colour: ids sorted, packed rgb floats
        self._rgb = (np.zeros(0, np.int64), np.zeros(0, np.float32))

    def set_params(self, params: ReconstructorParams) -> None:
        self.params = params
        self._reset()

    def recover(self, kind: str, err: Exception) -> None:
        if kind == 'tracks':          # a half-done push: start the stream again
            self._reset()

    def status(self) -> dict[str, str]:
        """Batch solves won by the perspective model, planar ones of them refined under the
        pinhole camera (``pinhole_refinements``), first batches whose depth sign a rigid fit
        to the pinhole image decided (``pinhole_signs``), batch frames published with their
        depths reflected to agree with the perspective image (``reflected_frames``), the
        tracks the last solve left out as seen in too few of its frames (``min_seen``:
        ``tracks_left_out``), batches solved as halves (``batch_splits``: their tracks seen in
        too few of their frames), the last batch solve's method (what ``auto`` chose); dspr:
        compression (frames / stored states) and tracks new since the prior; spva: the frames
        (of the first batch) its shape prior was built from."""
        s = self.stream
        out = {'perspective_solves': str(s.perspective_solves),
               'pinhole_refinements': str(s.pinhole_refinements),
               'pinhole_signs': str(s.pinhole_signs),
               'reflected_frames': str(s.reflected_frames),
               'tracks_left_out': str(s.tracks_left_out),
               'batch_splits': str(s.batch_splits)}
        if s.last_method:
            out['last_method'] = s.last_method
        if self.params.mode == 'dspr':
            out['compression_ratio'] = f'{s.compression_ratio:.2f}'
            out['dspr_new_tracks'] = str(s.dspr_new_tracks)
        if self.params.mode == 'spva':      # the frames the prior was built from, once it is
            out['spva_prior_frames'] = ','.join(str(int(f)) for f in s.prior.frames) \
                if isinstance(s.prior, ShapePrior) else ''
        return out

    def accepts(self, kind: str) -> bool:
        if kind in ('image', 'image_compressed'):
            return self.params.mode == 'hdmnet'
        return kind != 'tracks' or self.params.mode != 'hdmnet'

    def _load_hdmnet(self) -> None:
        """The HDM-Net runtime for ``hdmnet_model`` (kept while the file and threads stay)."""
        from .io.hdmnet_model import HDMNetModel
        p = self.params
        key = (p.hdmnet_model, p.hdmnet_threads)
        if getattr(self, '_hdm_key', None) != key:
            self.hdmnet = HDMNetModel(p.hdmnet_model or None, p.hdmnet_threads)
            self._hdm_key = key

    def on_image(self, msg: Any) -> list[Output]:
        return self._hdmnet(img_io.image_to_array(msg), str(msg.encoding), msg.header)

    def on_image_compressed(self, msg: Any) -> list[Output]:
        arr, enc = img_io.compressed_to_array(msg)
        return self._hdmnet(arr, enc, msg.header)

    def _hdmnet(self, arr: np.ndarray, encoding: str, header: Any) -> list[Output]:
        """mode hdmnet: one image -> one nrsfm/points (the valid grid nodes, track_id = row *
        73 + column, rgb from the image) and one nrsfm/depth."""
        if encoding not in HDMNET_ENCODINGS:
            raise MessageError('encoding', encoding, 'hdmnet needs a colour image (one of '
                               f'{", ".join(HDMNET_ENCODINGS)})')
        rgb = np.ascontiguousarray(img_io.to_rgb8(arr, encoding), np.uint8)
        h, w = rgb.shape[:2]
        if min(h, w) < hdmnet_core.MIN_SIDE:
            raise MessageError('height/width', (h, w),
                               f'hdmnet needs at least {hdmnet_core.MIN_SIDE} px a side')
        K = self.K if self.K is not None and self.image_size in (None, (h, w)) else None
        if K is None and self.params.focal_length_px > 0:
            f = self.params.focal_length_px
            K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
        res = self.hdmnet.predict(rgb, K)
        K = self.hdmnet.last_K
        X, ids = res.cloud()
        if ids.size < 4:
            raise MessageError('data', f'{ids.size} valid nodes', 'hdmnet predicted fewer than '
                               '4 points in front of the camera')
        uv = hdmnet_core.grid_uv(X, K)
        x = np.clip(np.rint(uv[:, 0]), 0, w - 1).astype(np.int64)
        y = np.clip(np.rint(uv[:, 1]), 0, h - 1).astype(np.int64)
        stamp, frame = stamp_ns(header), str(header.frame_id)
        X = X.astype(np.float32)
        cloud = pc2.to_msg({'x': X[:, 0], 'y': X[:, 1], 'z': X[:, 2],
                            'rgb': pc2.pack_rgb(rgb[y, x]), 'track_id': ids}, self.factory,
                           stamp, frame)
        out: list[Output] = [(TOPICS['points'], PC2, cloud)]
        if self.params.publish_depth:
            depth = depth_image(uv, X[:, 2], (h, w))
            out.append((TOPICS['nrsfm_depth'], IMAGE,
                        img_io.array_to_image(depth, '32FC1', self.factory, stamp, frame)))
        return out

    def on_camera_info(self, msg: Any) -> list[Output]:
        self.K = img_io.camera_info_K(msg)
        w, h = int(msg.width), int(msg.height)
        self.image_size = (h, w) if w > 0 and h > 0 else None
        self._apply_intrinsics()
        return []

    def _apply_intrinsics(self) -> None:
        """The perspective refinement needs the true intrinsics (CameraInfo's, never the
        focal_length_px fallback, which has no principal point)."""
        if self.K is not None:
            self.stream.set_intrinsics(float(self.K[0, 0]), self.K[:2, 2])

    def _intrinsics(self) -> np.ndarray | None:
        if self.K is not None:
            return self.K
        if self.params.focal_length_px > 0:
            f = self.params.focal_length_px
            return np.array([[f, 0, 0], [0, f, 0], [0, 0, 1.0]])
        return None

    def on_tracks(self, msg: Any) -> list[Output]:
        cols = pc2.read_fields(msg, ('u', 'v', 'visibility'), np.float64)
        ids = pc2.read_fields(msg, ('track_id',), np.uint32)[:, 0]
        names = pc2.field_names(msg)
        rgb = pc2.read_points(msg).reshape(-1)['rgb'].astype(np.float32) if 'rgb' in names \
            else np.zeros(ids.size, np.float32)
        if ids.size < 4:       # (unique ids: checked with the cloud rule in handle)
            raise MessageError('width', ids.size, 'need at least 4 tracks to reconstruct')
        finite = np.isfinite(cols[:, :2]).all(axis=1)
        if finite.sum() < 4:
            raise MessageError('u/v', 'non-finite', 'fewer than 4 finite track positions')
        vis = np.where(finite, np.clip(np.nan_to_num(cols[:, 2]), 0.0, 1.0), 0.0)
        uv = np.where(finite[:, None], cols[:, :2], np.nanmean(cols[finite, :2], axis=0))
        index = self.stream.frames_seen
        self._measure_rate(stamp_ns(msg.header))
        self._pending[index] = (stamp_ns(msg.header), str(msg.header.frame_id), uv)
        self._vis[index] = (ids.copy(), vis)
        self._keep_colours(ids.astype(np.int64), rgb)
        return self._emit(self.stream.push(ids, uv, vis))

    RATE_FRAMES = 5             # batch_seconds: the frame rate from this many first stamps
    MAX_BATCH_FRAMES = 300

    def _measure_rate(self, stamp: int) -> None:
        """``batch_seconds``: once ``RATE_FRAMES`` stamps are in, the batches resized to that
        span of the stream (``StreamNRSfM.set_batch``); stamps not increasing leave
        ``batch_frames`` as it is."""
        if self._rate_stamps is None:
            return
        self._rate_stamps.append(stamp)
        if len(self._rate_stamps) < self.RATE_FRAMES:
            return
        dt = float(np.median(np.diff(self._rate_stamps))) * 1e-9
        self._rate_stamps = None
        p = self.params
        if not dt > 0:
            return
        n = int(np.clip(round(p.batch_seconds / dt), 3, self.MAX_BATCH_FRAMES))
        if p.mode == 'spva':
            n = max(n, p.spva_prior_frames)
        try:
            self.stream.set_batch(n, int(round(p.batch_context * n / p.batch_frames)))
        except ValueError:
            pass            # a batch shorter than RATE_FRAMES was solved already: kept

    def _emit(self, shapes: list[StreamShape]) -> list[Output]:
        """One nrsfm/points cloud and one nrsfm/depth image per shape."""
        for index, why in self.stream.fallbacks:      # published, but by a fallback: counted
            self.stats.fallbacks += 1
            self.stats.last_error = f'frame {index} published by a fallback: {why}'
        self.stream.fallbacks.clear()
        out: list[Output] = []
        K = self._intrinsics()
        for sh in shapes:
            stamp, frame, uv_all = self._pending.pop(sh.index)
            depth = self.params.mean_depth * (sh.depth_ratio or 1.0)
            X = to_metric(sh.X, sh.t, K, depth).astype(np.float32)
            if sh.R is not None:        # before the cloud: scene_flow pairs it on arrival
                T = np.eye(4)
                T[:3, :3] = sh.R
                T[:3, 3] = to_metric(np.zeros((1, 3)), sh.t, K, depth)[0]
                out.append((TOPICS['object_pose'], TRANSFORM,
                            transform_msg(self.factory, T, stamp, frame,
                                          self.params.object_frame)))
            ids = sh.ids.astype(np.uint32)
            rgb = self._colours(sh.ids)
            cloud = pc2.to_msg({'x': X[:, 0], 'y': X[:, 1], 'z': X[:, 2], 'rgb': rgb,
                                'track_id': ids,
                                'visibility': self._visibility(sh.index, ids)},
                               self.factory, stamp, frame)
            out.append((TOPICS['points'], PC2, cloud))
            if K is not None and self.params.publish_depth:
                size = self.image_size or _size_from(uv_all)
                uv = project(X, K)                      # the published cloud, as imaged
                out.append((TOPICS['nrsfm_depth'], IMAGE,
                            img_io.array_to_image(depth_image(uv, X[:, 2], size), '32FC1',
                                                  self.factory, stamp, frame)))
        return out

    def _keep_colours(self, ids: np.ndarray, rgb: np.ndarray) -> None:
        """A track keeps its first colour: the ids not seen before join the table."""
        known, values = self._rgb
        pos = np.searchsorted(known, ids).clip(max=max(known.size - 1, 0))
        new = ~(known[pos] == ids) if known.size else np.ones(ids.size, bool)
        if new.any():
            all_ids = np.concatenate([known, ids[new]])
            order = np.argsort(all_ids, kind='stable')
            self._rgb = (all_ids[order], np.concatenate([values, rgb[new]])[order])

    def _colours(self, ids: np.ndarray) -> np.ndarray:
        """The packed colours of ``ids`` (0 for a track never seen)."""
        known, values = self._rgb
        out = np.zeros(ids.size, np.float32)
        if known.size:
            ids = np.asarray(ids, np.int64)
            pos = np.searchsorted(known, ids).clip(max=known.size - 1)
            hit = known[pos] == ids
            out[hit] = values[pos[hit]]
        return out

    def _visibility(self, index: int, ids: np.ndarray) -> np.ndarray:
        """The tracker's visibility of ``ids`` in frame ``index`` (0: not in its tracks)."""
        tid, vis = self._vis.pop(index, (np.zeros(0, np.uint32), np.zeros(0)))
        for k in [k for k in self._vis if k < index]:      # frames the stream never published
            del self._vis[k]
        out = np.zeros(ids.size, np.float32)
        if tid.size:
            order = np.argsort(tid, kind='stable')
            k = order[np.searchsorted(tid, ids, sorter=order).clip(max=tid.size - 1)]
            hit = tid[k] == ids
            out[hit] = vis[k[hit]]
        return out

    def expect_frames(self, frames: int) -> None:
        """An offline stream's length in tracks messages (:meth:`StreamNRSfM.expect`: its
        last batch takes the rest instead of a short one alone).  A stream restarted after a
        failed push (``recover``) has no known length."""
        self.stream.expect(frames)

    def flush(self) -> list[Output]:
        """End of an offline stream: a shape for every frame still pending."""
        return self._emit(self.stream.flush())


def _size_from(uv: np.ndarray) -> tuple[int, int]:
    """Image (height, width) covering the track positions (without CameraInfo)."""
    w, h = np.ceil(np.nanmax(uv, axis=0) + 1).astype(int)
    return int(max(h, 1)), int(max(w, 1))


def registration_kwargs(p: RegistrarParams, target_tree: cKDTree | None = None
                        ) -> dict[str, Any]:
    """The keyword arguments of ``core.registration.register`` for the registrar's parameters
    (priors aside): each family gets the parameters it takes, ``max_points`` 0 as
    ``ALL_POINTS`` for CPD and NRGA (which have no 0-means-all), BH-RGA's iterations from
    ``max_iterations``; ``target_tree`` (a cKDTree of the reference) serves ICP."""
    if p.method.startswith(('cpd', 'ecpd')):
        kw: dict[str, Any] = dict(max_iterations=p.max_iterations, tolerance=p.tolerance,
                                  max_points=p.max_points or ALL_POINTS, w=p.w)
        if p.method.endswith('nonrigid'):
            kw.update(beta=p.beta, lam=p.lam)
    elif p.method == 'ga':
        kw = dict(max_iterations=p.max_iterations, max_points=p.max_points)
    elif p.method == 'bhrga':
        kw = dict(iterations=p.max_iterations)
    elif p.method == 'nrga':
        kw = dict(max_points=p.max_points or ALL_POINTS, beta=p.beta)
    else:
        kw = dict(max_iterations=p.max_iterations, tolerance=p.tolerance, trim=p.trim,
                  max_points=p.max_points, target_tree=target_tree, voxel=p.voxel, init=p.init)
    kw['inlier_threshold'] = p.inlier_threshold
    return kw


class RegistrarProcessor(Processor):
    """nrsfm/points + registration/reference -> aligned cloud, transform, displacement."""

    name = 'registrar'
    params_cls = RegistrarParams

    def handlers(self) -> dict[str, Handler]:
        return {'reference': self.on_reference, 'points': self.on_points}

    def status(self) -> dict[str, str]:
        """Clouds posed from their track ids (match track_id; the rest by ``method``), clouds
        published unmoved by the identity guard, the fraction of the last track-id pose's
        matches within inlier_threshold, and the depth reflection in use."""
        return {'posed_by_track_id': str(self.matched_by_id),
                'identity_kept': str(self.identity_kept),
                'match_inliers': f'{self.match_inliers:.3f}',
                'reflected': str(bool(self.last_reflected)).lower()}

    def __init__(self, factory: MsgFactory, params: RegistrarParams | None = None) -> None:
        super().__init__(factory, params)
        self.reference: np.ndarray | None = None
        self.reference_frame = ''
        self.last_reflected = False
        self._checks = 0
        self._last_T: np.ndarray | None = None
        self._mirror_evidence = 0.0      # sum of log(cost unmirrored / mirrored) over checks
        self.reference_ids: np.ndarray | None = None
        # _matches' last (reference ids, cloud ids, cloud indices, matched reference points)
        self._match_key: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self.identity_kept = 0           # clouds where the identity beat the registration
        self.matched_by_id = 0           # clouds posed from their track ids (match track_id)
        self.match_inliers = float('nan')  # the last such pose: its matches within threshold

    def on_reference(self, msg: Any) -> list[Output]:
        xyz = pc2.read_xyz(msg, skip_nans=False)
        ok = np.isfinite(xyz).all(axis=1)
        if ok.sum() < 3:
            raise MessageError('width', int(ok.sum()), 'reference needs at least 3 finite points')
        ids = pc2.read_fields(msg, ('track_id',), np.uint32)[ok, 0] \
            if 'track_id' in pc2.field_names(msg) else None
        ref = xyz[ok]
        tree = cKDTree(ref)
        # everything read and checked: now the state changes, all at once
        self.reference, self.reference_ids, self._tree = ref, ids, tree
        self._thr: tuple[float, float] | None = None    # (parameter, resolved threshold)
        self.reference_frame = str(msg.header.frame_id)
        self._checks, self._last_T, self._mirror_evidence = 0, None, 0.0
        self.last_reflected = False
        return []

    def on_points(self, msg: Any) -> list[Output]:
        if self.reference is None:
            self.stats.dropped += 1
            return []
        src = pc2.read_xyz(msg, skip_nans=False)
        ok = np.isfinite(src).all(axis=1)
        if ok.sum() < 3:
            raise MessageError('data', int(ok.sum()), 'fewer than 3 finite points')
        ids = pc2.read_fields(msg, ('track_id',), np.uint32)[:, 0] \
            if 'track_id' in pc2.field_names(msg) else np.arange(src.shape[0], dtype=np.uint32)
        src, ids = src[ok], ids[ok]
        has_ids = 'track_id' in pc2.field_names(msg)
        posed = self._pose_by_track_id(src, ids) \
            if self.params.match == 'track_id' and has_ids else None
        if posed is None:
            res = self._pose_by_method(src, ids)
            posed = res.T_target_source, res.aligned
        T, aligned_xyz = posed
        self._checks += 1
        self._last_T = T
        stamp = stamp_ns(msg.header)
        frame = self.reference_frame or str(msg.header.frame_id)
        A = aligned_xyz.astype(np.float32)
        D = (aligned_xyz - src).astype(np.float32)
        aligned = pc2.to_msg({'x': A[:, 0], 'y': A[:, 1], 'z': A[:, 2], 'track_id': ids},
                             self.factory, stamp, frame)
        disp = pc2.to_msg({'x': src[:, 0].astype(np.float32), 'y': src[:, 1].astype(np.float32),
                           'z': src[:, 2].astype(np.float32), 'dx': D[:, 0], 'dy': D[:, 1],
                           'dz': D[:, 2]}, self.factory, stamp, str(msg.header.frame_id))
        return [(TOPICS['aligned'], PC2, aligned),
                (TOPICS['transform'], 'geometry_msgs/msg/TransformStamped',
                 transform_msg(self.factory, T, stamp, frame, str(msg.header.frame_id))),
                (TOPICS['displacement'], PC2, disp),
                # the same transform as the camera's pose in the frame tree: source points in
                # this camera's frame -> the reference camera's frame (world_frame)
                (TOPICS['camera_pose'], 'geometry_msgs/msg/TransformStamped',
                 transform_msg(self.factory, T, stamp, self.params.world_frame,
                               str(msg.header.frame_id)))]

    def _threshold(self) -> float:
        """``inlier_threshold`` resolved against the reference (base.resolve_threshold), once
        per reference and parameter value."""
        t = self.params.inlier_threshold
        if self._thr is None or self._thr[0] != t:
            self._thr = (t, resolve_threshold(self.reference, t))
        return self._thr[1]

    def _pose_by_track_id(self, src: np.ndarray, ids: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray] | None:
        """The pose from the track ids the cloud shares with the reference, trusting its
        viewing rays over its depth (``core.registration.rays``), warm-started from the previous
        cloud's pose; None where the cloud cannot be posed that way (fewer than MIN_MATCHES
        shared ids, not a camera-frame cloud: a point at z <= 0, or fewer than
        MIN_INLIER_FRACTION of the matches within inlier_threshold of the pose: ids that do not
        name the same points as the reference's).  Candidates, scored by one
        robust ray cost: the solve (on reflection checks also the solve of the cloud mirrored
        along its rays), the previous pose unchanged, and the identity (``identity_guard``).
        Returns (T_target_source, the whole cloud moved by it); the fraction of the matches
        within inlier_threshold goes to ``match_inliers`` (no nearest-neighbour scoring of the
        whole cloud: nothing reads it, and it was 60-85% of the time at 100k points)."""
        p = self.params
        if self.reference_ids is None or not (src[:, 2] > 0).all():
            return None
        si, target = self._matches(ids)
        if si.size < MIN_MATCHES:
            return None
        thr = self._threshold()
        kw = dict(depth_weight=p.depth_weight, max_iterations=p.max_iterations,
                  tolerance=p.tolerance, max_points=p.max_points, tree=self._tree,
                  score=False)
        # the mirror changes only the depth: nothing to choose with depth_weight 0
        check = p.try_reflection and p.depth_weight > 0 and self._checks % 10 == 0
        sources = {False: src, True: mirror_along_rays(src)} if check or self.last_reflected \
            else {False: src}
        solves = {refl: ray_pose(sources[refl][si], target, thr, init=self._last_T, **kw)
                  for refl in ((False, True) if check else (self.last_reflected,))}
        evidence, refl = self._mirror_evidence, self.last_reflected
        if check:
            # one frame's costs of a deforming surface may favour either reflection: the
            # evidence adds up over the checks (each capped at a factor 4), the sum decides
            ratio = solves[False][1] / max(solves[True][1], 1e-300)
            evidence += float(np.clip(np.log(max(ratio, 1e-300)), -np.log(4), np.log(4)))
            refl = evidence > 0
        res, cost = solves[refl]
        moving = sources[refl]
        matched = moving[si]
        d = matched / np.linalg.norm(matched, axis=1, keepdims=True)
        others = [('previous', self._last_T)] if self._last_T is not None else []
        if p.identity_guard:
            others.append(('identity', np.eye(4)))
        T, method = res.T_target_source, 'rays'
        r = ray_residuals(invert(T), target, matched, d, p.depth_weight)
        for name, T_other in others:
            r_other = ray_residuals(invert(T_other), target, matched, d, p.depth_weight)
            if ray_cost(r_other, thr) < cost:
                T, method, cost, r = T_other, name, ray_cost(r_other, thr), r_other
        inliers = float(np.mean(r <= thr))
        if inliers < MIN_INLIER_FRACTION:
            return None       # the shared ids do not name the same points: nearest neighbours
        self._mirror_evidence, self.last_reflected = evidence, refl
        self.identity_kept += method == 'identity'
        self.matched_by_id += 1
        self.match_inliers = inliers
        return T, apply(T, moving)    # the whole cloud moved (the solve saw the matches)

    def _matches(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(indices into ``ids``, the reference's points they match by id), kept while the
        clouds' ids and the reference stay the same (a batch's clouds share one track set:
        the intersection and the reference's gather were ~1 ms a 30k-point cloud)."""
        key = self._match_key
        if key is not None and key[0] is self.reference_ids and np.array_equal(key[1], ids):
            return key[2], key[3]
        _, si, ri = np.intersect1d(ids, self.reference_ids, return_indices=True)
        target = self.reference[ri]
        self._match_key = (self.reference_ids, ids.copy(), si, target)
        return si, target

    def _pose_by_method(self, src: np.ndarray, ids: np.ndarray) -> RegistrationResult:
        """``method`` on nearest neighbours, with the reflection check and the identity guard
        on the robust residual (``base.robust_residual``)."""
        p = self.params
        kw = registration_kwargs(p, self._tree)
        if p.prior_matches and p.method in ('ecpd-rigid', 'ecpd-nonrigid', 'ga', 'bhrga'):
            kw['priors'] = self._priors(ids, p.prior_matches)
        # The depth reflection of the reconstruction is consistent between windows, so both
        # hypotheses are tried only on the first cloud and every 10th after.
        c = src.mean(axis=0)
        mirrored = src.copy()
        mirrored[:, 2] = 2 * c[2] - mirrored[:, 2]
        t0 = time.perf_counter()
        thr = self._threshold()
        if p.try_reflection and (self._checks % 10 == 0):
            res = register(src, self.reference, method=p.method, **kw)
            alt = register(mirrored, self.reference, method=p.method, **kw)
            cost = robust_residual(res.aligned, self._tree, thr)
            alt_cost = robust_residual(alt.aligned, self._tree, thr)
            self.last_reflected = alt_cost < cost
            res, cost = (alt, alt_cost) if self.last_reflected else (res, cost)
        else:
            # consecutive clouds move little: start from the previous frame's transform
            moving = mirrored if self.last_reflected else src
            if p.method.startswith('icp') and self._last_T is not None:
                kw['init'] = self._last_T
            res = register(moving, self.reference, method=p.method, **kw)
            cost = robust_residual(res.aligned, self._tree, thr)
        # never worse than doing nothing: the unmoved cloud wins when it explains the
        # reference better on the same robust residual
        if p.identity_guard and robust_residual(src, self._tree, thr) < cost:
            res = make_result(src, src.copy(), np.eye(4), self._tree, thr, 'identity', 0, True,
                              t0)
            self.identity_kept += 1
        return res

    def _priors(self, ids: np.ndarray, count: int) -> np.ndarray:
        """(K, 2) (cloud index, reference index) pairs of shared track ids, evenly spread."""
        if self.reference_ids is None:
            raise MessageError('track_id', 'absent', 'prior_matches needs a reference cloud '
                               'with a track_id field')
        _, si, ri = np.intersect1d(ids, self.reference_ids, assume_unique=False,
                                   return_indices=True)
        if si.size == 0:
            raise MessageError('track_id', 0, 'no track_id shared with the reference, so no '
                               'prior matches')
        pick = np.unique(np.linspace(0, si.size - 1, min(count, si.size)).astype(np.intp))
        return np.stack([si[pick], ri[pick]], axis=1)


def transform_msg(factory: MsgFactory, T: np.ndarray, stamp: int, parent: str, child: str
                  ) -> Any:
    from scipy.spatial.transform import Rotation
    q = Rotation.from_matrix(T[:3, :3]).as_quat()  # x, y, z, w
    tr = factory.make('geometry_msgs/msg/Transform',
                      translation=factory.make('geometry_msgs/msg/Vector3', x=float(T[0, 3]),
                                               y=float(T[1, 3]), z=float(T[2, 3])),
                      rotation=factory.make('geometry_msgs/msg/Quaternion', x=float(q[0]),
                                            y=float(q[1]), z=float(q[2]), w=float(q[3])))
    return factory.make('geometry_msgs/msg/TransformStamped',
                        header=factory.header(stamp, parent), child_frame_id=child, transform=tr)


def transform_matrix(msg: Any) -> np.ndarray:
    from scipy.spatial.transform import Rotation
    r, t = msg.transform.rotation, msg.transform.translation
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([r.x, r.y, r.z, r.w]).as_matrix()
    T[:3, 3] = [t.x, t.y, t.z]
    return T


class SceneFlowProcessor(Processor):
    """scene_flow/points (x, y, z, vx, vy, vz in m/s, track_id, visibility) + arrow markers.

    ``method='nrsfm'``: from consecutive nrsfm/points clouds (matched by track id), the
    velocity in the previous camera's axes (core.sceneflow.definition); ``frame='object'``
    removes the camera's ego-motion estimated over the last ``window`` clouds
    (core.sceneflow.nrsfm_flow.object_poses, warm-started from the previous window's weights)
    and, with ``shrinkage='jitter'``, scales each point's flow toward zero by the window's
    measured jitter and by its visibility (core.sceneflow.nrsfm_flow.shrunk). ``visibility``:
    the smaller of the point's ``visibility`` in the two clouds (the tracker's, carried by
    nrsfm/points; 1 where a cloud has no such field), 0 = occluded in either frame (the
    position is the reconstructor's fill-in, its flow a guess); the first cloud's points get 0
    and zero flow.
    ``method='msf'``: RGB-D MSF (core.sceneflow.msf) from camera/image_raw,
    camera/depth/image_raw and camera/camera_info, image and depth paired by stamp; the points
    are the surface pixels of the first frame (every ``stride``-th, track_id = y * width + x)
    at their current positions, the velocity their camera-frame displacement since the previous
    RGB-D frame over its time step (core.sceneflow.definition)."""

    name = 'scene_flow'
    params_cls = SceneFlowParams

    def handlers(self) -> dict[str, Handler]:
        return {'camera_info': self.on_camera_info, 'image': self.on_image,
                'depth': self.on_depth, 'points': self.on_points,
                'object_pose': self.on_object_pose}

    def __init__(self, factory: MsgFactory, params: SceneFlowParams | None = None) -> None:
        super().__init__(factory, params)
        # the window: (stamp ns, frame, X, ids, visibility) of the last clouds, the newest
        # ``_waiting`` of them not yet published (look-ahead)
        self._buf: deque[tuple[int, str, np.ndarray, np.ndarray, np.ndarray]] = deque()
        self._waiting = 0
        self._weights: tuple[np.ndarray, np.ndarray] | None = None
        self._nb: tuple[np.ndarray, np.ndarray] | None = None   # flow ids, neighbour index
        self._last: tuple[float, float] | None = None   # shrinkage factor, jitter of the last
        self._poses: dict[int, np.ndarray] = {}   # nrsfm/object_pose rotations by stamp
        self._held: deque = deque()     # clouds waiting for their object poses, in order
        self.ego_motion = {'poses': 0, 'estimated': 0}   # object-frame flows by ego-motion
        self._reset_msf()

    def status(self) -> dict[str, str]:
        """nrsfm object frame with shrinkage: the last cloud's shrinkage factor and jitter."""
        out = {f'ego_motion_{k}': str(v) for k, v in self.ego_motion.items() if v}
        if self._last is not None:
            out.update(shrinkage=f'{self._last[0]:.3f}', jitter=f'{self._last[1]:.5f}')
        return out

    def _reset_msf(self) -> None:
        self._K: np.ndarray | None = None
        self._msf: Any = None
        self._pending: dict[str, dict[int, tuple[Any, np.ndarray]]] = {'image': {}, 'depth': {}}
        self._msf_prev: tuple[int, np.ndarray] | None = None

    def set_params(self, params: Params) -> None:
        changed = any(getattr(params, k) != getattr(self.params, k)
                      for k in ('method', 'stride', 'segments', 'frame'))
        super().set_params(params)
        if changed:
            self._buf.clear()
            self._waiting = 0
            self._weights = None
            self._nb = None
            self._held.clear()
            self._reset_msf()

    # ---------------------------------------------------------------- msf (RGB-D)
    def on_camera_info(self, msg: Any) -> list[Output]:
        if self.params.method != 'msf':
            return []
        self._K = img_io.camera_info_K(msg)
        return []

    def on_image(self, msg: Any) -> list[Output]:
        if self.params.method != 'msf':
            return []
        arr = img_io.image_to_array(msg)
        grey = img_io.to_mono8(arr, str(msg.encoding)).astype(np.float32)
        return self._pair('image', msg.header, grey)

    def on_depth(self, msg: Any) -> list[Output]:
        if self.params.method != 'msf':
            return []
        enc = str(msg.encoding)
        if enc not in ('32FC1', '16UC1', 'mono16'):
            raise MessageError('encoding', enc, 'depth must be 32FC1 (m) or 16UC1 (mm)')
        from .core.sceneflow.msf import depth_metres
        return self._pair('depth', msg.header, depth_metres(img_io.image_to_array(msg)))

    def _pair(self, kind: str, header: Any, arr: np.ndarray) -> list[Output]:
        stamp = stamp_ns(header)
        other = 'depth' if kind == 'image' else 'image'
        tol = int(self.params.sync_tolerance_s * 1e9)
        match = min(self._pending[other], key=lambda t: abs(t - stamp), default=None)
        if match is None or abs(match - stamp) > tol:
            self._pending[kind][stamp] = (header, arr)
            for k in self._pending:      # keep a few unmatched frames, the newest
                for t in sorted(self._pending[k])[:-4]:
                    del self._pending[k][t]
            return []
        _, other_arr = self._pending[other].pop(match)
        for k in self._pending:          # older unmatched frames will never match now
            self._pending[k] = {t: v for t, v in self._pending[k].items() if t > stamp}
        grey, depth = (arr, other_arr) if kind == 'image' else (other_arr, arr)
        if grey.shape != depth.shape:
            raise MessageError('depth', f'{depth.shape[1]}x{depth.shape[0]}',
                               f'differs from the image size {grey.shape[1]}x{grey.shape[0]}')
        if self._K is None:
            raise MessageError('camera_info', None, 'no CameraInfo received yet (needed for msf)')
        return self._msf_frame(stamp, str(header.frame_id), grey, depth)

    def _msf_frame(self, stamp: int, frame: str, grey: np.ndarray,
                   depth: np.ndarray) -> list[Output]:
        from .core.sceneflow.msf import MSF, MSFConfig
        prev = self._msf_prev
        if self._msf is not None and (grey.shape != self._msf_shape or prev is None
                                      or stamp <= prev[0]):
            self._msf = None             # new size or time went backwards: start over
        if self._msf is None:
            self._msf = MSF(self._K, MSFConfig(segments=self.params.segments))
            self._msf_shape = grey.shape
            self._msf.step(grey, depth)
            X0 = self._msf._X0
            sel = np.zeros(grey.shape, bool)
            sel[::self.params.stride, ::self.params.stride] = True
            self._msf_sel = np.nonzero((sel & np.isfinite(X0).all(-1)).ravel())[0]
            pts = X0.reshape(-1, 3)[self._msf_sel].astype(np.float64)
            v = np.zeros_like(pts)
        else:
            fr = self._msf.step(grey, depth)
            pts = (self._msf._X0 + fr.flow).reshape(-1, 3)[self._msf_sel].astype(np.float64)
            v = (pts - prev[1]) / ((stamp - prev[0]) * 1e-9)
        self._msf_prev = (stamp, pts)
        keep = np.isfinite(pts).all(1) & np.isfinite(v).all(1)
        return self._outputs(pts[keep], v[keep], self._msf_sel[keep].astype(np.uint32), stamp,
                             frame)

    # ---------------------------------------------------------------- nrsfm (clouds)
    def _uses_poses(self) -> bool:
        p = self.params
        return p.method == 'nrsfm' and p.frame == 'object' and p.ego_motion == 'auto'

    def on_object_pose(self, msg: Any) -> list[Output]:
        """nrsfm/object_pose: the reconstructor's camera of the cloud of the same stamp (kept
        for the window; the clouds that arrived first and wait for it are processed now)."""
        if not self._uses_poses():
            return []
        T = transform_matrix(msg)
        if not np.isfinite(T).all():
            raise MessageError('transform', 'non-finite', 'the object pose must be finite')
        stamp = stamp_ns(msg.header)
        self._poses[stamp] = T[:3, :3]
        self._forget_poses()
        return self._release()

    def _release(self, force: int = 0) -> list[Output]:
        """The held clouds, in order, whose pose has come (or a later one: theirs will not),
        and the first ``force`` of them in any case (with the estimate where a pose is
        missing)."""
        out: list[Output] = []
        newest = max(self._poses) if self._poses else None
        while self._held and (force > 0 or (newest is not None and self._held[0][0] <= newest)):
            out += self._cloud_flow(*self._held.popleft())
            force -= 1
        return out

    def _forget_poses(self) -> None:
        """Forget the poses no cloud can still use: those before the oldest cloud of the
        window.  Not a count of the newest: the reconstructor's batch mode publishes 60 poses
        and clouds at once, the cheap pose callbacks run ahead of the clouds', and a count
        evicted the poses of clouds not yet arrived (which then fell back on the estimate:
        the demo's flow 0.61 -> 0.79 in one run of three).  At most ``MAX_POSES`` wait for
        clouds that do not come."""
        if self._buf:
            for old in [s for s in self._poses if s < self._buf[0][0]]:
                del self._poses[old]
        if len(self._poses) > MAX_POSES:
            for old in sorted(self._poses)[:len(self._poses) - MAX_POSES]:
                del self._poses[old]

    def on_points(self, msg: Any) -> list[Output]:
        """A cloud; with ``ego_motion: auto`` while the reconstructor's poses come with its
        clouds (the last cloud had one), a cloud whose pose has not arrived yet (the two
        topics are not ordered over DDS, and the reconstructor's batch mode publishes 60 of
        each at once) waits for it, and the clouds after it wait behind it, until its pose or
        a later one arrives; at most ``MAX_HELD`` wait (the first then goes on with the
        estimate).  Before, the next cloud released a waiting one with the estimate: the live
        demo's flow came out 0.75 instead of 0.61 in a run where 47 of 59 clouds did."""
        if self.params.method != 'nrsfm':
            return []
        cloud = self._read_cloud(msg)
        stamp = cloud[0]
        if self._held or (self._uses_poses() and self._buf and self._buf[-1][0] in self._poses
                          and stamp not in self._poses and stamp > max(self._poses)):
            self._held.append(cloud)
            return self._release(force=len(self._held) - MAX_HELD)
        return self._cloud_flow(*cloud)

    def flush(self) -> list[Output]:
        """End of a stream (or, live, ``idle_flush_s`` without a cloud): the cloud still
        waiting for its pose, with the estimate, and the clouds still waiting for their
        look-ahead, with the clouds there are."""
        out = self._release(force=len(self._held))
        return out + self.flush_waiting()

    def _window_rotations(self, stamps: list[int]) -> np.ndarray | None:
        if not self._uses_poses() or any(t not in self._poses for t in stamps):
            return None
        return np.stack([self._poses[t] for t in stamps])

    def _read_cloud(self, msg: Any) -> tuple[int, str, np.ndarray, np.ndarray, np.ndarray]:
        """(stamp, frame, X, ids, visibility) of a checked nrsfm/points cloud (finite points)."""
        X = pc2.read_xyz(msg, skip_nans=False)
        ids = pc2.read_fields(msg, ('track_id',), np.uint32)[:, 0]
        vis = (np.clip(np.nan_to_num(pc2.read_fields(msg, ('visibility',), np.float64)[:, 0]),
                       0.0, 1.0) if 'visibility' in pc2.field_names(msg) else np.ones(ids.size))
        ok = np.isfinite(X).all(axis=1)
        X, ids, vis = X[ok].astype(np.float64), ids[ok].astype(np.int64), vis[ok]
        dup = duplicates(ids)
        if dup:
            raise MessageError('track_id', f'{dup} duplicated',
                               'track ids of a cloud must be unique')
        return stamp_ns(msg.header), str(msg.header.frame_id), X, ids, vis

    def _cloud_flow(self, stamp: int, frame: str, X: np.ndarray, ids: np.ndarray,
                    vis: np.ndarray) -> list[Output]:
        """A cloud arrives: kept in the window; the flows now due are published (the cloud's
        own at once, or with ``lookahead`` L in the object frame the one of the cloud L
        before it)."""
        cloud = (stamp, frame, X, ids, vis)
        if not self._buf or stamp <= self._buf[-1][0]:
            # first cloud (or time went backwards): zero flow, so every input has an output;
            # clouds still waiting for their look-ahead are published first with what there is
            out = self.flush_waiting()
            self._buf.clear()
            self._buf.append(cloud)
            self._weights = None
            self._nb = None
            return out + self._outputs(X, np.zeros_like(X), ids, stamp, frame,
                                       np.zeros(ids.size))
        self._buf.append(cloud)
        self._waiting += 1
        out: list[Output] = []
        while self._waiting > self._lookahead():
            out += self._due(len(self._buf) - self._waiting)
            self._waiting -= 1
        p = self.params
        keep = max(p.window, 2) if self._lookahead() == 0 else 2 * self._lookahead() + 2
        while len(self._buf) > max(keep, self._waiting + 1):
            self._buf.popleft()
        self._forget_poses()
        return out

    def _lookahead(self) -> int:
        p = self.params
        return p.lookahead if p.frame == 'object' else 0

    def flush_waiting(self) -> list[Output]:
        """The clouds still waiting for their look-ahead, each with the clouds there are."""
        out: list[Output] = []
        while self._waiting > 0:
            out += self._due(len(self._buf) - self._waiting)
            self._waiting -= 1
        return out

    def _due(self, j: int) -> list[Output]:
        """The flow of ``self._buf[j]``, now due.  Where it cannot be computed (e.g. a cloud
        that shares no track with the one before it) the cloud is still published, with zero
        flow and visibility 0, and counted as a fallback with the reason (``/diagnostics``
        ``fallbacks``, ``last_error``): with look-ahead the cloud was accepted on arrival,
        frames earlier, so its failure must not be charged to the message now in hand."""
        try:
            return self._flow_of(j)
        except Exception as err:  # noqa: BLE001 -- contained: the cloud is published anyway
            stamp, frame, X, ids, _ = self._buf[j]
            self.stats.fallbacks += 1
            self.stats.last_error = (f'points stamp {stamp}: published with zero flow: '
                                     f'{type(err).__name__}: {err}')
            return self._outputs(X, np.zeros_like(X), ids, stamp, frame, np.zeros(ids.size))

    def _flow_of(self, j: int) -> list[Output]:
        """The flow of ``self._buf[j]`` from ``self._buf[j - 1]``: causal over the ``window``
        clouds ending at j, or with look-ahead L over the clouds j - 1 - L .. j + L."""
        p = self.params
        stamp, frame, X, ids, vis = self._buf[j]
        pstamp, _, pX, pids, pvis = self._buf[j - 1]
        dt = (stamp - pstamp) * 1e-9
        L = self._lookahead()
        if p.frame == 'camera':
            sf = scene_flow(pX, pids, X, ids, dt, frame='camera')
            out_vis = np.minimum(_lookup(pids, pvis, sf.ids), _lookup(ids, vis, sf.ids))
            return self._outputs(sf.points, sf.velocity, sf.ids, stamp, frame, out_vis)
        from .core.sceneflow.nrsfm_flow import (centred_flow, known_poses, motion_between,
                                                object_poses, pair_flow, shrunk)
        if L == 0:
            lo, hi = max(0, j + 1 - max(p.window, 2)), j + 1
        else:   # as many clouds after the pair as before it: a fit at a window's edge is
            #     noisier than the raw difference (the first pair's flow came out 4x worse)
            m = min(L, j - 1, len(self._buf) - 1 - j)
            lo, hi = j - 1 - m, j + 1 + m
        span = [self._buf[k] for k in range(lo, hi)]
        window = [(c[2], c[3]) for c in span]
        times = [c[0] * 1e-9 for c in span]
        k = j - lo
        rot = self._window_rotations([c[0] for c in span])
        if rot is not None:
            R, t = known_poses(window, rot, assume_checked=True)
            self.ego_motion['poses'] += 1
        else:
            R, t, self._weights = object_poses(
                window, iterations=p.iterations if self._weights is None else
                p.warm_iterations, softness=p.softness, prior=self._weights,
                return_weights=True, max_points=p.pose_points, assume_checked=True)
            self.ego_motion['estimated'] += 1
        gain = None
        if L > 0:
            sf, gain = centred_flow(window, R, t, k, times)
        else:
            sf = pair_flow(window[k - 1], window[k], motion_between(R, t, k - 1, k), dt)
        out_vis = np.minimum(_lookup(pids, pvis, sf.ids), _lookup(ids, vis, sf.ids))
        if p.shrinkage == 'jitter':
            sf = shrunk(sf, window, R, t, dt, times, visibility=out_vis,
                        index=self._neighbours(sf), gain=gain)
            self._last = (sf.shrinkage, sf.jitter)
        return self._outputs(sf.points, sf.velocity, sf.ids, stamp, frame, out_vis)

    def _neighbours(self, sf: Any) -> np.ndarray:
        """The shrinkage's neighbourhoods (nrsfm_flow.neighbour_index), found in the first
        cloud of a track set and kept while the flow's track ids stay the same (a stream's
        track set changes at the tracker's re-selections and the reconstructor's batches):
        neighbours on the surface stay neighbours while it deforms, and the k-d query of every
        point was 70% of this node's time at 30k points."""
        from .core.sceneflow.nrsfm_flow import neighbour_index
        if self._nb is None or not np.array_equal(self._nb[0], sf.ids):
            self._nb = (sf.ids, neighbour_index(sf.points))
        return self._nb[1]

    def _outputs(self, pts: np.ndarray, v: np.ndarray, ids: np.ndarray, stamp: int,
                 frame: str, visibility: np.ndarray | None = None) -> list[Output]:
        pts32, v32 = pts.astype(np.float32), v.astype(np.float32)
        vis = np.ones(len(ids), np.float32) if visibility is None else visibility
        cloud = pc2.to_msg({'x': pts32[:, 0], 'y': pts32[:, 1], 'z': pts32[:, 2],
                            'vx': v32[:, 0], 'vy': v32[:, 1], 'vz': v32[:, 2],
                            'track_id': ids.astype(np.uint32),
                            'visibility': np.asarray(vis, np.float32)},
                           self.factory, stamp, frame)
        return [(TOPICS['scene_flow'], PC2, cloud),
                (TOPICS['markers'], 'visualization_msgs/msg/MarkerArray',
                 self._markers(pts, v, stamp, frame))]

    def _markers(self, pts: np.ndarray, v: np.ndarray, stamp: int, frame: str) -> Any:
        f = self.factory
        sel = slice(None, None, self.params.marker_stride)
        a, b = pts[sel], pts[sel] + v[sel] * self.params.marker_scale
        seg = np.empty((2 * a.shape[0], 3))
        seg[0::2], seg[1::2] = a, b
        points = f.points(seg)
        marker = f.make('visualization_msgs/msg/Marker', header=f.header(stamp, frame),
                        ns='scene_flow', id=0, type=MARKER_LINE_LIST, action=MARKER_ADD,
                        pose=f.make('geometry_msgs/msg/Pose',
                                    orientation=f.make('geometry_msgs/msg/Quaternion', w=1.0)),
                        scale=f.make('geometry_msgs/msg/Vector3', x=0.003),
                        color=f.make('std_msgs/msg/ColorRGBA', r=1.0, g=0.3, b=0.1, a=1.0),
                        points=points)
        return f.make('visualization_msgs/msg/MarkerArray', markers=[marker])


def _lookup(ids: np.ndarray, values: np.ndarray, query: np.ndarray) -> np.ndarray:
    """values[k] where ids[k] == q for each q of ``query`` (every q is one of ``ids``)."""
    order = np.argsort(ids, kind='stable')
    return values[order[np.searchsorted(ids, query, sorter=order)]]


def diagnostics_msg(factory: MsgFactory, node: str, stats: Stats, stamp: int,
                    extra: dict[str, str] | None = None) -> Any:
    """DiagnosticArray with one status: rate, latency, received/processed/dropped/malformed,
    and per input kind the processing time of its callbacks: ``<kind>_ms_p50`` and ``_p90``
    over the last ``stats.timing_window`` calls, ``_mean``, ``_max`` and ``<kind>_calls`` over
    all of them."""
    values = {'rate_hz': f'{stats.rate_hz():.2f}', 'latency_ms': f'{stats.latency_ms():.2f}',
              'received': str(stats.received), 'processed': str(stats.processed),
              'published': str(stats.published), 'dropped': str(stats.dropped),
              'malformed': str(stats.malformed), 'failed': str(stats.failed),
              'fallbacks': str(stats.fallbacks),
              'errors': ', '.join(f'{k}={n}' for k, n in sorted(stats.errors.items())),
              'last_error': stats.last_error}
    for kind, timing in sorted(stats.timing.items()):
        t = timing.summary()
        values[f'{kind}_calls'] = str(t['calls'])
        for k in ('mean', 'p50', 'p90', 'max'):
            values[f'{kind}_ms_{k}'] = f"{t[k + '_ms']:.2f}"
    values.update(extra or {})
    level = 0 if not (stats.malformed or stats.dropped or stats.failed) else 1
    status = factory.make('diagnostic_msgs/msg/DiagnosticStatus',
                          level=bytes([level]) if factory.backend == 'rclpy' else level,
                          name=f'nrsfm_ros: {node}',
                          message='ok' if level == 0 else 'malformed, failed or dropped input',
                          hardware_id=node,
                          values=[factory.make('diagnostic_msgs/msg/KeyValue', key=k, value=v)
                                  for k, v in values.items()])
    return factory.make('diagnostic_msgs/msg/DiagnosticArray',
                        header=factory.header(stamp, ''), status=[status])
