"""Per-frame processing latency of the tracker and of each reconstructor mode (issue 12 target:
<= 50 ms per frame after start-up at 320x240 on 2 cores).

    .venv/bin/python bench/bench_latency.py [--size 320x240] [--frames 40]
        [--modes window,online,batch] [--downsample 1,2] [--json out.json]
    .venv/bin/python bench/bench_latency.py --frames 100 --modes dspr,spva

A 30 deg flag render is fed frame by frame through the nodes' processors (no DDS): the tracker,
then the reconstructor in every mode on the tracker's tracks.  'After start-up' excludes the
frames before the first window is full; `batch` publishes nothing until its batch is full (60
frames by default), so its per-frame cost is buffering only and its solve is the batch row of
bench_pipeline.py.  `dspr` and `spva` solve their first batch too, then every frame alone
against the prior built from it (issue 13 target: <= 20 ms a frame at 10k points): their rows
are the frames after the first batch (``--frames`` above 61).  ``--modes ''``: the tracker
alone.  Next to the wall time (median, p95), the mean CPU time of the process per frame
(``time.process_time``: every thread, not inflated by other work on the machine as the wall
time is) and the frames per second of both.
``--downsample 1,2``: a tracker row per value of the tracker's ``downsample`` (the reconstructor
rows take the tracks of the first).
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
from nrsfm_ros.io import image as img_io  # noqa: E402
from nrsfm_ros.io.msgtypes import RosbagsFactory  # noqa: E402
from nrsfm_ros.io.synth import SynthConfig, generate  # noqa: E402
from nrsfm_ros.params import ReconstructorParams, TrackerParams  # noqa: E402
from nrsfm_ros.processing import ReconstructorProcessor, TrackerProcessor  # noqa: E402

MODES = ('window', 'online', 'batch', 'dspr', 'spva')
DEFAULT_MODES = ('window', 'online', 'batch')
PRIOR_MODES = ('dspr', 'spva')          # per-frame steps after their first batch


def main() -> None:
    p = parser(__doc__)
    p.add_argument('--size', default='320x240')
    p.add_argument('--frames', type=int, default=40)
    p.add_argument('--modes', default=','.join(DEFAULT_MODES),
                   help="reconstructor modes after the tracker, comma-separated ('': none)")
    p.add_argument('--downsample', default='1',
                   help="the tracker's downsample values, comma-separated (a row each)")
    a = p.parse_args()
    modes = [m for m in a.modes.split(',') if m]
    factors = [int(v) for v in a.downsample.split(',') if v]
    for m in modes:
        if m not in MODES:
            p.error(f'--modes: {m!r} is not one of {", ".join(MODES)}')
    batch = ReconstructorParams().batch_frames
    if any(m in PRIOR_MODES for m in modes) and a.frames <= batch + 1:
        p.error(f'--modes {a.modes}: dspr and spva step frame by frame after their first batch '
                f'of {batch} frames: use --frames {batch + 30} or more')
    w, h = (int(v) for v in a.size.split('x'))
    fac = RosbagsFactory()
    seq = generate(SynthConfig(surface='flag', width=w, height=h, frames=a.frames,
                               camera_motion_deg=30))
    trackers = {('tracker' if n == 1 else f'tracker downsample {n}'):
                TrackerProcessor(fac, TrackerParams(downsample=n)) for n in factors}
    recs = {m: ReconstructorProcessor(fac, ReconstructorParams(mode=m)) for m in modes}
    info = img_io.make_camera_info(seq.K, w, h, fac, int(seq.stamps_ns[0]), 'cam')
    for r in recs.values():
        r.handle('camera_info', info)
    ms: dict[str, list[float]] = {**{k: [] for k in trackers}, **{m: [] for m in modes}}
    cpu: dict[str, list[float]] = {k: [] for k in ms}
    for f in range(a.frames):
        msg = img_io.array_to_image(seq.images[f], 'rgb8', fac, int(seq.stamps_ns[f]), 'cam')
        tracks = None
        for k, tracker in trackers.items():
            t, c = time.perf_counter(), time.process_time()
            out = tracker.handle('image', msg)
            ms[k].append(1e3 * (time.perf_counter() - t))
            cpu[k].append(1e3 * (time.process_time() - c))
            if tracks is None:
                tracks = next(o[2] for o in out if o[0] == 'nrsfm/tracks')
        for m, r in recs.items():
            t, c = time.perf_counter(), time.process_time()
            r.handle('tracks', tracks)
            ms[m].append(1e3 * (time.perf_counter() - t))
            cpu[m].append(1e3 * (time.process_time() - c))
    start = ReconstructorParams().window + 1
    rows = []
    for name, v in ms.items():
        first = 1 if name in trackers else batch + 1 if name in PRIOR_MODES else start
        after, after_cpu = np.array(v[first:]), np.array(cpu[name][first:])
        rows.append({'stage': name if name in trackers else f'reconstructor {name}',
                     'median_ms': float(np.median(after)),
                     'p95_ms': float(np.percentile(after, 95)),
                     'max_ms': float(max(v)),
                     'cpu_mean_ms': float(after_cpu.mean()),
                     'fps_wall': 1e3 / float(after.mean()),
                     'fps_cpu': 1e3 / max(float(after_cpu.mean()), 1e-9)})
    table(['stage', 'median ms/frame', 'p95', 'max over the stream', 'CPU ms/frame (mean)',
           'frames/s (wall)', 'frames/s (CPU)'],
          [[r['stage'], f"{r['median_ms']:.1f}", f"{r['p95_ms']:.1f}", f"{r['max_ms']:.0f}",
            f"{r['cpu_mean_ms']:.1f}", f"{r['fps_wall']:.1f}", f"{r['fps_cpu']:.1f}"]
           for r in rows])
    print(f'load average {os.getloadavg()[0]:.2f}')
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == '__main__':
    main()
