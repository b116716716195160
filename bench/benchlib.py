"""Shared by the benchmark scripts: the command line (``--json``) and markdown tables."""
from __future__ import annotations

import argparse
from collections.abc import Iterable, Sequence


def parser(doc: str | None) -> argparse.ArgumentParser:
    """An argument parser with the script's docstring as help and ``--json OUT``."""
    p = argparse.ArgumentParser(description=doc,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--json', default=None, help='also write the rows as JSON to this file')
    return p


def table(header: Sequence[str], rows: Iterable[Sequence[object]]) -> None:
    """Print a markdown table."""
    print('| ' + ' | '.join(header) + ' |')
    print('|' + '---|' * len(header))
    for row in rows:
        print('| ' + ' | '.join(str(c) for c in row) + ' |')
