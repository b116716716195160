"""The registrar on the pipeline (issue 15): does registration/transform beat doing nothing?

    .venv/bin/python bench/bench_registrar_pipeline.py [--surfaces flag,face] [--motions 12,30]
        [--amplitudes 1] [--frames 60] [--cache DIR] [--set name=value ...] [--json out.json]

Per case (``nrsfm-ros synth`` renders, seed 0), the rotation of registration/transform against
the true camera rotation from frame f to frame 0 (``evaluation.registration_errors``' measure:
the reference is frame 0's ground truth in its camera optical frame), median and p90 over the
frames, and the aligned RMSE (m, mean over frames) of registration/aligned to the frame-0 ground
truth, both nearest-neighbour (what ``nrsfm-ros evaluate`` reports) and by track id, for
- ``identity``: doing nothing (the clouds as they are);
- ``gt``: the registrar (shipped defaults, or ``--set``) on the ground-truth clouds S[f];
- ``pipe``: the registrar on the reconstructor's published clouds: ``process`` (tracker ->
  reconstructor, shipped defaults) on the rendered bag; the clouds are cached in ``--cache``
  (keyed by the case) so that registrar variants rerun in seconds;
- ``pipe identity``: the identity on the reconstructor's clouds (its RMSE).
The registrar is fed exactly the messages ``process`` feeds it (reference once, then one
nrsfm/points cloud per frame with its track ids), through ``RegistrarProcessor``.
"""
from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchlib import parser, table  # noqa: E402
from nrsfm_ros.core.metrics import rotation_error_deg  # noqa: E402
from nrsfm_ros.evaluation import read_clouds  # noqa: E402
from nrsfm_ros.io import pointcloud2 as pc2  # noqa: E402
from nrsfm_ros.io.msgtypes import RosbagsFactory  # noqa: E402
from nrsfm_ros.io.sequence_bag import write_sequence_bag  # noqa: E402
from nrsfm_ros.io.synth import SynthConfig, generate  # noqa: E402
from nrsfm_ros.params import RegistrarParams  # noqa: E402
from nrsfm_ros.pipeline import process_bag  # noqa: E402
from nrsfm_ros.processing import TOPICS, RegistrarProcessor, transform_matrix  # noqa: E402

FAC = RosbagsFactory()


def cloud_msg(X: np.ndarray, ids: np.ndarray, stamp: int) -> object:
    X = np.asarray(X, np.float32)
    return pc2.to_msg({'x': X[:, 0], 'y': X[:, 1], 'z': X[:, 2],
                       'track_id': np.asarray(ids, np.uint32)}, FAC, stamp,
                      'camera_optical_frame')


def true_rotations(seq) -> np.ndarray:
    """(F, 3, 3) rotation taking frame f's camera axes to frame 0's."""
    R = seq.T_camera_world[:, :3, :3]
    return R[0] @ np.transpose(R, (0, 2, 1))


def run_registrar(seq, clouds: dict, params: RegistrarParams) -> dict:
    """Feed the reference and ``clouds`` {f: (X, ids)} through a RegistrarProcessor; returns
    {f: (4x4 transform, aligned (n, 3), ids)} and the seconds per cloud."""
    proc = RegistrarProcessor(FAC, params)
    proc.handle('reference', cloud_msg(seq.S[0], seq.track_ids, int(seq.stamps_ns[0])))
    out = {}
    t = time.perf_counter()
    for f in sorted(clouds):
        X, ids = clouds[f]
        res = {topic: m for topic, _, m in
               proc.handle('points', cloud_msg(X, ids, int(seq.stamps_ns[f])))}
        if TOPICS['transform'] not in res:
            continue
        A = res[TOPICS['aligned']]
        out[f] = (transform_matrix(res[TOPICS['transform']]), pc2.read_xyz(A),
                  pc2.read_fields(A, ('track_id',), np.uint32)[:, 0])
    return {'frames': out, 's_per_cloud': (time.perf_counter() - t) / max(len(clouds), 1),
            'identity_kept': proc.identity_kept, 'errors': dict(proc.stats.errors)}


def errors(seq, frames: dict) -> dict:
    """Rotation error (deg) median / p90 and the aligned RMSEs of {f: (T, aligned, ids)}."""
    from scipy.spatial import cKDTree
    Rt = true_rotations(seq)
    tree = cKDTree(seq.S[0])
    col = {int(t): i for i, t in enumerate(seq.track_ids)}
    rot, nn, byid = [], [], []
    for f, (T, A, ids) in sorted(frames.items()):
        rot.append(rotation_error_deg(T[:3, :3], Rt[f]))
        ok = np.isfinite(A).all(axis=1)
        nn.append(float(np.sqrt(np.mean(tree.query(A[ok])[0] ** 2))))
        c = np.array([col.get(int(i), -1) for i in ids[ok]])
        keep = c >= 0
        byid.append(float(np.sqrt(np.mean(np.sum((A[ok][keep] - seq.S[0][c[keep]]) ** 2, 1)))))
    return {'rot_median': float(np.median(rot)), 'rot_p90': float(np.percentile(rot, 90)),
            'rmse_nn': float(np.mean(nn)), 'rmse_id': float(np.mean(byid)), 'frames': len(rot)}


def identity(clouds: dict) -> dict:
    return {f: (np.eye(4), X, ids) for f, (X, ids) in clouds.items()}


def pipeline_clouds(cfg: SynthConfig, seq, cache: Path) -> dict:
    """The reconstructor's published clouds of the rendered bag (shipped defaults), cached."""
    key = cache / (f'{cfg.surface}_{cfg.camera_motion_deg:g}_{cfg.amplitude:g}_'
                   f'{cfg.frames}_{cfg.width}x{cfg.height}.npz')
    if key.exists():
        z = np.load(key)
        return {int(k[1:]): (z[k], z['i' + k[1:]]) for k in z.files if k.startswith('X')}
    with tempfile.TemporaryDirectory() as tmp:
        write_sequence_bag(seq, Path(tmp) / 'in')
        process_bag(Path(tmp) / 'in', Path(tmp) / 'out', stages=['tracker', 'reconstructor'],
                    progress=False)
        clouds = read_clouds(Path(tmp) / 'out', seq.stamps_ns)
    clouds = {f: (X[np.isfinite(X).all(axis=1)], ids[np.isfinite(X).all(axis=1)])
              for f, (X, ids) in clouds.items()}
    cache.mkdir(parents=True, exist_ok=True)
    np.savez(key, **{f'X{f}': X for f, (X, _) in clouds.items()},
             **{f'i{f}': ids for f, (_, ids) in clouds.items()})
    return clouds


def run_case(cfg: SynthConfig, params: RegistrarParams, cache: Path) -> list[dict]:
    seq = generate(cfg)
    gt = {f: (seq.S[f], seq.track_ids) for f in range(seq.S.shape[0])}
    pipe = pipeline_clouds(cfg, seq, cache)
    case = f'{cfg.surface} {cfg.camera_motion_deg:g} deg amp {cfg.amplitude:g}'
    rows = [{'case': case, 'row': 'identity', **errors(seq, identity(gt))}]
    for name, clouds in (('gt', gt), ('pipe', pipe)):
        r = run_registrar(seq, clouds, params)
        rows.append({'case': case, 'row': name, **errors(seq, r['frames']),
                     'ms': 1e3 * r['s_per_cloud'], 'identity_kept': r['identity_kept'],
                     'errors': r['errors']})
    rows.append({'case': case, 'row': 'pipe identity', **errors(seq, identity(pipe))})
    return rows


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument('--surfaces', default='flag,face')
    ap.add_argument('--motions', default='12,30')
    ap.add_argument('--amplitudes', default='1')
    ap.add_argument('--frames', type=int, default=60)
    ap.add_argument('--cache', default=str(Path(tempfile.gettempdir()) / 'nrsfm_registrar_bench'))
    ap.add_argument('--set', nargs='*', default=[], metavar='NAME=VALUE',
                    help='registrar parameters (as on the node, YAML values)')
    a = ap.parse_args()
    import yaml
    params = RegistrarParams().updated({k: yaml.safe_load(v) for k, v in
                                        (s.split('=', 1) for s in a.set)})
    rows = []
    for surface in a.surfaces.split(','):
        for motion in (float(m) for m in a.motions.split(',')):
            for amp in (float(x) for x in a.amplitudes.split(',')):
                cfg = SynthConfig(surface=surface, camera_motion_deg=motion, amplitude=amp,
                                  frames=a.frames)
                rows += run_case(cfg, params, Path(a.cache))
    table(['case', 'row', 'rot median (deg)', 'rot p90 (deg)', 'RMSE nn (m)', 'RMSE by id (m)',
           'ms/cloud', 'identity kept'],
          [(r['case'], r['row'], f"{r['rot_median']:.2f}", f"{r['rot_p90']:.2f}",
            f"{r['rmse_nn']:.4f}", f"{r['rmse_id']:.4f}",
            f"{r['ms']:.0f}" if 'ms' in r else '', r.get('identity_kept', ''))
           for r in rows])
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == '__main__':
    main()
