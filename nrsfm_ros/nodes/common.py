"""Shared node plumbing: parameters with on-set validation, QoS, bounded input queues,
diagnostics, contained and counted errors."""
from __future__ import annotations

import faulthandler
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Collection
from dataclasses import fields
from typing import Any

import rclpy
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import (ExternalShutdownException, MultiThreadedExecutor,
                              SingleThreadedExecutor)
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)

from ..io.errors import MessageError
from ..io.msgtypes import RclpyFactory, rclpy_class
from ..params import NODE_PARAMS, Params
from ..processing import TOPICS, Processor, diagnostics_msg, error_key

# Keep-last 64 rather than 10: the reconstructor publishes a whole window (15+ clouds) at once
# when its window first fills, and a depth of 10 drops part of that burst.
RELIABLE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=64,
                      reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
SENSOR = qos_profile_sensor_data


# ``queue_size: 0`` (the default): how many messages an input holds, by its QoS.  A best-effort
# (sensor-data) input is a camera-rate stream: holding only the newest message keeps the
# latency at about one processing time when the node cannot keep up (a 30 Hz 640x480 camera
# into the tracker, bench/bench_overload.py: p50 latency 2981 ms with 64 held, 29x its
# processing time, 140 ms = 1.25x with 1).  A reliable input is a pipeline stage's output,
# whose messages all matter and may come in bursts (the reconstructor's batch of 60 clouds at
# once).
AUTO_QUEUE_SENSOR = 1
AUTO_QUEUE_RELIABLE = 64


def queue_depth(queue_size: int, reliable: bool) -> int:
    """Messages one input holds: ``queue_size``, or with 0 the automatic depth by QoS."""
    if queue_size > 0:
        return int(queue_size)
    return AUTO_QUEUE_RELIABLE if reliable else AUTO_QUEUE_SENSOR


class InputQueue:
    """The bounded input queue of a node: one FIFO in arrival order, at most ``size(kind)``
    messages per subscription kind.  A full kind under ``keep_latest`` discards its oldest
    message (counted by ``on_drop``); under ``keep_all`` ``put`` waits until there is room.
    A ``latest`` kind is a state whose newest value alone matters (CameraInfo, sent with every
    image): a new message replaces the one still queued, in its place in the queue (so it
    applies no later than that one would have), and nothing is counted as dropped."""

    def __init__(self, size: Callable[[str], int], policy: Callable[[], str],
                 on_drop: Callable[[str], None], latest: Collection[str] = ()) -> None:
        self._items: deque[list[Any]] = deque()        # [kind, msg]
        self._counts: dict[str, int] = {}
        self._size, self._policy, self._on_drop = size, policy, on_drop
        self.latest = set(latest)
        self._cond = threading.Condition()
        self.closed = False

    def __len__(self) -> int:
        return len(self._items)

    def put(self, kind: str, msg: Any) -> None:
        with self._cond:
            if kind in self.latest and self._counts.get(kind, 0):
                next(item for item in self._items if item[0] == kind)[1] = msg
                return
            while not self.closed and self._counts.get(kind, 0) >= self._size(kind):
                if self._policy() == 'keep_all':
                    self._cond.wait(0.1)
                    continue
                oldest = next(i for i, (k, _) in enumerate(self._items) if k == kind)
                del self._items[oldest]
                self._counts[kind] -= 1
                self._on_drop(kind)
            if self.closed:
                return
            self._items.append([kind, msg])
            self._counts[kind] = self._counts.get(kind, 0) + 1
            self._cond.notify_all()

    def get(self, timeout: float) -> tuple[str, Any] | None:
        with self._cond:
            if not self._items and not self.closed:
                self._cond.wait(timeout)
            if not self._items:
                return None
            kind, msg = self._items.popleft()
            self._counts[kind] -= 1
            self._cond.notify_all()
            return kind, msg

    def close(self) -> None:
        with self._cond:
            self.closed = True
            self._cond.notify_all()


class ProcessorNode(Node):
    """A node around one processor: declares the processor's parameters (same names as the
    YAML and the core), validates changes, subscribes its inputs, publishes its outputs.

    Subscription callbacks only queue the message (:class:`InputQueue`, parameters
    ``queue_size`` and ``queue_policy``); one worker thread processes the queue.  Every
    exception of a message's processing or publishing is contained: counted by kind on
    /diagnostics, logged once per kind, and the node goes on."""

    def __init__(self, name: str, processor_cls: type[Processor],
                 outputs: list[tuple[str, str]], **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.factory = RclpyFactory()
        defaults = NODE_PARAMS[name]()
        for f in fields(defaults):
            self.declare_parameter(f.name, getattr(defaults, f.name),
                                   ParameterDescriptor(description=f.metadata.get('doc', '')))
        values = {f.name: self.get_parameter(f.name).value for f in fields(defaults)}
        try:
            params = defaults.updated(values)
        except ValueError as err:
            raise SystemExit(f'{name}: invalid parameters: {err}') from err
        self.processor = processor_cls(self.factory, params)  # type: ignore[call-arg]
        self.lock = threading.RLock()     # the processor: worker, timers, parameter changes
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._out_pubs: dict[str, Any] = {}
        self._logged: set[str] = set()
        self.input_group = MutuallyExclusiveCallbackGroup()
        self._reliable: dict[str, bool] = {}      # per input kind: its QoS is reliable
        self.queue = InputQueue(self.queue_depth, lambda: self.processor.params.queue_policy,
                                self._dropped)
        for kind, msgtype in outputs:  # eagerly, so discovery completes before data flows
            self.publisher(TOPICS[kind], msgtype)
        self.diag_pub = self.create_publisher(rclpy_class('diagnostic_msgs/msg/DiagnosticArray'),
                                              TOPICS['diagnostics'], RELIABLE)
        self.create_timer(1.0, self.publish_diagnostics)
        self._worker = threading.Thread(target=self._work, name=f'{name}-worker', daemon=True)
        self._worker.start()

    def _on_set_parameters(self, changes: list[Any]) -> SetParametersResult:
        params: Params = self.processor.params
        try:
            new = params.updated({p.name: p.value for p in changes})
        except (ValueError, TypeError) as err:
            return SetParametersResult(successful=False, reason=str(err))
        with self.lock:
            self.processor.set_params(new)
        return SetParametersResult(successful=True)

    def queue_depth(self, kind: str) -> int:
        """Messages the input ``kind`` may hold (``queue_size``; 0: by its QoS)."""
        return queue_depth(self.processor.params.queue_size, self._reliable.get(kind, True))

    def subscribe(self, kind: str, msgtype: str, qos: QoSProfile, latest: bool = False
                  ) -> None:
        """Subscribe input ``kind``; ``latest``: a state input whose newest message alone
        matters (:class:`InputQueue`)."""
        topic = TOPICS[kind]
        if latest:
            self.queue.latest.add(kind)
        self._reliable[kind] = qos.reliability == ReliabilityPolicy.RELIABLE
        events = SubscriptionEventCallbacks(
            message_lost=lambda info: self._dropped(kind, int(info.total_count_change)))
        self.create_subscription(rclpy_class(msgtype), topic,
                                 lambda msg: self._enqueue(kind, msg), qos,
                                 callback_group=self.input_group, event_callbacks=events)

    def _enqueue(self, kind: str, msg: Any) -> None:
        # an input the current parameters do not use (the reconstructor's camera images outside
        # mode hdmnet) never takes a place in the queue nor counts as dropped
        if self.processor.accepts(kind):
            self.queue.put(kind, msg)

    def _dropped(self, kind: str, n: int = 1) -> None:
        if not self.processor.accepts(kind):
            return
        self.processor.stats.dropped += n
        self.processor.stats.count_error(f'{kind}:dropped', f'{kind}: {n} message(s) dropped '
                                         f'(input queue full or lost in transport)')

    def _work(self) -> None:
        while not self.queue.closed:
            item = self.queue.get(0.2)
            if item is not None:
                self._on_message(*item)
            else:
                self.on_idle()

    # the input whose silence for ``idle_flush_s`` publishes what the processor still holds
    # (its ``flush``): a stream that stopped before a window or look-ahead filled
    idle_flush_kind: str | None = None
    _last_input = 0.0

    def on_idle(self) -> None:
        """Called by the worker thread when no input arrived for 0.2 s (long work done here
        does not hold up a shutdown: the worker is a daemon thread)."""
        idle = getattr(self.processor.params, 'idle_flush_s', 0.0)
        if self.idle_flush_kind is None or idle <= 0 or not self._last_input or \
                time.monotonic() - self._last_input < idle:
            return
        try:
            with self.lock:
                outputs = self.processor.flush()
        except Exception as err:  # noqa: BLE001 -- contained like every message
            self._failed('flush', err)
            return
        self.publish_outputs(outputs)

    def _on_message(self, kind: str, msg: Any) -> None:
        if kind == self.idle_flush_kind:
            self._last_input = time.monotonic()
        try:
            with self.lock:
                outputs = self.processor.handle(kind, msg)
        except MessageError as err:
            self._log_once(error_key(kind, err), f'skipping {kind} message: {err}')
            return
        except Exception as err:  # noqa: BLE001 -- handle contains; this is the last guard
            self._failed(kind, err)
            return
        if outputs:
            t0, c0 = time.perf_counter(), time.process_time()
            self.publish_outputs(outputs)
            # serializing and handing the outputs to DDS: kind 'publish' on /diagnostics
            self.processor.stats.add_time('publish', time.perf_counter() - t0,
                                          time.process_time() - c0)

    def publish_outputs(self, outputs: list[tuple[str, str, Any]]) -> None:
        for topic, msgtype, out in outputs:
            try:
                self.publisher(topic, msgtype).publish(out)
            except Exception as err:  # noqa: BLE001 -- e.g. an out-of-range field value
                self._failed(f'publish {topic}', err)

    def _failed(self, what: str, err: Exception) -> None:
        self.processor.stats.failed += 1
        key = f'{what}:{type(err).__name__}'
        self.processor.stats.count_error(key, f'{what}: {type(err).__name__}: {err}')
        self._log_once(key, f'{what} failed: {type(err).__name__}: {err}')

    def _log_once(self, key: str, text: str) -> None:
        if key not in self._logged:  # log each kind of problem once, count all
            self._logged.add(key)
            self.get_logger().error(f'{text} (further ones are counted on /diagnostics)')

    def publisher(self, topic: str, msgtype: str, qos: QoSProfile = RELIABLE) -> Any:
        if topic not in self._out_pubs:
            self._out_pubs[topic] = self.create_publisher(rclpy_class(msgtype), topic, qos)
        return self._out_pubs[topic]

    def publish_diagnostics(self) -> None:
        stamp = self.get_clock().now().nanoseconds
        self.diag_pub.publish(diagnostics_msg(self.factory, self.get_name(),
                                              self.processor.stats, stamp,
                                              {'queued': str(len(self.queue)),
                                               **self.processor.status()}))

    def destroy_node(self) -> None:
        self.queue.close()
        if self._worker.is_alive() and self._worker is not threading.current_thread():
            self._worker.join(1.0)      # a daemon: one still inside a long solve is left
        super().destroy_node()


def make_executor(node: Any, context: Any = None) -> Any:
    """The executor that spins ``node``: one thread while its inputs keep their latest messages
    (every callback then only enqueues or runs a short timer; the worker thread processes);
    two otherwise (``queue_policy: keep_all``, or a node without a processor), so that a
    subscription held by a full queue never stops the timers.  rclpy's multi-threaded executor
    delivers late on some machines (best-effort frames 20 ms apart taken up to 1.1 s after
    publication, half of them overwritten by DDS unreported; the single-threaded one within
    1 ms on the same machine)."""
    params = getattr(getattr(node, 'processor', None), 'params', None)
    if getattr(params, 'queue_policy', None) == 'keep_latest':
        return SingleThreadedExecutor(context=context)
    return MultiThreadedExecutor(num_threads=2, context=context)


def spin_node(make: Any, args: list[str] | None = None) -> int:
    """The idiomatic main: init, spin, clean shutdown on Ctrl-C or external shutdown."""
    from . import STOP_REQUESTED
    node = None
    code = 1
    try:
        signal.signal(signal.SIGINT, signal.default_int_handler)   # see nodes/__init__.py
        if STOP_REQUESTED:           # Ctrl-C while importing: stop before starting anything
            code = 0
            return 0
        rclpy.init(args=args)
        node = make()
        executor = make_executor(node)
        executor.add_node(node)
        executor.spin()
        code = 0
    except (KeyboardInterrupt, ExternalShutdownException):
        code = 0
    except Exception:
        # Ctrl-C between rclpy.init and a running executor: rclpy's handler shut the context
        # down and creating the node or its entities fails (RCLError); that is a clean stop
        if rclpy.ok():
            raise
        code = 0
    finally:
        shutdown_watchdog(_name(node), code)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


SHUTDOWN_GRACE_S = 5.0   # a node still running this long after Ctrl-C exits anyway


def _name(node: Any) -> str:
    try:
        return node.get_name()
    except Exception:            # not created, or its handle already gone
        return 'node'


def shutdown_watchdog(name: str, code: int = 0, grace_s: float | None = None
                      ) -> threading.Thread:
    """A daemon thread that, if the process is still alive ``grace_s`` after the node began
    to stop (a thread stuck in a DDS call or a callback, or interpreter teardown joining a
    worker), writes every thread's stack to stderr and ends the process with ``code`` (0 after
    Ctrl-C: the node's work is over, and Ctrl-C of a graph must stop it in bounded time; 1 when
    it stops on an error)."""
    grace_s = SHUTDOWN_GRACE_S if grace_s is None else grace_s

    def expire() -> None:
        time.sleep(grace_s)
        sys.stderr.write(f'warning: node {name} still running {grace_s:g} s after it began '
                         'to stop; its threads:\n')
        sys.stderr.flush()
        faulthandler.dump_traceback(sys.stderr, all_threads=True)
        sys.stderr.flush()
        os._exit(code)
    t = threading.Thread(target=expire, name='shutdown-watchdog', daemon=True)
    t.start()
    arm_teardown_alarm(grace_s + ALARM_AFTER_GRACE_S)
    return t


ALARM_AFTER_GRACE_S = 2.0   # the kernel's backstop, after the Python watchdog's grace


def arm_teardown_alarm(after_s: float) -> None:
    """A backstop that needs no Python thread to run.  rclpy's teardown calls into DDS
    (``rcl_node_fini`` and the participant's deletion) holding the GIL; when one of those
    calls hangs (rclpy#456, Fast-DDS#235: seen once in CI in ~20 sessions) the watchdog thread
    above can never wake.  faulthandler's C thread writes every thread's stack to stderr
    half a second before the alarm; SIGALRM with its default action then ends the process
    (status -SIGALRM, which the graph launcher reads as "stopped, teardown cut short").  Only
    from the main thread (signal handlers are set there); elsewhere the watchdog is all."""
    if threading.current_thread() is not threading.main_thread():
        return
    faulthandler.dump_traceback_later(max(0.1, after_s - 0.5), exit=False)
    signal.signal(signal.SIGALRM, signal.SIG_DFL)
    signal.setitimer(signal.ITIMER_REAL, after_s)

