"""The registrar's rate on large clouds (issue 17 target: >= 10 Hz at 100k points on 2 cores):
``RegistrarProcessor`` fed deserialised clouds one after another, no DDS, per-cloud wall time
after the reference.  Clouds: a waving 1.0 x 0.7 m sheet seen by a camera turning 0.3 deg a
frame at 2 m, 2 mm noise, every point with its track id (what the reconstructor publishes).

    .venv/bin/python bench/bench_registrar_rate.py [--points 100000] [--clouds 30]
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchlib import parser, table  # noqa: E402


def clouds(points: int, count: int, seed: int = 0) -> list:
    """``count`` PointCloud2 messages (x, y, z, track_id) of the waving sheet."""
    from scipy.spatial.transform import Rotation

    from nrsfm_ros.io import pointcloud2 as pc2
    from nrsfm_ros.io.msgtypes import RosbagsFactory
    rng = np.random.default_rng(seed)
    s, t = rng.random(points), rng.random(points)
    ids = np.arange(points, dtype=np.uint32)
    out = []
    for f in range(count):
        X = np.stack([s - 0.5, (t - 0.5) * 0.7,
                      0.09 * s * np.sin(2 * np.pi * (1.1 * s - 0.05 * f) + 1.3 * t)], 1)
        X = X @ Rotation.from_euler('y', 0.3 * f, degrees=True).as_matrix().T + [0, 0, 2.0]
        X = (X + rng.normal(0, 0.002, X.shape)).astype(np.float32)
        out.append(pc2.to_msg({'x': X[:, 0], 'y': X[:, 1], 'z': X[:, 2], 'track_id': ids},
                              RosbagsFactory(), f * 33_333_333, 'camera'))
    return out


def main() -> None:
    p = parser(__doc__)
    p.add_argument('--points', type=int, default=100_000)
    p.add_argument('--clouds', type=int, default=30)
    a = p.parse_args()
    from nrsfm_ros.io.msgtypes import RosbagsFactory
    from nrsfm_ros.params import RegistrarParams
    from nrsfm_ros.processing import RegistrarProcessor
    msgs = clouds(a.points, a.clouds + 1)
    rows = []
    for match in ('track_id', 'nearest'):
        proc = RegistrarProcessor(RosbagsFactory(), RegistrarParams(match=match))
        proc.handle('reference', msgs[0])
        ms = []
        for m in msgs[1:]:
            t0 = time.perf_counter()
            out = proc.handle('points', m)
            ms.append(1000 * (time.perf_counter() - t0))
            assert out, 'the registrar published nothing'
        med = float(np.median(ms))
        rows.append({'match': match, 'points': a.points, 'clouds': len(ms),
                     'median_ms': round(med, 1), 'p90_ms': round(float(np.percentile(ms, 90)), 1),
                     'hz': round(1000 / med, 1)})
    table(['match', 'points', 'clouds', 'median ms', 'p90 ms', 'Hz (1 / median)'],
          [list(r.values()) for r in rows])
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == '__main__':
    main()
