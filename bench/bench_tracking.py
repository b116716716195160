"""Tracking benchmark (issue 5): data-step EPE on Middlebury, dense track error on generated
deforming sequences (with and without an occluder), and streaming time per frame against
resolution.

    .venv/bin/python bench/bench_tracking.py [--seeds 5] [--frames 60] [--json out.json]

Sequences: nrsfm_ros.io.synth_tracks (320x256, textured, smooth non-rigid motion up to ~60 px,
mild illumination change, sigma=2 noise; the occluder crosses the view in 15 frames).  Errors are
mean endpoint distances to the true track positions over frames 1.. and all in-view points
('all'), the visible ones, and the ones under the occluder.  Methods, in the same run:
- chain: DIS-medium frame-to-frame, chained (what the issue warns against);
- anchor: DIS-medium reference-to-frame seeded by the previous frame (ReferenceFlowTracker);
- mfof stream: MFOFTracker, what the tracker node publishes per frame;
- mfof batch: track_sequence (streaming + two-sided subspace pass), what `nrsfm-ros track` writes.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from nrsfm_ros.core.tracking import (PRESETS, MFOFConfig, MFOFTracker,  # noqa: E402
                                     ReferenceFlowTracker, track_sequence)
from nrsfm_ros.io.flo import endpoint_error, read_flo  # noqa: E402
from nrsfm_ros.io.synth_tracks import DeformConfig, generate_deforming  # noqa: E402

MIDDLEBURY = ROOT.parent / 'shared' / 'data' / 'flow' / 'middlebury'


def middlebury() -> list[dict]:
    seqs = sorted(p for p in MIDDLEBURY.iterdir() if (p / 'flow10.flo').exists())
    pairs = [(cv2.imread(str(s / 'frame10.png'), cv2.IMREAD_GRAYSCALE),
              cv2.imread(str(s / 'frame11.png'), cv2.IMREAD_GRAYSCALE),
              read_flo(s / 'flow10.flo')) for s in seqs]

    def farneback(a, b):
        return cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 5, 15, 5, 7, 1.5, 0)

    methods = {f'DIS-{name}': cv2.DISOpticalFlow_create(p).calc for name, p in PRESETS.items()}
    rows = []
    for name, fn in [*methods.items(), ('Farneback', farneback)]:
        epe, ms = [], []
        for a, b, gt in pairs:
            args = (a, b, None) if name.startswith('DIS') else (a, b)
            fn(*args)                                   # warm-up
            t = time.perf_counter()
            flow = fn(*args)
            ms.append((time.perf_counter() - t) * 1e3)
            epe.append(endpoint_error(flow, gt))
        rows.append({'method': name, 'epe': float(np.mean(epe)), 'ms': float(np.mean(ms)),
                     'pairs': len(pairs)})
    return rows


def errors(W: np.ndarray, seq) -> dict:
    h, w = seq.config.height, seq.config.width
    e = np.hypot(W[0::2] - seq.W[0::2], W[1::2] - seq.W[1::2])
    x, y = seq.W[0::2], seq.W[1::2]
    inview = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    occ = seq.occluded & inview
    return {'all': float(e[1:][inview[1:]].mean()), 'visible': float(e[1:][seq.V[1:]].mean()),
            'occluded': float(e[occ].mean()) if occ.any() else float('nan'),
            'last_frame': float(e[-1][inview[-1]].mean())}


def chain(images) -> np.ndarray:
    dis = cv2.DISOpticalFlow_create(PRESETS['medium'])
    h, w = images[0].shape
    ys, xs = np.mgrid[0:h, 0:w]
    pos = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float32)
    out = [pos.copy()]
    for a, b in zip(images[:-1], images[1:]):
        flow = dis.calc(a, b, None)
        pos = pos + np.stack([cv2.remap(flow[..., k], pos[:, 0].reshape(h, w),
                                        pos[:, 1].reshape(h, w), cv2.INTER_LINEAR,
                                        borderMode=cv2.BORDER_REPLICATE).ravel()
                              for k in range(2)], 1)
        out.append(pos.copy())
    return np.concatenate([p.T for p in out])


def sequences(seeds: int, frames: int) -> list[dict]:
    rows = []
    for occluder in (0, 15):
        for seed in range(seeds):
            seq = generate_deforming(DeformConfig(frames=frames, seed=seed,
                                                  occluder_frames=occluder))
            F = frames
            runs = {}
            t = time.perf_counter()
            runs['chain'] = (chain(seq.images), time.perf_counter() - t)
            t = time.perf_counter()
            tr = ReferenceFlowTracker(stride=1, mask='full')
            W = np.concatenate([tr.step(im).uv.T for im in seq.images])
            runs['anchor'] = (W, time.perf_counter() - t)
            r = track_sequence(seq.images, MFOFConfig(stride=1, mask='full'), smooth=False)
            runs['mfof stream'] = (r.W, r.seconds)
            r = track_sequence(seq.images, MFOFConfig(stride=1, mask='full'), smooth=True)
            runs['mfof batch'] = (r.W, r.seconds)
            for name, (W, sec) in runs.items():
                rows.append({'occluder_frames': occluder, 'seed': seed, 'method': name,
                             'ms_per_frame': sec / F * 1e3, **errors(W, seq)})
            print(f'  occluder {occluder} seed {seed}: ' + ', '.join(
                f"{r['method']} {r['all']:.2f}/{r['occluded']:.2f}" for r in rows[-4:]),
                file=sys.stderr)
    return rows


def speed(frames: int = 30) -> list[dict]:
    rows = []
    for w, h in ((160, 128), (320, 256), (640, 480)):
        seq = generate_deforming(DeformConfig(width=w, height=h, frames=frames,
                                              max_motion_px=60 * w / 320))
        dense = MFOFConfig(stride=1, mask='full')      # every pixel, as the anchor
        for name, make in (('mfof stream', lambda: MFOFTracker(dense)),
                           ('anchor', lambda: ReferenceFlowTracker(stride=1, mask='full'))):
            tr = make()
            tr.step(seq.images[0])
            ts = []
            for im in seq.images[1:]:
                t = time.perf_counter()
                tr.step(im)
                ts.append((time.perf_counter() - t) * 1e3)
            ts = np.array(ts)
            rows.append({'size': f'{w}x{h}', 'method': name, 'ms_mean': float(ts.mean()),
                         'ms_p95': float(np.percentile(ts, 95)), 'fps': 1e3 / float(ts.mean())})
    return rows


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--seeds', type=int, default=5)
    p.add_argument('--frames', type=int, default=60)
    p.add_argument('--json', default=None)
    args = p.parse_args()
    cv2.setNumThreads(2)
    mb = middlebury()
    print('| data step (Middlebury, 8 pairs) | mean EPE (px) | ms / pair |')
    print('|---|---|---|')
    for r in mb:
        print(f"| {r['method']} | {r['epe']:.3f} | {r['ms']:.1f} |")
    seq_rows = sequences(args.seeds, args.frames)
    print()
    print(f'| sequence (320x256, {args.frames} frames, {args.seeds} seeds) | method | all (px) '
          '| visible (px) | occluded (px) | last frame (px) | all vs anchor | ms / frame |')
    print('|---|---|---|---|---|---|---|---|')
    for occ in (0, 15):
        sub = [r for r in seq_rows if r['occluder_frames'] == occ]
        anchor = np.mean([r['all'] for r in sub if r['method'] == 'anchor'])
        for m in ('chain', 'anchor', 'mfof stream', 'mfof batch'):
            rs = [r for r in sub if r['method'] == m]
            a = np.mean([r['all'] for r in rs])
            o = (f"{np.mean([r['occluded'] for r in rs]):.2f} "
                 f"(worst {np.max([r['occluded'] for r in rs]):.2f})" if occ else '-')
            label = f'occluder over {occ} frames' if occ else 'deforming, no occluder'
            print(f"| {label} | {m} | {a:.3f} | {np.mean([r['visible'] for r in rs]):.3f} | "
                  f"{o} | {np.mean([r['last_frame'] for r in rs]):.2f} | {a / anchor:.2f} | "
                  f"{np.mean([r['ms_per_frame'] for r in rs]):.1f} |")
    sp = speed()
    print()
    print('| streaming, 2 cores | method | ms / frame (mean) | p95 | frames / s |')
    print('|---|---|---|---|---|')
    for r in sp:
        print(f"| {r['size']} | {r['method']} | {r['ms_mean']:.1f} | {r['ms_p95']:.1f} | "
              f"{r['fps']:.1f} |")
    if args.json:
        Path(args.json).write_text(json.dumps({'middlebury': mb, 'sequences': seq_rows,
                                               'speed': sp}, indent=1))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
