"""Launch the node graph as processes (there is no ros2 launch here): python -m nrsfm_ros.launch
[--nodes tracker,reconstructor,...] [--params DIR]."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .live import NODES, Graph


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog='nrsfm_ros.launch', description=__doc__)
    p.add_argument('--nodes', default=','.join(NODES))
    p.add_argument('--params', default=None, help='folder with <node>.yaml files')
    args = p.parse_args(argv)
    nodes = [n for n in args.nodes.split(',') if n]
    try:
        graph = Graph(nodes, Path(args.params) if args.params else None)
    except ValueError as err:
        print(f'error: {err}', file=sys.stderr)
        return 2
    return graph.wait()


if __name__ == '__main__':
    sys.exit(main())
