"""NRSfM methods by name: ``reconstruct(W, V, method=...)`` and the sliding window."""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from .amp import amp
from .bmm import bmm, smsr
from .cdf import cdf
from .dspr import DynamicShapePrior
from .hdsm import hdsm
from .factorization import low_rank, rigid
from .planar import planar
from .spva import ShapePrior, spva
from .va import va
from .result import NRSfMResult, check_tracks
from .stream import StreamNRSfM

METHODS: dict[str, Callable[..., NRSfMResult]] = {
    'rigid': rigid,
    'lowrank': low_rank,
    'bmm': bmm,
    'smsr': smsr,
    'amp': amp,
    'cdf': cdf,
    'hdsm': hdsm,
    'va': va,
    'planar': planar,
    'spva': spva,
}


def reconstruct(W: np.ndarray, V: np.ndarray | None = None, method: str = 'bmm',
                **params: Any) -> NRSfMResult:
    """Run the named method (default ``bmm``, as the CLI) on tracks W (2F, P) with optional
    visibility V (F, P)."""
    if method not in METHODS:
        raise ValueError(f'method={method!r}: expected one of {sorted(METHODS)}')
    return METHODS[method](W, V, **params)


__all__ = ['METHODS', 'DynamicShapePrior', 'NRSfMResult', 'ShapePrior', 'StreamNRSfM',
           'check_tracks',
           'low_rank', 'reconstruct', 'rigid']
