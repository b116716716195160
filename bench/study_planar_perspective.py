"""Study (issue 12): the planar model refined under the pinhole camera
(``core/nrsfm/planar_pinhole.py``, which the stream runs on every planar batch with CameraInfo)
against the perspective step alone and the true-depth bound, on ground-truth tracks of ``synth``
renders.

    .venv/bin/python bench/study_planar_perspective.py [--cases flag:30:1:1.6,sheet:30:1:1.6]
        [--rounds 12] [--rank 2] [--json out.json]

Case = surface:camera motion (deg):amplitude:distance (m; 1.6 = a ~45 deg field of view, 4 the
sweep's ~19 deg).  Columns (metric B, per-frame Procrustes + scale, as bench_pipeline.py):
``persp step`` = ``perspective.perspective_solve`` of ``planar``; ``refined`` =
``planar_pinhole.refine_planar_pinhole`` of that (``--rounds``, heights of rank ``--rank``);
``true depths``: the stream on the tracks corrected by the true depths (bench_pipeline's
``--true-depths`` bound); ``px``: the pinhole reprojection error of each.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / 'bench'))

from bench_pipeline import true_depth_bound  # noqa: E402
from benchlib import parser, table  # noqa: E402
from nrsfm_ros.core.nrsfm import reconstruct  # noqa: E402
from nrsfm_ros.core.nrsfm.perspective import perspective_solve  # noqa: E402
from nrsfm_ros.core.nrsfm.planar_pinhole import refine_planar_pinhole  # noqa: E402
from nrsfm_ros.evaluation import score, shapes_as_clouds  # noqa: E402
from nrsfm_ros.io.synth import SynthConfig, generate  # noqa: E402


def run_case(case: str, rounds: int, rank: int, size: tuple[int, int] = (256, 192),
             frames: int = 60) -> dict:
    surface, motion, amp, dist = case.split(':')
    seq = generate(SynthConfig(surface=surface, width=size[0], height=size[1], frames=frames,
                               seed=0,
                               camera_motion_deg=float(motion), amplitude=float(amp),
                               distance=float(dist)))
    V = np.maximum(seq.V, 1e-3)
    f, c = float(seq.K[0, 0]), seq.K[:2, 2]

    def e3d(S: np.ndarray) -> float:
        return score(shapes_as_clouds(S, seq.track_ids), seq).summary()['e3d']

    def solve(W: np.ndarray, V: np.ndarray):
        return reconstruct(W, V, method='planar')
    step = perspective_solve(solve, seq.W, V, f, c, weak=solve(seq.W, V))
    t = time.perf_counter()
    ref = refine_planar_pinhole(step, seq.W, seq.V, f, c, rounds=rounds, rank=rank)
    return {'case': case, 'static': score(shapes_as_clouds(seq.S, seq.track_ids),
                                           seq).summary()['static'],
            'step': e3d(step.S), 'step_px': step.residual_px, 'refined': e3d(ref.S),
            'refined_px': ref.residual_px, 'refine_s': time.perf_counter() - t,
            'true_depths': true_depth_bound(seq)}


def main() -> None:
    p = parser(__doc__)
    p.add_argument('--cases', default='flag:30:1:1.6,sheet:30:1:1.6')
    p.add_argument('--rounds', type=int, default=12)
    p.add_argument('--rank', type=int, default=2)
    a = p.parse_args()
    rows = [run_case(case, a.rounds, a.rank) for case in a.cases.split(',')]
    table(['case (surface:deg:amp:m)', 'static', 'persp step', 'px', 'refined', 'px',
           'refined / step', 'true depths', 'refine s'],
          [[r['case'], f"{r['static']:.4f}", f"{r['step']:.4f}", f"{r['step_px']:.3f}",
            f"{r['refined']:.4f}", f"{r['refined_px']:.3f}", f"{r['refined'] / r['step']:.2f}",
            f"{r['true_depths']:.4f}", f"{r['refine_s']:.1f}"] for r in rows])
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == '__main__':
    main()
