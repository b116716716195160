"""Live tools over real rclpy (there is no ros2 CLI here): loopback DDS environment, graph
launch as separate processes, bag record and replay of raw CDR bytes, topic inspection."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from .io.bag import LATCHED_TOPICS, BagWriter, read_messages
from .nodes import LAUNCHED_ENV

NODES = ('tracker', 'reconstructor', 'registrar', 'scene_flow')


def package_root() -> Path:
    return Path(__file__).resolve().parent.parent


def default_profile() -> Path:
    """The loopback Fast DDS profile: installed share/ copy or the source tree's config/."""
    candidates = [package_root() / 'config' / 'fastdds_loopback.xml',
                  Path(sys.prefix) / 'share' / 'nrsfm_ros' / 'config' / 'fastdds_loopback.xml']
    try:
        from ament_index_python.packages import get_package_share_directory
        candidates.append(Path(get_package_share_directory('nrsfm_ros')) / 'config'
                          / 'fastdds_loopback.xml')
    except Exception:  # not installed through colcon
        pass
    for c in candidates:
        if c.exists():
            return c
    raise FileNotFoundError('fastdds_loopback.xml not found in config/ or the package share')


DDS_ENV = 'NRSFM_DDS'
DDS_MODES = ('loopback', 'network')


def ensure_loopback_env(env: dict[str, str] | None = None) -> dict[str, str]:
    """Set the loopback-only DDS variables where missing (in ``env`` or os.environ).

    ``NRSFM_DDS=network`` (the graph across hosts) leaves discovery to the environment
    instead: ROS_AUTOMATIC_DISCOVERY_RANGE (default SUBNET), ROS_STATIC_PEERS,
    FASTRTPS_DEFAULT_PROFILES_FILE (none: Fast DDS's defaults) and ROS_DOMAIN_ID (none: 0)
    are used as given, the same on every host."""
    target = os.environ if env is None else env
    mode = target.get(DDS_ENV, 'loopback')
    if mode not in DDS_MODES:
        raise ValueError(f'{DDS_ENV}={mode!r}: expected one of {", ".join(DDS_MODES)}')
    if mode == 'network':
        if target.get('ROS_AUTOMATIC_DISCOVERY_RANGE', 'SUBNET') == 'LOCALHOST':
            raise ValueError(f'{DDS_ENV}=network with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST: '
                             'set SUBNET (or unset it) to reach other hosts')
        target.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'SUBNET')
        target.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
        return dict(target)
    target.setdefault('FASTRTPS_DEFAULT_PROFILES_FILE', str(default_profile()))
    target['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    target.setdefault('ROS_DOMAIN_ID', str(10 + os.getpid() % 90))
    target.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    return dict(target)


# ------------------------------------------------------------------ graph launch

class Graph:
    """The node graph as child processes; Ctrl-C is forwarded.  Under :meth:`wait` a node
    that dies is restarted with exponential backoff (the launcher says so) and the graph gives
    up, non-zero, only after ``max_restarts`` restarts of one node in a row."""

    def __init__(self, nodes: Sequence[str] = NODES, params_dir: Path | None = None,
                 overrides: dict[str, dict[str, Any]] | None = None, quiet: bool = False
                 ) -> None:
        env = ensure_loopback_env(dict(os.environ))
        env[LAUNCHED_ENV] = '1'       # nodes/__init__.py: Ctrl-C at startup exits 0
        self._env = env
        self._quiet = quiet
        params_dir = params_dir or package_root() / 'config'
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.started: dict[str, float] = {}
        self.restarts: dict[str, int] = {}
        self._cmds: dict[str, list[str]] = {}
        for name in nodes:
            if name not in NODES:
                raise ValueError(f'node {name!r}: expected one of {NODES}')
            cmd = [sys.executable, '-m', f'nrsfm_ros.nodes.{name}', '--ros-args']
            yaml_path = params_dir / f'{name}.yaml'
            if yaml_path.exists():
                cmd += ['--params-file', str(yaml_path)]
            for k, v in (overrides or {}).get(name, {}).items():
                val = str(v).lower() if isinstance(v, bool) else str(v)
                cmd += ['-p', f'{k}:={val}']
            self._cmds[name] = cmd
            self.restarts[name] = 0
            self._spawn(name)

    def _spawn(self, name: str) -> None:
        out = subprocess.DEVNULL if self._quiet else None
        self.procs[name] = subprocess.Popen(self._cmds[name], env=self._env, stdout=out,
                                            stderr=None)
        self.started[name] = time.monotonic()

    def poll(self) -> dict[str, int]:
        """Nodes that have exited, with their return codes."""
        return {n: p.returncode for n, p in self.procs.items() if p.poll() is not None}

    def stop(self, timeout: float = 5.0) -> dict[str, int]:
        """Ctrl-C to every node; one still running after ``timeout`` is asked for its
        threads' stacks (SIGUSR1: nodes/__init__.py) and killed, and the launcher says so."""
        for p in self.procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        end = time.monotonic() + timeout
        for name, p in self.procs.items():
            try:
                p.wait(max(0.1, end - time.monotonic()))
            except subprocess.TimeoutExpired:
                sys.stderr.write(f'graph: node {name} (pid {p.pid}) did not stop within '
                                 f'{timeout:g} s of Ctrl-C; its stacks follow, then kill\n')
                sys.stderr.flush()
                try:
                    p.send_signal(signal.SIGUSR1)
                    p.wait(1.0)
                except subprocess.TimeoutExpired:
                    pass
                p.kill()
                p.wait()
        return {n: p.returncode for n, p in self.procs.items()}

    def wait(self, max_restarts: int = 10, backoff_s: float = 0.25, max_backoff_s: float = 8.0,
             stable_s: float = 30.0) -> int:
        """Block until Ctrl-C (exit 0 when the nodes stop cleanly) or a node dies more than
        ``max_restarts`` times in a row (exit 1).  A dead node is restarted after
        ``backoff_s`` doubling per consecutive restart up to ``max_backoff_s``; a node that ran
        ``stable_s`` before dying starts the count again."""
        due: dict[str, float] = {}
        try:
            while True:
                now = time.monotonic()
                for n, code in self.poll().items():
                    if n in due:
                        continue
                    if now - self.started[n] >= stable_s:
                        self.restarts[n] = 0
                    if self.restarts[n] >= max_restarts:
                        self.stop()
                        tail = f' after {self.restarts[n]} restart(s)' if max_restarts else ''
                        sys.stderr.write(f'error: node {n} exited with code {code}; giving up'
                                         f'{tail}\n')
                        return 1
                    delay = min(backoff_s * 2 ** self.restarts[n], max_backoff_s)
                    self.restarts[n] += 1
                    due[n] = now + delay
                    sys.stderr.write(f'graph: node {n} exited with code {code}; restarting in '
                                     f'{delay:.2f} s (restart {self.restarts[n]} of '
                                     f'{max_restarts})\n')
                for n in [n for n, t in due.items() if now >= t]:
                    del due[n]
                    self._spawn(n)
                    sys.stderr.write(f'graph: node {n} restarted (pid {self.procs[n].pid})\n')
                time.sleep(0.1)
        except KeyboardInterrupt:
            codes = self.stop(timeout=10.0)     # a node still starting on a loaded machine
            return 1 if stop_problems(codes, set(due)) else 0


def stop_problems(codes: dict[str, int], restarting: set[str] = frozenset()) -> dict[str, int]:
    """The nodes whose exit codes after Ctrl-C are not a clean stop, each reported on stderr.
    A clean stop: 0, death by SIGINT (130 from a shell), or -SIGALRM: the node's work was
    over and its own shutdown alarm cut a hung DDS teardown short (nodes/common.py:
    ``arm_teardown_alarm``; its stacks are on stderr).  Nodes waiting to be restarted do not
    count."""
    for n, c in codes.items():
        if c == -signal.SIGALRM:
            sys.stderr.write(f'graph: node {n} stopped; its DDS teardown hung and its '
                             'shutdown alarm ended it (stacks above)\n')
    bad = {n: c for n, c in codes.items()
           if n not in restarting and c not in (0, -signal.SIGINT, 130, -signal.SIGALRM)}
    for n, c in bad.items():
        sys.stderr.write(f'error: node {n} exited with code {c} on Ctrl-C\n')
    return bad


# ------------------------------------------------------------------ record / replay

def _qos(latched: bool, depth: int = 100) -> Any:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1 if latched else depth,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched
                      else DurabilityPolicy.VOLATILE)


def topic_types(node: Any) -> dict[str, str]:
    return {name: types[0] for name, types in node.get_topic_names_and_types()}


def normalise(topic: str) -> str:
    return topic if topic.startswith('/') else '/' + topic


class Recorder:
    """Raw subscriptions (CDR bytes, no deserialisation) writing into a bag; counts per topic.

    Topics whose type is not yet known are subscribed as soon as discovery shows them.
    """

    def __init__(self, node: Any, topics: Sequence[str], out: str | Path,
                 known_types: dict[str, str] | None = None, storage: str = 'mcap') -> None:
        self.node = node
        self.topics = [normalise(t) for t in topics]
        self.writer = BagWriter(out, storage).__enter__()
        self.counts = {t: 0 for t in self.topics}
        self.first_ns: dict[str, int] = {}
        self._types = {normalise(k): v for k, v in (known_types or {}).items()}
        self._subs: dict[str, Any] = {}
        self._lock = threading.Lock()
        self._closed = False
        self.refresh()
        self._timer = node.create_timer(0.2, self.refresh)

    def refresh(self) -> None:
        from .io.msgtypes import rclpy_class
        live = topic_types(self.node)
        for t in self.topics:
            if t in self._subs:
                continue
            msgtype = self._types.get(t) or live.get(t)
            if not msgtype:
                continue
            self._types[t] = msgtype
            latched = t.lstrip('/') in LATCHED_TOPICS
            self._subs[t] = self.node.create_subscription(
                rclpy_class(msgtype), t, self._callback(t, msgtype), _qos(latched, 1000),
                raw=True)

    def _callback(self, topic: str, msgtype: str) -> Callable[[bytes], None]:
        def cb(raw: bytes) -> None:
            now = self.node.get_clock().now().nanoseconds
            with self._lock:
                if self._closed:
                    return
                self.writer.write(topic.lstrip('/'), msgtype, raw, now)
                self.counts[topic] += 1
                self.first_ns.setdefault(topic, now)
        return cb

    @property
    def subscribed(self) -> list[str]:
        return list(self._subs)

    def close(self) -> dict[str, int]:
        with self._lock:
            if not self._closed:
                self._closed = True
                self.writer.__exit__(None, None, None)
        return dict(self.counts)


DISCOVERY_SETTLE_S = 2.0   # after this long the ROS graph knows the running subscriptions


def wait_for_subscribers(node: Any, pubs: dict[str, Any], n: int, timeout: float,
                         settle: float = DISCOVERY_SETTLE_S) -> list[str]:
    """Wait until every publisher in ``pubs`` ({topic: publisher}) has >= ``n`` matched
    subscriptions, at most ``timeout`` s.  Once some topic is matched (discovery works) and the
    matches have not changed for ``settle`` s, a topic that nobody in the ROS graph subscribes
    to is not waited for.  Returns the topics left with fewer than ``n`` (published anyway)."""
    t0 = last_change = time.monotonic()
    seen: list[int] = []
    while True:
        now = time.monotonic()
        matched = [p.get_subscription_count() for p in pubs.values()]
        if matched != seen:
            seen, last_change = matched, now
        missing = [t for t, m in zip(pubs, matched) if m < n]
        if not missing or now - t0 >= timeout:
            return missing
        if any(matched) and now - last_change >= settle and not any(
                node.count_subscribers(t) > pubs[t].get_subscription_count() for t in missing):
            return missing          # every subscriber the graph knows of is matched
        time.sleep(0.05)


def replay(node: Any, bag: str | Path, rate: float = 1.0, loop: bool = False,
           clock: bool = False, topics: Sequence[str] | None = None,
           wait_subscribers: dict[str, int] | None = None, stop: threading.Event | None = None,
           wait_for: int = 0, wait_timeout: float = 10.0, damage: list[str] | None = None,
           unheard: list[str] | None = None) -> dict[str, int]:
    """Publish a bag's raw messages with the recorded timing (scaled by ``rate``).

    ``clock`` publishes /clock with the bag time (for ``use_sim_time``).  ``wait_for`` > 0 waits
    (at most ``wait_timeout`` s) until every published topic has that many subscribers matched
    (:func:`wait_for_subscribers`; the topics nobody subscribes to go to ``unheard``);
    ``wait_subscribers`` ({topic: n}) waits up to 10 s for those topics only.  A damaged bag is
    replayed as far as it reads and ``damage`` gets the line naming what was lost.  Returns
    counts per topic."""
    from .io.msgtypes import rclpy_class
    if rate <= 0:
        raise ValueError(f'rate: expected > 0, got {rate}')
    msgs = list(read_messages(bag, topics, damage=[] if damage is None else damage))
    pubs: dict[str, Any] = {}
    for m in msgs:
        if m.topic not in pubs:
            pubs[m.topic] = node.create_publisher(rclpy_class(m.msgtype), m.topic,
                                                  _qos(m.topic in LATCHED_TOPICS, 100))
    clock_pub = node.create_publisher(rclpy_class('rosgraph_msgs/msg/Clock'), '/clock', 10) \
        if clock else None
    if wait_for > 0:
        left = wait_for_subscribers(node, pubs, wait_for, wait_timeout)
        if unheard is not None:
            unheard += left
    if wait_subscribers:
        end = time.monotonic() + 10.0
        while time.monotonic() < end and not all(
                pubs[t].get_subscription_count() >= n for t, n in wait_subscribers.items()
                if t in pubs):
            time.sleep(0.05)
    counts: dict[str, int] = {}
    stop = stop or threading.Event()
    while True:
        t_wall0 = time.monotonic()
        t_bag0 = msgs[0].stamp_ns if msgs else 0
        for m in msgs:
            if stop.is_set():
                return counts
            due = t_wall0 + (m.stamp_ns - t_bag0) * 1e-9 / rate
            delay = due - time.monotonic()
            if delay > 0:
                stop.wait(delay)
            if clock_pub is not None:
                from rosgraph_msgs.msg import Clock
                from builtin_interfaces.msg import Time
                clock_pub.publish(Clock(clock=Time(sec=m.stamp_ns // 1_000_000_000,
                                                   nanosec=m.stamp_ns % 1_000_000_000)))
            pubs[m.topic].publish(m.raw)
            counts[m.topic] = counts.get(m.topic, 0) + 1
        if not loop:
            _wait_acked(pubs.values(), ACK_TIMEOUT_S)
            return counts


ACK_TIMEOUT_S = 5.0


def _wait_acked(pubs: Any, timeout: float) -> None:
    """Block until every matched reliable reader acknowledged what was published (at most
    ``timeout`` s in all): destroying a publisher earlier can drop the last samples in flight."""
    from rclpy.duration import Duration
    end = time.monotonic() + timeout
    for p in pubs:
        left = max(0.0, end - time.monotonic())
        p.wait_for_all_acked(Duration(nanoseconds=int(left * 1e9)))


# ------------------------------------------------------------------ topic tools

def hz(node: Any, topic: str, seconds: float) -> dict[str, float]:
    """Measured rate, message count and mean size on ``topic`` over ``seconds``."""
    import rclpy
    from .io.msgtypes import rclpy_class
    topic = normalise(topic)
    msgtype = _wait_type(node, topic, 10.0)
    times: list[float] = []
    sizes: list[int] = []
    node.create_subscription(rclpy_class(msgtype), topic,
                             lambda raw: (times.append(time.monotonic()), sizes.append(len(raw))),
                             _qos(False, 100), raw=True)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
    rate = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 else 0.0
    return {'rate_hz': rate, 'messages': len(times),
            'mean_bytes': sum(sizes) / len(sizes) if sizes else 0.0}


def _wait_type(node: Any, topic: str, timeout: float) -> str:
    import rclpy
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        t = topic_types(node).get(topic)
        if t:
            return t
        rclpy.spin_once(node, timeout_sec=0.05)
    raise LookupError(f'topic {topic} not found (is a publisher running on '
                      f'ROS_DOMAIN_ID={os.environ.get("ROS_DOMAIN_ID")}?)')


def describe(msg: Any, msgtype: str) -> str:
    """Human summary of a message; clouds and images get a header plus decoded fields."""
    import numpy as np

    from .io import pointcloud2 as pc2
    from .io.msgtypes import stamp_ns
    if msgtype.endswith('PointCloud2'):
        pts = pc2.read_points(msg).reshape(-1)
        lines = [f'stamp={stamp_ns(msg.header)} frame_id={msg.header.frame_id} '
                 f'points={pts.shape[0]} ({msg.height}x{msg.width}) fields='
                 f'{",".join(pc2.field_names(msg))}']
        for name in pts.dtype.names or ():
            col = pts[name].astype(np.float64)
            if col.size:
                lines.append(f'  {name}: min={np.nanmin(col):.4g} max={np.nanmax(col):.4g} '
                             f'first={col[:3].tolist()}')
        return '\n'.join(lines)
    if msgtype.endswith('msg/Image'):
        return (f'stamp={stamp_ns(msg.header)} frame_id={msg.header.frame_id} '
                f'{msg.width}x{msg.height} {msg.encoding} step={msg.step}')
    text = str(msg)
    return text if len(text) < 2000 else text[:2000] + '...'


def echo(node: Any, topic: str, count: int, timeout: float,
         write: Callable[[str], None] = print) -> int:
    import rclpy
    from .io.msgtypes import rclpy_class
    topic = normalise(topic)
    msgtype = _wait_type(node, topic, timeout)
    got: list[Any] = []
    node.create_subscription(rclpy_class(msgtype), topic, got.append,
                             _qos(topic.lstrip('/') in LATCHED_TOPICS, 100))
    end = time.monotonic() + timeout
    shown = 0
    while shown < count and time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
        while got and shown < count:
            write(describe(got.pop(0), msgtype))
            write('---')
            shown += 1
    return shown
