"""Replay the sample bag into a running node graph N times per camera QoS setting and count the
frames on each output (issue 16 target: 60/60 on every topic, 10 runs in a row, both QoS).

    . launch_scripts/ros_env.sh && .venv/bin/python bench/bench_replay.py [--runs 10]
"""
from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchlib import parser, table  # noqa: E402

TOPICS = ['nrsfm/tracks', 'nrsfm/points', 'scene_flow/points']


def main() -> None:
    p = parser(__doc__)
    p.add_argument('--runs', type=int, default=10)
    a = p.parse_args()
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from nrsfm_ros.demo import OUTPUTS, ensure_sample
    from nrsfm_ros.live import Graph, Recorder, ensure_loopback_env, replay
    ensure_loopback_env()
    bag, _ = ensure_sample(ROOT / 'bags')
    rclpy.init()
    node = Node('bench_replay')
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    threading.Thread(target=ex.spin, daemon=True).start()
    rows = []
    out = Path('/tmp') / 'bench_replay'
    try:
        for reliable in (True, False):
            graph = Graph(overrides={'tracker': {'reliable': reliable}}, quiet=True)
            try:
                time.sleep(3)
                for k in range(a.runs):
                    rec = Recorder(node, TOPICS, out / f'{int(reliable)}_{k}', known_types=OUTPUTS)
                    replay(node, bag, rate=1.0, wait_subscribers={'camera/image_raw': 1})
                    end = time.monotonic() + 20
                    while time.monotonic() < end and min(rec.counts.get('/' + t, 0)
                                                         for t in TOPICS) < 60:
                        time.sleep(0.2)
                    time.sleep(0.5)
                    counts = [rec.counts.get('/' + t, 0) for t in TOPICS]
                    rec.close()
                    rows.append(['reliable' if reliable else 'best effort', k, *counts])
            finally:
                graph.stop()
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    table(['camera QoS', 'run', *TOPICS], rows)


if __name__ == '__main__':
    main()
