"""``nrsfm-ros view``: a Foxglove WebSocket server (``foxglove-sdk``) over a bag or the live
topics.

:class:`Viewer` owns the server and one channel per route of
:data:`nrsfm_ros.io.foxglove_view.ROUTES` (the converters live there); :func:`play_bag` plays a
bag into it with the recorded timing, :func:`bridge_live` feeds it from rclpy subscriptions.
Open ``ws://HOST:PORT`` in Foxglove (Open connection -> Foxglove WebSocket) with
``config/foxglove_layout.json`` (:func:`layout`).

The camera pose is a FrameTransform to ``camera_optical_frame``: from ``ground_truth/camera_pose``
(``world`` ->) where the bag or the live graph has it, else from the registrar's estimate
``registration/camera_pose`` (``nrsfm_reference`` ->, its ``world_frame``).  Both parent the
clouds' frame and a frame has one parent, so the estimate yields (``Route.yields_to``): a bag with
the ground truth does not advertise ``/registration/camera_pose``; live, it is published until
the first ground-truth pose arrives, then counted in ``yielded``.

Bag playback waits for a client's first subscription (then :data:`SUBSCRIBE_SETTLE_S` for the
rest of its subscriptions), so nothing is played to nobody; the recorded times are shifted to
the wall clock at each start, so ``--loop`` runs forward in time and Foxglove treats the data
as live.
"""
from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import foxglove
from foxglove import channels as fch
from foxglove import messages as fm
from foxglove.websocket import ServerListener

from .io.bag import bag_info, deserialize, read_messages
from .io.errors import MessageError
from .io.foxglove_view import CAMERA_FRAME, ROUTES, Route, routes_for

SERVER_NAME = 'nrsfm_ros'
LAYOUT_FILE = 'foxglove_layout.json'
DEFAULT_PORT = 8765
SUBSCRIBE_SETTLE_S = 0.25     # after a client's first subscription, time for its others
POLL_S = 0.1                  # stop-flag polling while waiting or spinning
RELEASE_TIMEOUT_S = 2.0       # close(): longest wait for the server to let go of its port
LIVE_QUEUE = 5                # live subscriptions: keep last N
DEPTH_RANGE_M = (0.0, 8.0)    # the layout's depth panels map this range to black..white
# the layout's grid: horizontal in the optical frame (y down), 1 m below the camera, 4 m ahead
GRID_POSE: dict[str, Any] = {'position': (0.0, 1.0, 4.0), 'rotation': (90.0, 0.0, 0.0)}

CHANNEL_CLASSES: dict[type, type] = {
    fm.PointCloud: fch.PointCloudChannel, fm.RawImage: fch.RawImageChannel,
    fm.SceneUpdate: fch.SceneUpdateChannel, fm.FrameTransform: fch.FrameTransformChannel,
    fm.FrameTransforms: fch.FrameTransformsChannel,
    fm.CameraCalibration: fch.CameraCalibrationChannel,
}


class _Listener(ServerListener):
    """Sets ``subscribed`` on a client's first subscription."""

    def __init__(self) -> None:
        self.subscribed = threading.Event()

    def on_subscribe(self, client: Any, channel: Any) -> None:
        self.subscribed.set()


class Viewer:
    """The Foxglove server (its own context, so several can run in one process) and its
    channels.  ``with Viewer(port=0) as v: v.advertise(routes); v.publish(topic, msg)``;
    leaving the block closes the channels and stops the server (the port is free again)."""

    def __init__(self, host: str = '127.0.0.1', port: int = DEFAULT_PORT) -> None:
        if not 0 <= port <= 65535:
            raise ValueError(f'port={port}: expected 0..65535 (0: any free port)')
        self.context = foxglove.Context()
        self.listener = _Listener()
        try:
            self.server = foxglove.start_server(name=SERVER_NAME, host=host, port=port,
                                                context=self.context,
                                                server_listener=self.listener)
        except RuntimeError as err:       # the SDK's error, e.g. the port is taken
            raise OSError(f'cannot serve on {host}:{port}: {err}') from err
        self.host, self.port = host, int(self.server.port)
        self._routes: dict[str, list[Route]] = {}
        self._channels: dict[str, Any] = {}
        self.counts: dict[str, int] = {}          # Foxglove topic -> messages logged
        self.errors: dict[str, int] = {}          # ROS topic -> messages not shown
        self.last_error: dict[str, str] = {}      # ROS topic -> why (the latest)
        self.yielded: dict[str, int] = {}         # Foxglove topic -> messages not shown
        self._seen: set[str] = set()              # ROS topics a message was published of
        self.started = threading.Event()          # playback began (see play_bag)
        self.started_at = 0.0                     # time.monotonic() of that
        self._closed = False

    @property
    def url(self) -> str:
        return f'ws://{self.host}:{self.port}'

    def advertise(self, routes: Iterable[Route]) -> None:
        """One channel per route (advertised to clients at once)."""
        for r in routes:
            if r.out_topic not in self._channels:
                self._channels[r.out_topic] = CHANNEL_CLASSES[r.schema](r.out_topic,
                                                                       context=self.context)
            self._routes.setdefault(r.topic, [])
            if r not in self._routes[r.topic]:
                self._routes[r.topic].append(r)

    @property
    def topics(self) -> list[str]:
        """The Foxglove topics advertised."""
        return list(self._channels)

    def publish(self, topic: str, msg: Any, stamp_ns: int | None = None,
                log_time_ns: int | None = None) -> int:
        """Convert a ROS message of ``topic`` by its routes and log it; returns how many
        Foxglove messages went out.  A message a converter rejects is counted in ``errors``;
        one of a route that yields to a topic already seen, in ``yielded``."""
        n = 0
        topic = topic.lstrip('/')
        self._seen.add(topic)
        for r in self._routes.get(topic, ()):
            if r.yields_to and r.yields_to in self._seen:
                self.yielded[r.out_topic] = self.yielded.get(r.out_topic, 0) + 1
                continue
            try:
                out = r.convert(msg, stamp_ns)
            except (MessageError, ValueError, AttributeError, TypeError) as err:
                self._error(r.topic, f'{r.out_topic}: {err}')
                continue
            if out is None:
                continue
            self._channels[r.out_topic].log(out, log_time=log_time_ns)
            self.counts[r.out_topic] = self.counts.get(r.out_topic, 0) + 1
            n += 1
        return n

    def _error(self, topic: str, reason: str) -> None:
        self.errors[topic] = self.errors.get(topic, 0) + 1
        self.last_error[topic] = reason

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for ch in self._channels.values():
            ch.close()
        self.server.stop()
        _wait_released(self.host, self.port)

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _wait_released(host: str, port: int, timeout: float = RELEASE_TIMEOUT_S) -> bool:
    """Wait until nothing listens on host:port (the server stops asynchronously, in ms)."""
    addr = '127.0.0.1' if host in ('', '0.0.0.0') else '::1' if host == '::' else host
    end = time.monotonic() + timeout
    while True:
        with socket.socket(socket.AF_INET6 if ':' in addr else socket.AF_INET) as s:
            s.settimeout(POLL_S)
            if s.connect_ex((addr, port)) != 0:
                return True
        if time.monotonic() > end:
            return False
        time.sleep(0.01)


def _wait_for_client(viewer: Viewer, stop: threading.Event) -> bool:
    while not stop.is_set():
        if viewer.listener.subscribed.wait(POLL_S):
            stop.wait(SUBSCRIBE_SETTLE_S)
            return not stop.is_set()
    return False


def bag_routes(bag: str | Path) -> list[Route]:
    """The routes of the topics ``bag`` has; ValueError when it has none of them."""
    have = {t: v['type'] for t, v in bag_info(bag)['topics'].items()}
    routes = routes_for(have)
    if not routes:
        shown = sorted({r.topic for r in ROUTES})
        raise ValueError(f'{bag}: none of the topics view shows ({", ".join(shown)}); it has '
                         f'{", ".join(sorted(have)) or "no topics"}')
    return routes


def play_bag(viewer: Viewer, bag: str | Path, rate: float = 1.0, loop: bool = False,
             stop: threading.Event | None = None, wait_client: bool = True,
             damage: list[str] | None = None,
             on_pass: Callable[[int], None] | None = None) -> dict[str, int]:
    """Advertise the bag's routes, wait for a client (``wait_client``), then publish its
    messages with the recorded timing scaled by ``rate`` (again and again with ``loop``)
    until done or ``stop`` is set.  Sets ``viewer.started`` when the first pass begins;
    ``on_pass(n)`` after each pass.  Returns the ROS messages read per topic (all passes)."""
    if not rate > 0:
        raise ValueError(f'rate={rate}: expected > 0')
    stop = stop or threading.Event()
    routes = bag_routes(bag)
    viewer.advertise(routes)
    msgs = list(read_messages(bag, sorted({r.topic for r in routes}),
                              damage=[] if damage is None else damage))
    counts: dict[str, int] = {}
    if wait_client and not _wait_for_client(viewer, stop):
        return counts
    passes = 0
    while msgs and not stop.is_set():
        t_wall0 = time.monotonic()
        offset = time.time_ns() - msgs[0].stamp_ns      # bag time -> wall clock
        if not viewer.started.is_set():
            viewer.started_at = t_wall0
            viewer.started.set()
        for m in msgs:
            delay = t_wall0 + (m.stamp_ns - msgs[0].stamp_ns) * 1e-9 / rate - time.monotonic()
            if delay > 0 and stop.wait(delay):
                return counts
            if stop.is_set():
                return counts
            counts[m.topic] = counts.get(m.topic, 0) + 1
            try:
                msg = deserialize(m.raw, m.msgtype)
            except MessageError as err:
                viewer._error(m.topic, str(err))
                continue
            stamp = m.stamp_ns + offset
            viewer.publish(m.topic, msg, stamp_ns=stamp, log_time_ns=stamp)
        passes += 1
        if on_pass is not None:
            on_pass(passes)
        if not loop:
            break
    return counts


def _live_qos(topic: str) -> Any:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    from .io.bag import LATCHED_TOPICS
    if topic in LATCHED_TOPICS:       # the reference cloud: get the latched sample
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                          reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
    # best effort matches both best-effort (camera) and reliable (output) publishers
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=LIVE_QUEUE,
                      reliability=ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.VOLATILE)


def bridge_live(viewer: Viewer, node: Any, routes: Sequence[Route] = ROUTES
                ) -> tuple[list[Any], list[str]]:
    """One rclpy subscription per routed ROS topic on ``node``, each feeding ``viewer`` (the
    messages keep their own stamps).  Returns (subscriptions, topics skipped because their
    message package is not installed).  The caller spins the node."""
    from .io.msgtypes import rclpy_class
    viewer.advertise(routes)
    subs, skipped = [], []
    for topic in dict.fromkeys(r.topic for r in routes):
        msgtype = next(r.msgtype for r in routes if r.topic == topic)
        try:
            cls = rclpy_class(msgtype)
        except (ImportError, AttributeError):
            skipped.append(f'{topic} ({msgtype} not installed)')
            continue
        subs.append(node.create_subscription(
            cls, topic, lambda msg, t=topic: viewer.publish(t, msg), _live_qos(topic)))
    return subs, skipped


def spin(node: Any, stop: threading.Event) -> None:
    """Spin ``node`` (default context) until ``stop`` is set or rclpy shuts down."""
    import rclpy
    while not stop.is_set() and rclpy.ok():
        rclpy.spin_once(node, timeout_sec=POLL_S)


def serve(bag: str | Path | None = None, host: str = '127.0.0.1', port: int = DEFAULT_PORT,
          rate: float = 1.0, loop: bool = False, stop: threading.Event | None = None,
          out: Callable[[str], None] = print) -> Viewer:
    """The ``nrsfm-ros view`` session: serve ``bag`` (or, without one, the live topics)
    until ``stop`` is set or Ctrl-C; progress and a per-topic summary go to ``out``.  A bag
    stays served after its last message (Foxglove keeps showing it).  Returns the (closed)
    viewer."""
    stop = stop or threading.Event()
    if bag is not None:
        bag_routes(bag)                   # a bad bag fails before the server starts
    with Viewer(host, port) as viewer:
        out(f'serving {viewer.url} (Foxglove: Open connection -> Foxglove WebSocket; layout '
            f'{layout_path()}); Ctrl-C to stop')
        try:
            if bag is None:
                _serve_live(viewer, stop, out)
            else:
                damage: list[str] = []
                out('playback starts when a client subscribes')
                counts = play_bag(viewer, bag, rate=rate, loop=loop, stop=stop, damage=damage,
                                  on_pass=lambda n: out(f'pass {n} done'))
                for line in damage:
                    out(f'note: {line}')
                if not stop.is_set():
                    out(f'played {sum(counts.values())} messages; still serving')
                    while not stop.wait(3600):
                        pass
        except KeyboardInterrupt:
            pass
        finally:
            stop.set()
            for topic, n in viewer.counts.items():
                out(f'  {topic}: {n} messages')
            for topic, n in viewer.yielded.items():
                out(f'  {topic}: {n} not shown (the ground-truth pose is served)')
            for topic, n in viewer.errors.items():
                out(f'  {topic}: {n} not shown ({viewer.last_error[topic]})')
    return viewer


def _serve_live(viewer: Viewer, stop: threading.Event, out: Callable[[str], None]) -> None:
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node

    from .live import ensure_loopback_env
    ensure_loopback_env()
    rclpy.init()
    node = Node('nrsfm_view')
    try:
        _, skipped = bridge_live(viewer, node)
        for line in skipped:
            out(f'note: not bridged: {line}')
        spin(node, stop)
    except ExternalShutdownException:     # Ctrl-C: rclpy's handler shut the context down
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


# ------------------------------------------------------------------ layout

def layout() -> str:
    """The shipped Foxglove layout (config/foxglove_layout.json) as JSON: a 3D panel with the
    clouds, the arrows and the camera frame; image panels for the camera and the depths."""
    import foxglove.layouts as fl
    lo, hi = DEPTH_RANGE_M
    clouds: dict[str, Any] = {
        '/nrsfm/points': fl.BaseRendererPointCloudTopicSettings(
            visible=True, point_size=4, color_mode='rgba-fields'),
        '/ground_truth/points': fl.BaseRendererPointCloudTopicSettings(
            visible=False, point_size=2, color_mode='flat', flat_color='#30c030'),
        '/registration/reference': fl.BaseRendererPointCloudTopicSettings(
            visible=False, point_size=2, color_mode='flat', flat_color='#a0a0a0'),
        '/registration/aligned': fl.BaseRendererPointCloudTopicSettings(
            visible=True, point_size=2, color_mode='flat', flat_color='#2080ff'),
        '/scene_flow/points': fl.BaseRendererPointCloudTopicSettings(
            visible=False, point_size=2, color_mode='colormap', color_field='z',
            color_map='turbo'),
        '/scene_flow/arrows': fl.BaseRendererSceneUpdateTopicSettings(visible=True),
        '/registration/displacement': fl.BaseRendererSceneUpdateTopicSettings(visible=False),
    }
    three_d = fl.ThreeDeePanel(title='clouds and scene flow', config=fl.ThreeDeeConfig(
        follow_tf=CAMERA_FRAME, topics=clouds,
        layers={'grid': fl.BaseRendererGridLayerSettings(
            visible=True, frame_id=CAMERA_FRAME, size=4, divisions=8, **GRID_POSE)}))

    def image(title: str, topic: str, depth: bool) -> Any:
        mode = fl.ImageModeConfig(image_topic=topic, calibration_topic='/camera/camera_info')
        if depth:
            mode = fl.ImageModeConfig(image_topic=topic, min_value=lo, max_value=hi)
        return fl.ImagePanel(title=title, config=fl.ImageConfig(image_mode=mode))

    images = fl.SplitContainer(direction='column', items=[
        fl.SplitItem(content=image('camera', '/camera/image_raw', False)),
        fl.SplitItem(content=image('depth (input, m)', '/camera/depth/image_raw', True)),
        fl.SplitItem(content=image('depth (nrsfm, m)', '/nrsfm/depth', True)),
    ])
    doc = fl.Layout(content=fl.SplitContainer(direction='row', items=[
        fl.SplitItem(proportion=2, content=three_d), fl.SplitItem(proportion=1, content=images)]))
    return doc.to_json()


def layout_path() -> Path:
    """config/foxglove_layout.json of the source tree, else of the installed share/."""
    import sys

    from .live import package_root
    candidates = [package_root() / 'config' / LAYOUT_FILE,
                  Path(sys.prefix) / 'share' / 'nrsfm_ros' / 'config' / LAYOUT_FILE]
    return next((c for c in candidates if c.exists()), candidates[0])
