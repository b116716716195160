"""HDM-Net (issue 18): single-image e3D of the shipped model on fresh renders, per held-out
texture and illumination, against the rest shape and flat baselines, and on the frames of
``nrsfm-ros synth`` sequences of the same sheet against the NRSfM methods on those frames.

    .venv/bin/python bench/bench_hdmnet.py [--model nrsfm_ros/models/hdmnet.onnx]
        [--samples 200] [--seed 1] [--cases sheet:1,sheet:2,flag:1] [--motion 30]
        [--frames 60] [--methods rigid,lowrank,planar,bmm,stream] [--threads 2] [--json out.json]

Metric B (per-frame Procrustes + scale, mean over frames: ``core.metrics``, as
bench/bench_pipeline.py).  Part 1: ``synth_hdmnet`` renders (seed ``--seed``; the shipped
model's own metrics used seed 0) of the test split (held-out states; seen texture families,
unseen instances), the held-out texture family and the held-out lights; baselines: the rest
shape (the flat sheet) and the ground truth flattened onto its own plane (an oracle).  Part 2:
``synth.generate`` sequences (256 x 192, camera yaw +-``--motion`` deg, seed 0): HDM-Net on
each frame alone (with the sequence's K), sampled at the tracked points' material coordinates,
scored with the pipeline benchmark's ``score`` on exactly the points the NRSfM methods
reconstruct from the ground-truth tracks (perfect tracks: their best case); ``stream`` is
the reconstructor's own default (``evaluation.stream_on_tracks``: the stream fed the
ground-truth tracks frame by frame with the camera's K, as the pipeline benchmark's
``default (GT)``: the planar model refined under the pinhole camera where it is chosen), the
other methods ``core.nrsfm.reconstruct`` on the whole sequence.  Per-frame ms:
median of ``HDMNetModel.predict`` (network, and network + pre/post-processing) with
``--threads`` ONNX Runtime threads.
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
from nrsfm_ros.core import hdmnet as H  # noqa: E402
from nrsfm_ros.core.metrics import flat_shape  # noqa: E402
from nrsfm_ros.core.nrsfm import reconstruct  # noqa: E402
from nrsfm_ros.evaluation import score, shapes_as_clouds, stream_on_tracks  # noqa: E402
from nrsfm_ros.io import synth  # noqa: E402
from nrsfm_ros.io import synth_hdmnet as D  # noqa: E402
from nrsfm_ros.io.hdmnet_model import HDMNetModel  # noqa: E402

GT_KW = {'lowrank': {'rank': 3}}


def single_image(model: HDMNetModel, samples: int, seed: int) -> tuple[list, dict]:
    rows, times = [], {'infer': [], 'total': []}
    K = D.canonical_K()
    for split in ('test', 'heldout-texture', 'heldout-light'):
        d = D.make_dataset(D.HDMDataConfig(split=split, samples=samples, seed=seed,
                                           stored=H.INPUT_SIZE))
        G = d['grids'].reshape(samples, -1, 3)
        P = []
        for im in d['images']:
            r = model.predict(im, K)
            P.append(r.points)
            times['infer'].append(r.infer_ms)
            times['total'].append(r.total_ms)
        e = H.e3d_per_frame(np.stack(P).reshape(G.shape), G)
        rest = H.e3d_per_frame(np.broadcast_to(D.rest_grid().reshape(1, -1, 3), G.shape), G)
        flat = H.e3d_per_frame(np.stack([flat_shape(g) for g in G]), G)
        groups = [('all', np.ones(samples, bool))]
        groups += [(f'texture {D.TEXTURES[i]}', d['texture'] == i)
                   for i in np.unique(d['texture'])]
        groups += [(f'light {list(D.LIGHTS)[i]}', d['light'] == i)
                   for i in np.unique(d['light'])]
        for name, m in groups:
            rows.append({'split': split, 'group': name, 'n': int(m.sum()),
                         'hdmnet': float(e[m].mean()), 'rest': float(rest[m].mean()),
                         'flat': float(flat[m].mean())})
    return rows, times


def track_material_coords(cfg: synth.SynthConfig, seq: synth.SynthSequence) -> np.ndarray:
    """(P, 2) material coordinates (s, t) of the sequence's tracks: frame 0 re-rendered as
    ``synth.generate`` renders it, read at the reference pixels."""
    rng = np.random.default_rng(cfg.seed)
    synth._texture(rng)
    phase = rng.uniform(0, 2 * np.pi, 3)
    poses = synth._camera_poses(cfg, rng)
    n_s = max(40, cfg.width // 3)
    s, t, tris = synth._grid_mesh(cfg.surface, n_s, int(n_s * 0.75))
    Xw = synth._surface(cfg.surface, s, t, synth.deformation_time(0, cfg.fps), cfg.amplitude,
                        phase)
    Xc = Xw @ poses[0, :3, :3].T + poses[0, :3, 3]
    _, att = synth.rasterise(synth._project(seq.K, Xc), Xc[:, 2], np.stack([s, t], 1), tris,
                             cfg.width, cfg.height)
    ys, xs = np.divmod(seq.track_ids.astype(np.int64), cfg.width)
    st = att[ys, xs]
    chk = synth._surface(cfg.surface, st[:, 0], st[:, 1], 0.0, cfg.amplitude, phase)
    assert np.allclose(chk, seq.S_world[0], atol=1e-6), 'material coordinates disagree'
    return st


def sequence_case(model: HDMNetModel, surface: str, amp: float, motion: float, frames: int,
                  methods: list[str]) -> dict:
    cfg = synth.SynthConfig(surface=surface, amplitude=amp, camera_motion_deg=motion,
                            frames=frames, seed=0)
    seq = synth.generate(cfg)
    st = track_material_coords(cfg, seq)
    clouds, ms = {}, []
    for f in range(frames):
        r = model.predict(seq.images[f], seq.K)
        clouds[f] = (H.sample_grid(r.points, st[:, 0], st[:, 1]), seq.track_ids)
        ms.append(r.total_ms)
    s = score(clouds, seq).summary()
    row = {'surface': surface, 'amp': amp, 'motion_deg': motion, 'frames': frames,
           'points': int(seq.track_ids.size), 'hdmnet': s['e3d'], 'static': s['static'],
           'flat': s['flat'], 'ms': float(np.median(ms))}
    rest = {f: (H.sample_grid(D.rest_grid(), st[:, 0], st[:, 1]), seq.track_ids)
            for f in range(frames)}
    row['rest'] = score(rest, seq).summary()['e3d']
    V = np.maximum(seq.V, 1e-3)
    for m in methods:
        try:
            if m == 'stream':           # the reconstructor's default, fed the perfect tracks
                clouds = stream_on_tracks(seq.W, seq.V, seq.track_ids, seq.K)
            else:
                res = reconstruct(seq.W, V, method=m, **GT_KW.get(m, {}))
                clouds = shapes_as_clouds(res.S, seq.track_ids)
            row[m] = score(clouds, seq).summary()['e3d']
        except Exception as err:  # noqa: BLE001 -- a method that fails is a result
            row[m] = float('nan')
            row[f'{m}_error'] = str(err)
    finite = [row[m] for m in methods if np.isfinite(row[m])]
    row['best_nrsfm'] = min(finite) if finite else float('nan')
    row['ratio'] = row['hdmnet'] / row['best_nrsfm']
    return row


def main() -> None:
    p = parser(__doc__)
    p.add_argument('--model', default=None)
    p.add_argument('--samples', type=int, default=200)
    p.add_argument('--seed', type=int, default=1)
    p.add_argument('--cases', default='sheet:1,sheet:2,flag:1')
    p.add_argument('--motion', type=float, default=30.0)
    p.add_argument('--frames', type=int, default=60)
    p.add_argument('--methods', default='rigid,lowrank,planar,bmm,stream')
    p.add_argument('--threads', type=int, default=2)
    a = p.parse_args()
    model = HDMNetModel(a.model, threads=a.threads)
    t0 = time.perf_counter()
    rows, times = single_image(model, a.samples, a.seed)
    print(f'## single images ({a.samples} per split, seed {a.seed}; '
          f'{time.perf_counter() - t0:.0f} s)\n')
    table(['split', 'group', 'n', 'HDM-Net', 'rest shape', 'flat (oracle)', 'HDM-Net/rest'],
          [[r['split'], r['group'], r['n'], f"{r['hdmnet']:.4f}", f"{r['rest']:.4f}",
            f"{r['flat']:.4f}", f"{r['hdmnet'] / r['rest']:.2f}"] for r in rows])
    tm = {k: float(np.median(v)) for k, v in times.items()}
    print(f"\nper frame ({a.threads} threads): network {tm['infer']:.2f} ms, with pre/post-"
          f"processing {tm['total']:.2f} ms (median of {len(times['infer'])})\n")
    methods = [m for m in a.methods.split(',') if m]
    seq_rows = []
    for case in a.cases.split(','):
        surface, amp = case.split(':')
        seq_rows.append(sequence_case(model, surface, float(amp), a.motion, a.frames, methods))
        print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v)
                          for k, v in seq_rows[-1].items()}), file=sys.stderr)
    print(f'## synth sequences (256x192, yaw +-{a.motion:g} deg, {a.frames} frames; NRSfM on '
          'ground-truth tracks)\n')
    table(['surface', 'amp', 'points', 'HDM-Net', 'rest', 'static', 'flat']
          + [f'{m}(GT)' for m in methods] + ['HDM-Net/best NRSfM', 'ms/frame'],
          [[r['surface'], f"{r['amp']:g}", r['points'], f"{r['hdmnet']:.4f}",
            f"{r['rest']:.4f}", f"{r['static']:.4f}", f"{r['flat']:.4f}"]
           + [f'{r[m]:.4f}' for m in methods] + [f"{r['ratio']:.2f}", f"{r['ms']:.1f}"]
           for r in seq_rows])
    if a.json:
        Path(a.json).write_text(json.dumps({'single': rows, 'times_ms': tm,
                                            'sequences': seq_rows}, indent=1))


if __name__ == '__main__':
    main()
