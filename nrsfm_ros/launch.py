"""Launch the node graph as processes (there is no ros2 launch here): python -m nrsfm_ros.launch
[--nodes tracker,reconstructor,...] [--params DIR] [--max-restarts N].  A node that dies is
restarted with backoff; the launcher exits non-zero only when it gives up."""
from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path


class _Startup:
    """Ctrl-C before the graph is up is only remembered (raising inside an import can break
    it: an interrupted C-extension import of NumPy fails with ImportError): once the imports
    are done the launcher exits 0 (no node exists yet); while the nodes are being spawned, it
    stops them once they all exist."""
    stop = False

    @classmethod
    def on_sigint(cls, signum: int, frame: object) -> None:
        cls.stop = True


def main(argv: list[str] | None = None) -> int:
    previous = signal.signal(signal.SIGINT, _Startup.on_sigint)
    try:
        from .live import NODES, Graph      # the heavy imports (rclpy, numpy)
        p = argparse.ArgumentParser(prog='nrsfm_ros.launch', description=__doc__)
        p.add_argument('--nodes', default=','.join(NODES))
        p.add_argument('--params', default=None, help='folder with <node>.yaml files')
        p.add_argument('--max-restarts', type=int, default=10, metavar='N',
                       help='restarts of one node in a row before the graph gives up and exits '
                       'non-zero (0: a dying node stops the graph; default 10)')
        args = p.parse_args(argv)
        if args.max_restarts < 0:
            print(f'error: --max-restarts {args.max_restarts}: must be >= 0', file=sys.stderr)
            return 2
        nodes = [n for n in args.nodes.split(',') if n]
        if _Startup.stop:
            return 0
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
    return graph.wait(max_restarts=args.max_restarts)


if __name__ == '__main__':
    sys.exit(main())
