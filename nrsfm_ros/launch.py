"""Launch the node graph as processes (there is no ros2 launch here): python -m nrsfm_ros.launch
[--nodes tracker,reconstructor,...] [--params DIR]."""
from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path


class _Startup:
    """Ctrl-C before the graph is up: exit 0 while importing (no node exists yet); while the
    nodes are being spawned, remember it and stop them once they all exist."""
    spawning = False
    stop = False

    @classmethod
    def on_sigint(cls, signum: int, frame: object) -> None:
        if not cls.spawning:
            raise SystemExit(0)
        cls.stop = True


def main(argv: list[str] | None = None) -> int:
    previous = signal.signal(signal.SIGINT, _Startup.on_sigint)
    try:
        from .live import NODES, Graph      # the heavy imports (rclpy, numpy)
        p = argparse.ArgumentParser(prog='nrsfm_ros.launch', description=__doc__)
        p.add_argument('--nodes', default=','.join(NODES))
        p.add_argument('--params', default=None, help='folder with <node>.yaml files')
        args = p.parse_args(argv)
        nodes = [n for n in args.nodes.split(',') if n]
        _Startup.spawning = True
        try:
            graph = Graph(nodes, Path(args.params) if args.params else None)
        except ValueError as err:
            print(f'error: {err}', file=sys.stderr)
            return 2
    finally:
        signal.signal(signal.SIGINT, previous)
    if _Startup.stop:
        graph.stop()
        return 0
    return graph.wait()


if __name__ == '__main__':
    sys.exit(main())
