"""SPVA (issue 13): accuracy behind an occluder and per-frame latency after the prior.

    .venv/bin/python bench/bench_spva.py [--surfaces face,flag] [--points 2000] [--soft 0.25]
        [--init cdf] [--latency-points 10000] [--json out.json]

Accuracy: ``dense_tracks`` (60 frames, camera 40 deg, amplitude 2, grid sampling, seed 0) with
``io.synth_occlusion.occlude_tracks`` (a disc over 30% of the tracks crossing frames 20-49, the
covered tracks dragged with it at visibility ``--soft``).  Per row: metric B (per-frame
Procrustes + scale) and the RMS point error (relative to the frame's RMS radius) on the
occluded points and on the visible points of the occluded frames, for the static oracle
(ground truth frame 0), the rigid factorisation, the ``--init`` batch method, and SPVA from it
with each prior weighting, without the prior (prior_weight 0) and with a refreshed prior.

Latency: a prior on ``--latency-points`` tracks (face, from the rigid factorisation of 24
frames; the accuracy does not matter here), then the median ``ShapePrior.step`` time over 20
frames with 30% of the tracks at visibility 0.2, on the cores this process may use (run it
under ``taskset -c 0,1`` for the 2-core figure), wall and process CPU time (what the frame
costs when the cores are not shared with other work).
"""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchlib import parser, table  # noqa: E402
from nrsfm_ros.core.metrics import batched_procrustes  # noqa: E402
from nrsfm_ros.core.nrsfm import reconstruct  # noqa: E402
from nrsfm_ros.core.nrsfm.spva import ShapePrior  # noqa: E402
from nrsfm_ros.io.synth import dense_tracks  # noqa: E402
from nrsfm_ros.io.synth_occlusion import occlude_tracks  # noqa: E402

VARIANTS = {'spva (pixel)': {}, 'spva (frame)': {'weighting': 'frame'},
            'spva (sequence)': {'weighting': 'sequence'},
            'spva (refresh 0.2)': {'refresh': 0.2},
            'same solver, no prior': {'prior_weight': 0.0}}


def errors(S: np.ndarray, S_gt: np.ndarray, occ: np.ndarray) -> tuple[float, float, float]:
    B = S_gt - S_gt.mean(1, keepdims=True)
    A = batched_procrustes(S - S.mean(1, keepdims=True), B, scale=True)
    e3d = float(np.mean(np.linalg.norm((A - B).reshape(len(A), -1), axis=1)
                        / np.linalg.norm(B.reshape(len(B), -1), axis=1)))
    rel = np.linalg.norm(A - B, axis=2) / np.sqrt((B ** 2).sum(2).mean(1))[:, None]
    fr = occ.any(1)
    return (e3d, float(np.sqrt(np.mean(rel[occ] ** 2))),
            float(np.sqrt(np.mean(rel[fr][~occ[fr]] ** 2))))


def accuracy(surface: str, points: int, soft: float, init: str) -> list[dict]:
    d = dense_tracks(surface, frames=60, points=points, camera_motion_deg=40, sampling='grid',
                     amplitude=2, seed=0)
    W, V, occ = occlude_tracks(d['W'], (20, 50), soft=soft)
    S = d['S']
    rows = []

    def add(name: str, S_est: np.ndarray, seconds: float) -> None:
        e, o, v = errors(S_est, S, occ)
        rows.append({'surface': surface, 'method': name, 'e3d': e, 'occluded': o, 'visible': v,
                     'seconds': seconds})
    add('static oracle', np.broadcast_to(S[0], S.shape), 0.0)
    for m in ('rigid', init):
        t = time.perf_counter()
        res = reconstruct(W, V, method=m)
        add(m, res.S, time.perf_counter() - t)
    for name, kw in VARIANTS.items():
        t = time.perf_counter()
        out = ShapePrior.from_batch(res, W, V, **kw).solve(W, V)
        add(f'{name} from {init}', out.S, time.perf_counter() - t)
    return rows


def latency(points: int) -> dict:
    d = dense_tracks('face', frames=44, points=points, camera_motion_deg=40, sampling='grid')
    P = d['W'].shape[1]
    res = reconstruct(d['W'][:48], method='rigid')
    prior = ShapePrior.from_batch(res, d['W'][:48], np.ones((24, P)))
    vis = np.ones(P)
    vis[:int(0.3 * P)] = 0.2
    cpu = []
    for f in range(24, 44):
        c = time.process_time()
        prior.step(d['W'][2 * f:2 * f + 2].T, vis)
        cpu.append(time.process_time() - c)
    sec = np.array(prior.seconds)
    return {'points': P, 'median_ms': 1e3 * float(np.median(sec)),
            'p90_ms': 1e3 * float(np.percentile(sec, 90)),
            'cpu_median_ms': 1e3 * float(np.median(cpu)), 'cores': len(os.sched_getaffinity(0)),
            'load': os.getloadavg()[0]}


def main() -> None:
    p = parser(__doc__)
    p.add_argument('--surfaces', default='face,flag')
    p.add_argument('--points', type=int, default=2000)
    p.add_argument('--soft', type=float, default=0.25)
    p.add_argument('--init', default='cdf')
    p.add_argument('--latency-points', type=int, default=10_000)
    a = p.parse_args()
    rows = [r for s in a.surfaces.split(',') if s for r in accuracy(s, a.points, a.soft, a.init)]
    table(['surface', 'method', 'e3D', 'occluded', 'visible', 'occluded/visible', 's'],
          [[r['surface'], r['method'], f"{r['e3d']:.4f}", f"{r['occluded']:.4f}",
            f"{r['visible']:.4f}", f"{r['occluded'] / r['visible']:.2f}", f"{r['seconds']:.1f}"]
           for r in rows])
    lat = latency(a.latency_points)
    print(f"\nper-frame latency after the prior: {lat['points']} tracks, median "
          f"{lat['median_ms']:.1f} ms, p90 {lat['p90_ms']:.1f} ms wall on {lat['cores']} cores "
          f"(load average {lat['load']:.1f}); CPU time {lat['cpu_median_ms']:.1f} ms")
    if a.json:
        Path(a.json).write_text(json.dumps({'accuracy': rows, 'latency': lat}, indent=1))


if __name__ == '__main__':
    main()
