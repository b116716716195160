"""Tracker accuracy under viewpoint change (issue 12): the streaming tracker, as the tracker node
runs it (``TrackerParams`` defaults -> ``MFOFTracker``), on rendered ``synth`` sequences.

    .venv/bin/python bench/bench_tracker_views.py [--surfaces face,sphere,flag]
        [--motions 12,30,60] [--amplitudes 1] [--size 256x192] [--frames 60]
        [--methods mfof,chain] [--distance M]
        [--set recapture_margin=0 ...] [--json out.json]

Per case (seed 0) and method, over the first reference's track ids (= ground-truth ids, y*W+x):
- err: mean / median distance (px) to the ground-truth track on ground-truth-visible points
  (frames 1..), and the mean per third of the sequence (frame bands);
- kept: the fraction of ground-truth-visible (point, frame) pairs the tracker calls visible
  (> 1/2);
- rigid/static: e3D (per-frame Procrustes + scale) of the rigid factorisation on the tracker's
  tracks over the static oracle's, next to the same ratio on the ground-truth tracks;
- ms / frame of the streaming step.
Methods: ``mfof`` (the node's tracker; ``--set`` overrides MFOFConfig fields, e.g.
``recapture_margin=0`` for the tracker before issue 12), ``chain`` (DIS-medium frame to frame,
chained; a naive baseline).
"""
from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchlib import parser, table  # noqa: E402
from nrsfm_ros.core.nrsfm import reconstruct  # noqa: E402
from nrsfm_ros.core.tracking import MFOFTracker, PRESETS  # noqa: E402
from nrsfm_ros.evaluation import score, shapes_as_clouds  # noqa: E402
from nrsfm_ros.io.synth import SynthConfig, generate  # noqa: E402
from nrsfm_ros.params import TrackerParams  # noqa: E402


def grey_frames(seq) -> list[np.ndarray]:
    return [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in seq.images]


def run_mfof(frames: list[np.ndarray], overrides: dict | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, int]:
    """Stream the frames through the node's tracker (MFOFConfig ``overrides``); tracks of the
    first reference's ids: W (2F, P), V (F, P) (0 where an id is no longer carried), ids (P,),
    ms / frame, number of re-selections."""
    tr = MFOFTracker(dataclasses.replace(TrackerParams().mfof_config(), **(overrides or {})))
    out, ts = [], []
    for im in frames:
        t = time.perf_counter()
        out.append(tr.step(im))
        ts.append(time.perf_counter() - t)
    ids = out[0].ids
    F, P = len(out), ids.size
    W = np.zeros((2 * F, P), np.float32)
    V = np.zeros((F, P), np.float32)
    order = np.argsort(ids)
    uv = out[0].uv.copy()
    for f, fr in enumerate(out):
        pos = np.clip(np.searchsorted(ids, fr.ids, sorter=order), 0, P - 1)
        j = order[pos]
        hit = ids[j] == fr.ids
        uv = uv.copy()
        uv[j[hit]] = fr.uv[hit]
        V[f, j[hit]] = fr.visibility[hit]
        W[2 * f], W[2 * f + 1] = uv[:, 0], uv[:, 1]
    return W, V, ids, 1e3 * float(np.mean(ts[1:])), sum(fr.reselected for fr in out[1:])


def run_chain(frames: list[np.ndarray], ids: np.ndarray, width: int
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, int]:
    """DIS-medium frame-to-frame flow, chained at the track positions (naive baseline)."""
    dis = cv2.DISOpticalFlow_create(PRESETS['medium'])
    xy = np.stack([ids % width, ids // width], 1).astype(np.float32)
    pos, out, ts = xy.copy(), [xy.copy()], []
    for a, b in zip(frames[:-1], frames[1:]):
        t = time.perf_counter()
        flow = dis.calc(a, b, None)
        p = pos.reshape(1, -1, 2)
        pos = pos + cv2.remap(flow, p[..., 0], p[..., 1], cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_REPLICATE).reshape(-1, 2)
        ts.append(time.perf_counter() - t)
        out.append(pos.copy())
    W = np.concatenate([p.T for p in out]).astype(np.float32)
    return W, np.ones((len(frames), ids.size), np.float32), ids, 1e3 * float(np.mean(ts)), 0


def rigid_ratio(W: np.ndarray, V: np.ndarray, ids: np.ndarray, seq) -> float:
    res = reconstruct(W.astype(np.float64), np.maximum(V, 1e-3).astype(np.float64),
                      method='rigid')
    s = score(shapes_as_clouds(res.S, ids), seq).summary()
    return s['e3d'] / s['static']


def evaluate(W: np.ndarray, V: np.ndarray, ids: np.ndarray, seq) -> dict:
    """Track errors of the tracker's (W, V, ids) against the sequence's ground truth."""
    gpos = {int(i): k for k, i in enumerate(seq.track_ids)}
    both = np.array([int(i) in gpos for i in ids])
    cols = np.array([gpos[int(i)] for i in ids[both]])
    W, V, ids = W[:, both], V[:, both], ids[both]
    Wg, Vg = seq.W[:, cols], seq.V[:, cols] > 0.5
    F = V.shape[0]
    e = np.hypot(W[0::2] - Wg[0::2], W[1::2] - Wg[1::2])
    vis = Vg.copy()
    vis[0] = False
    bands = np.array_split(np.arange(1, F), 3)
    row = {'points': int(ids.size),
           'err_mean': float(e[vis].mean()), 'err_median': float(np.median(e[vis])),
           'err_p90': float(np.percentile(e[vis], 90)),
           'err_bands': [float(e[b][vis[b]].mean()) for b in bands],
           'err_kept': float(e[vis & (V > 0.5)].mean()) if (vis & (V > 0.5)).any() else np.nan,
           'kept': float((V[vis] > 0.5).mean()),
           'rigid_static': rigid_ratio(W, V, ids, seq)}
    return row


def run_case(cfg: SynthConfig, methods: list[str], overrides: dict | None = None
             ) -> list[dict]:
    seq = generate(cfg)
    frames = grey_frames(seq)
    gt = {'rigid_static_gt': rigid_ratio(seq.W, seq.V, seq.track_ids, seq)}
    rows = []
    ids0 = None
    for m in methods:
        if m == 'mfof':
            W, V, ids, ms, nres = run_mfof(frames, overrides)
            ids0 = ids
        elif m == 'chain':
            W, V, ids, ms, nres = run_chain(frames, seq.track_ids if ids0 is None else ids0,
                                            cfg.width)
        else:
            raise ValueError(f'method {m!r}: expected mfof or chain')
        rows.append({'surface': cfg.surface, 'motion_deg': cfg.camera_motion_deg,
                     'amplitude': cfg.amplitude, 'method': m,
                     'ms_per_frame': ms, 'reselections': int(nres), **gt,
                     **evaluate(W, V, ids, seq)})
        print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v)
                          for k, v in rows[-1].items()}), file=sys.stderr)
    return rows


def main() -> None:
    p = parser(__doc__)
    p.add_argument('--surfaces', default='face,sphere,flag')
    p.add_argument('--motions', default='12,30,60')
    p.add_argument('--amplitudes', default='1',
                   help='deformation amplitude multipliers (SynthConfig.amplitude)')
    p.add_argument('--size', default='256x192')
    p.add_argument('--frames', type=int, default=60)
    p.add_argument('--distance', type=float, default=4.0,
                   help='camera distance in metres (the focal length keeps the surface\'s '
                   'image size: 4 = ~19 deg field of view, 1.6 = ~45 deg)')
    p.add_argument('--methods', default='mfof,chain')
    p.add_argument('--set', nargs='*', default=[], metavar='FIELD=VALUE',
                   help='MFOFConfig overrides of the mfof method')
    a = p.parse_args()
    base = TrackerParams().mfof_config()
    overrides = {}
    for kv in a.set:
        k, _, v = kv.partition('=')
        if not hasattr(base, k):
            p.error(f'--set {kv}: MFOFConfig has no field {k!r}')
        kind = type(getattr(base, k))
        overrides[k] = (v.lower() in ('1', 'true', 'yes')) if kind is bool else kind(v)
    cv2.setNumThreads(1)
    w, h = (int(v) for v in a.size.split('x'))
    rows = []
    for surface in a.surfaces.split(','):
        for motion in (float(v) for v in a.motions.split(',')):
            for amp in (float(v) for v in a.amplitudes.split(',')):
                cfg = SynthConfig(surface=surface, width=w, height=h, frames=a.frames, seed=0,
                                  camera_motion_deg=motion, amplitude=amp, distance=a.distance)
                rows += run_case(cfg, a.methods.split(','), overrides)
    table(['surface', 'cam deg', 'amp', 'method', 'err mean (px)', 'median', 'p90',
           'bands 1/3, 2/3, 3/3', 'err kept', 'kept', 'rigid/static', 'rigid/static (GT)',
           'reselections', 'ms / frame'],
          [[r['surface'], f"{r['motion_deg']:g}", f"{r['amplitude']:g}", r['method'],
            f"{r['err_mean']:.2f}",
            f"{r['err_median']:.2f}", f"{r['err_p90']:.2f}",
            ', '.join(f'{v:.2f}' for v in r['err_bands']), f"{r['err_kept']:.2f}",
            f"{r['kept']:.3f}", f"{r['rigid_static']:.2f}", f"{r['rigid_static_gt']:.2f}",
            r['reselections'], f"{r['ms_per_frame']:.1f}"] for r in rows])
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == '__main__':
    main()
