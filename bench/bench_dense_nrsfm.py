"""Dense NRSfM benchmark (issue 3): generated dense sequences, every method, metric B and time.

    .venv/bin/python bench/bench_dense_nrsfm.py [--points 10000] [--json out.json]

Data: `nrsfm_ros.io.synth.dense_tracks` -- the flag (cloth, travelling waves) and face-like
(jaw opening, cheeks) surfaces of the sample generator, sampled at P points (no rendering), 60
frames, the generator's two-axis camera path (40 degrees), orthographic or weak-perspective
projection (focal 2000 px at 4 m).  Conditions: clean; and 1 px Gaussian track noise with 30%
of the tracks (the left part of the first frame) occluded for 20 frames.  Metric B per frame
(`e3d_frobenius(..., 'frame', scale=True)`, camera frame; the scale is fitted because the
reconstruction is in pixels).  A second table: seconds and peak traced memory against P; a
third: the reconstructor's online mode, milliseconds per frame after its first window.
"""
from __future__ import annotations

import json
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchlib import parser, table  # noqa: E402
from nrsfm_ros.core.metrics import e3d_frobenius  # noqa: E402
from nrsfm_ros.core.nrsfm import reconstruct  # noqa: E402
from nrsfm_ros.io.synth import dense_tracks  # noqa: E402

METHODS = ('rigid', 'lowrank', 'bmm', 'smsr', 'amp', 'cdf', 'va', 'planar')
FAST = ('bmm', 'smsr', 'amp', 'cdf')
SIZES = (1_000, 3_000, 10_000, 30_000, 100_000)


def conditions(d: dict, seed: int = 0):
    """(name, W, V): clean, and noise + a 30% block occluded for 20 frames."""
    W, V = d['W'], d['V']
    yield 'clean', W, V
    rng = np.random.default_rng(seed)
    F = V.shape[0]
    hidden = W[0] < np.quantile(W[0], 0.3)
    Vo = V.copy()
    Vo[F // 3:F // 3 + 20][:, hidden] = 0
    yield 'noise 1 px + 30% occluded 20 f', W + rng.normal(0, 1.0, W.shape), Vo


def accuracy(points: int) -> list[dict]:
    rows = []
    for surface in ('flag', 'face'):
        for projection in ('orthographic', 'weak-perspective'):
            d = dense_tracks(surface, 60, points, projection)
            for cond, W, V in conditions(d):
                for method in METHODS:
                    t = time.perf_counter()
                    res = reconstruct(W, V, method=method)
                    rows.append({'table': 'accuracy', 'surface': surface,
                                 'projection': projection, 'condition': cond,
                                 'method': method, 'P': points,
                                 'e3d_B_frame': e3d_frobenius(res.S, d['S'], 'frame',
                                                              scale=True),
                                 'seconds': time.perf_counter() - t})
    return rows


def scaling() -> list[dict]:
    rows = []
    for P in SIZES:
        d = dense_tracks('face', 60, P, 'orthographic')
        for method in FAST:
            tracemalloc.start()
            t = time.perf_counter()
            res = reconstruct(d['W'], d['V'], method=method)
            sec = time.perf_counter() - t
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
            rows.append({'table': 'scaling', 'method': method, 'P': P, 'seconds': sec,
                         'peak_MB': peak / 2 ** 20,
                         'e3d_B_frame': e3d_frobenius(res.S, d['S'], 'frame', scale=True)})
    return rows


def online_latency() -> list[dict]:
    """Reconstructor ``mode: online``: ms per frame after the first window, against P."""
    from nrsfm_ros.core.nrsfm.stream import StreamNRSfM
    rows = []
    for P in (1_000, 10_000, 30_000):
        d = dense_tracks('face', 60, P)
        window = 15
        online = StreamNRSfM(mode='online', window=window)
        ids = np.arange(d['W'].shape[1])
        ms = []
        for f in range(60):
            t = time.perf_counter()
            online.push(ids, d['W'][2 * f:2 * f + 2].T)
            ms.append(1e3 * (time.perf_counter() - t))
        after = np.array(ms[window + 1:])
        rows.append({'table': 'online', 'P': P, 'window_ms': max(ms),
                     'frame_ms_median': float(np.median(after)),
                     'frame_ms_p95': float(np.percentile(after, 95))})
    return rows


def main() -> int:
    p = parser(__doc__)
    p.add_argument('--points', type=int, default=10_000)
    args = p.parse_args()
    reconstruct(dense_tracks('face', 20, 500)['W'], method='bmm')     # warm-up imports
    rows = accuracy(args.points)
    keys = sorted({(r['surface'], r['projection'], r['condition']) for r in rows},
                  key=lambda k: (k[0], k[1], k[2] != 'clean'))
    by_key = {(r['surface'], r['projection'], r['condition'], r['method']): r for r in rows}
    table(['surface', 'projection', 'condition', *METHODS],
          [[*key] + [f"{by_key[(*key, m)]['e3d_B_frame']:.4f} "
                     f"({by_key[(*key, m)]['seconds']:.1f} s)" for m in METHODS]
           for key in keys])
    scale = scaling()
    by_size = {(r['P'], r['method']): r for r in scale}
    print()
    table(['P'] + [f'{m} s (peak MB)' for m in FAST],
          [[f'{P:,}'] + [f"{by_size[(P, m)]['seconds']:.2f} ({by_size[(P, m)]['peak_MB']:.0f})"
                         for m in FAST] for P in SIZES])
    online = online_latency()
    print()
    table(['P', 'first window (ms)', 'online frame, median (ms)', 'online frame, p95 (ms)'],
          [(f"{r['P']:,}", f"{r['window_ms']:.0f}", f"{r['frame_ms_median']:.1f}",
            f"{r['frame_ms_p95']:.1f}") for r in online])
    if args.json:
        Path(args.json).write_text(json.dumps(rows + scale + online, indent=1))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
