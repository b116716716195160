"""Shared node plumbing: parameters with on-set validation, QoS, diagnostics, error counting."""
from __future__ import annotations

import signal
from dataclasses import fields
from typing import Any

import rclpy
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)

from ..io.errors import MessageError
from ..io.msgtypes import RclpyFactory, rclpy_class
from ..params import NODE_PARAMS, Params
from ..processing import TOPICS, Processor, diagnostics_msg

# Keep-last 64 rather than 10: the reconstructor publishes a whole window (15+ clouds) at once
# when its window first fills, and a depth of 10 drops part of that burst.
RELIABLE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=64,
                      reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
SENSOR = qos_profile_sensor_data


class ProcessorNode(Node):
    """A node around one processor: declares the processor's parameters (same names as the
    YAML and the core), validates changes, subscribes its inputs, publishes its outputs."""

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
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._out_pubs: dict[str, Any] = {}
        self._logged: set[str] = set()
        for kind, msgtype in outputs:  # eagerly, so discovery completes before data flows
            self.publisher(TOPICS[kind], msgtype)
        self.diag_pub = self.create_publisher(rclpy_class('diagnostic_msgs/msg/DiagnosticArray'),
                                              TOPICS['diagnostics'], RELIABLE)
        self.create_timer(1.0, self.publish_diagnostics)

    def _on_set_parameters(self, changes: list[Any]) -> SetParametersResult:
        params: Params = self.processor.params
        try:
            new = params.updated({p.name: p.value for p in changes})
        except (ValueError, TypeError) as err:
            return SetParametersResult(successful=False, reason=str(err))
        self.processor.set_params(new)
        return SetParametersResult(successful=True)

    def subscribe(self, kind: str, msgtype: str, qos: QoSProfile) -> None:
        topic = TOPICS[kind]
        self.create_subscription(rclpy_class(msgtype), topic,
                                 lambda msg: self._on_message(kind, msg), qos)

    def _on_message(self, kind: str, msg: Any) -> None:
        try:
            outputs = self.processor.handle(kind, msg)
        except MessageError as err:
            key = f'{kind}:{err.field}'
            if key not in self._logged:  # log each kind of problem once, count all
                self._logged.add(key)
                self.get_logger().error(f'skipping malformed {kind} message: {err} '
                                        '(further ones are counted on /diagnostics)')
            return
        for topic, msgtype, out in outputs:
            self.publisher(topic, msgtype).publish(out)

    def publisher(self, topic: str, msgtype: str, qos: QoSProfile = RELIABLE) -> Any:
        if topic not in self._out_pubs:
            self._out_pubs[topic] = self.create_publisher(rclpy_class(msgtype), topic, qos)
        return self._out_pubs[topic]

    def publish_diagnostics(self) -> None:
        stamp = self.get_clock().now().nanoseconds
        self.diag_pub.publish(diagnostics_msg(self.factory, self.get_name(),
                                              self.processor.stats, stamp))


def spin_node(make: Any, args: list[str] | None = None) -> int:
    """The idiomatic main: init, spin, clean shutdown on Ctrl-C or external shutdown."""
    signal.signal(signal.SIGINT, signal.default_int_handler)   # see nodes/__init__.py
    node = None
    try:
        rclpy.init(args=args)
        node = make()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0

