"""Latency of a node under overload over real DDS (issue 17 target: under a 30 Hz input the node
cannot keep up with, p50 latency <= 1.5x its processing time).

    .venv/bin/python bench/bench_overload.py [--node tracker] [--size 640x480] [--rate 30]
        [--seconds 12] [--queue-sizes 0,64] [--points 100000] [--json out.json]

One node runs alone as its own process (``live.Graph``, the shipped config, ``queue_size`` set
per row); this process publishes its input at ``--rate`` Hz like a driver and subscribes to its
output.  ``tracker``: a 30 deg flag render (``--size``) on ``camera/image_raw`` with sensor-data
QoS, as a camera driver publishes; output ``nrsfm/tracks``.  ``registrar``: the waving sheet of
``bench_registrar_rate.py`` (``--points``) on ``nrsfm/points``, reliable, as the reconstructor
publishes; output ``registration/transform``.  Per row: frames sent, processed and dropped (the
node's /diagnostics), latency from publishing to receiving the output (p50, p90; every output
matched by its stamp), the node's own processing time per message (p50 of its /diagnostics),
and their ratio.  ``queue_size`` 0 is the shipped default: by the input's QoS, 1 on a
best-effort input, 64 on a reliable one (docs/robustness.md).
"""
from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchlib import parser, table  # noqa: E402


def tracker_inputs(size: tuple[int, int], frames: int) -> list:
    from nrsfm_ros.io import image as img_io
    from nrsfm_ros.io.msgtypes import RclpyFactory
    from nrsfm_ros.io.synth import SynthConfig, generate
    seq = generate(SynthConfig(surface='flag', width=size[0], height=size[1], frames=frames,
                               camera_motion_deg=30))
    fac = RclpyFactory()
    return [img_io.array_to_image(im, 'rgb8', fac, 0, 'camera') for im in seq.images]


def registrar_inputs(points: int, count: int) -> list:
    """rclpy PointCloud2 messages of ``bench_registrar_rate``'s waving sheet (the publisher
    only restamps them)."""
    from bench_registrar_rate import clouds
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import PointCloud2

    from nrsfm_ros.io.bag import serialize
    return [deserialize_message(serialize(m, 'sensor_msgs/msg/PointCloud2'), PointCloud2)
            for m in clouds(points, count)]


def run_row(node: str, queue_size: int, inputs: list, rate: float, seconds: float,
            ctx) -> dict:
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import TransformStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image, PointCloud2

    from nrsfm_ros.live import Graph
    from nrsfm_ros.nodes.common import LATCHED, RELIABLE, SENSOR
    graph = Graph([node], overrides={node: {'queue_size': queue_size}}, quiet=True)
    probe = Node('overload_probe', context=ctx)
    recv: dict[int, float] = {}
    diags: list[dict[str, str]] = []
    out_topic, out_type = (('nrsfm/tracks', PointCloud2) if node == 'tracker'
                           else ('registration/transform', TransformStamped))
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)

    def got(msg) -> None:
        recv.setdefault(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec,
                        time.monotonic())

    def diag(msg) -> None:
        diags.extend({kv.key: kv.value for kv in st.values} for st in msg.status
                     if st.hardware_id == node)
    probe.create_subscription(out_type, out_topic, got, qos)
    probe.create_subscription(DiagnosticArray, '/diagnostics', diag, qos)
    if node == 'tracker':
        pub = probe.create_publisher(Image, 'camera/image_raw', SENSOR)
        kind = 'image'
    else:
        pub = probe.create_publisher(PointCloud2, 'nrsfm/points', RELIABLE)
        ref = probe.create_publisher(PointCloud2, 'registration/reference', LATCHED)
        kind = 'points'
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(probe)
    spin = threading.Thread(target=ex.spin, daemon=True)
    spin.start()
    sent: dict[int, float] = {}
    try:
        end = time.monotonic() + 60
        while (pub.get_subscription_count() < 1 or not diags) and time.monotonic() < end:
            time.sleep(0.05)
        if node == 'registrar':
            ref.publish(inputs[0])
            time.sleep(1.0)
        n = int(rate * seconds)
        t0 = time.monotonic()
        for i in range(n):
            while time.monotonic() < t0 + i / rate:
                time.sleep(0.0005)
            stamp = (i + 1) * 10**9 // int(rate)
            msg = inputs[1 + i % (len(inputs) - 1)]
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 10**9)
            sent[stamp] = time.monotonic()
            pub.publish(msg)
        # let the queue drain: until nothing new arrived for 3 s
        last = -1
        while len(recv) != last:
            last = len(recv)
            time.sleep(3.0)
        time.sleep(1.2)                       # one more /diagnostics
    finally:
        ex.shutdown()
        probe.destroy_node()
        graph.stop()
    lat = np.array([1000 * (recv[s] - sent[s]) for s in sent if s in recv])
    d = diags[-1] if diags else {}
    proc = float(d.get(f'{kind}_ms_p50', 'nan'))
    p50 = float(np.median(lat)) if lat.size else float('nan')
    return {'node': node, 'queue_size': queue_size, 'sent': len(sent),
            'processed': int(d.get('processed', 0)), 'dropped': int(d.get('dropped', 0)),
            'outputs': int(lat.size), 'latency_p50_ms': round(p50, 1),
            'latency_p90_ms': round(float(np.percentile(lat, 90)), 1) if lat.size else None,
            'processing_p50_ms': round(proc, 1), 'ratio': round(p50 / proc, 2)}


def main() -> None:
    p = parser(__doc__)
    p.add_argument('--node', default='tracker', choices=('tracker', 'registrar'))
    p.add_argument('--size', default='640x480')
    p.add_argument('--points', type=int, default=100_000)
    p.add_argument('--rate', type=float, default=30.0)
    p.add_argument('--seconds', type=float, default=12.0)
    p.add_argument('--queue-sizes', default='0,64')
    a = p.parse_args()
    import os

    import rclpy

    from nrsfm_ros.live import ensure_loopback_env
    os.environ.update(ensure_loopback_env(dict(os.environ)))
    w, h = (int(v) for v in a.size.split('x'))
    inputs = tracker_inputs((w, h), 31) if a.node == 'tracker' else \
        registrar_inputs(a.points, 31)
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx)
    rows = []
    try:
        for q in (int(v) for v in a.queue_sizes.split(',')):
            rows.append(run_row(a.node, q, inputs, a.rate, a.seconds, ctx))
            print(rows[-1], flush=True)
    finally:
        rclpy.shutdown(context=ctx)
    table(['node', 'queue_size', 'sent', 'processed', 'dropped', 'outputs', 'latency p50 ms',
           'p90 ms', 'processing p50 ms', 'latency / processing'],
          [list(r.values()) for r in rows])
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == '__main__':
    main()
