"""Throughput of ``nrsfm-ros process BAG ... --jobs N`` against ``--jobs 1``.

    .venv/bin/python bench/bench_fleet.py [--bags 4] [--size 128x96] [--frames 20]
                                          [--jobs 1,2] [--repeat 2] [--json out.json]

Writes ``--bags`` synthetic bags (flag surface, seeds 0.., in a temporary folder), then runs
``fleet.process_bags`` over all of them (the full four-stage pipeline, default parameters) for
each ``--jobs`` value, ``--repeat`` times in alternating order so that both settings see the
same machine load.  Reports wall time (median and every run), frames/s and the ratio to the
first ``--jobs`` value.  Wall time includes starting the spawned workers (about a second each:
imports), which is part of what a user waits for.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from nrsfm_ros.fleet import process_bags  # noqa: E402
from nrsfm_ros.io.sequence_bag import write_sequence_bag  # noqa: E402
from nrsfm_ros.io.synth import SynthConfig, generate  # noqa: E402
from nrsfm_ros.pipeline import STAGES  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--bags', type=int, default=4)
    p.add_argument('--size', default='128x96')
    p.add_argument('--frames', type=int, default=20)
    p.add_argument('--jobs', default='1,2')
    p.add_argument('--repeat', type=int, default=2)
    p.add_argument('--threads', type=int, default=None,
                   help='native threads per worker for every --jobs value (default: the '
                   'fleet default, 1); also sets OMP/OPENBLAS/MKL_NUM_THREADS')
    p.add_argument('--json', default=None)
    args = p.parse_args()
    w, h = (int(v) for v in args.size.split('x'))
    jobs = [int(j) for j in args.jobs.split(',')]
    if args.threads is not None:
        for v in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
            os.environ[v] = str(args.threads)
    with tempfile.TemporaryDirectory(prefix='bench_fleet_') as tmp:
        d = Path(tmp)
        bags = []
        for i in range(args.bags):
            bags.append(d / f'bag{i}')
            write_sequence_bag(generate(SynthConfig(surface='flag', width=w, height=h,
                                                    frames=args.frames, seed=i)), bags[-1])
        runs: dict[int, list[dict]] = {j: [] for j in jobs}
        for r in range(args.repeat):
            for j in (jobs if r % 2 == 0 else jobs[::-1]):
                out = d / f'out_j{j}_r{r}'
                rep = process_bags(bags, out, STAGES, jobs=j, threads=args.threads).as_dict()
                bad = [b for b in rep['bags'] if b['status'] != 'ok']
                if bad:
                    print(f'bag failed: {bad[0]["bag"]}: {bad[0]["error"]}', file=sys.stderr)
                    return 1
                runs[j].append({'wall_s': rep['wall_s'],
                                'frames_per_s': rep['throughput']['frames_per_s'],
                                'worker_s': rep['total']['worker_s'],
                                'worker_cpu_s': rep['total']['worker_cpu_s'],
                                'load': os.getloadavg()[0]})
                print(f'jobs {j} run {r}: {rep["wall_s"]:.2f} s wall, '
                      f'{rep["throughput"]["frames_per_s"]:.2f} frames/s, '
                      f'worker time {rep["total"]["worker_s"]:.2f} s, '
                      f'worker CPU {rep["total"]["worker_cpu_s"]:.2f} s, '
                      f'load {os.getloadavg()[0]:.2f}', flush=True)
    base = statistics.median(x['wall_s'] for x in runs[jobs[0]])
    threads = args.threads or 'default (1)'
    print(f'\n{args.bags} bags, {w}x{h}, {args.frames} frames, all four stages; threads per '
          f'worker {threads}; {os.cpu_count()} CPUs (load average {os.getloadavg()[0]:.2f} at '
          'the end)')
    print('| --jobs | wall s (median) | runs | frames/s (median) | throughput vs '
          f'--jobs {jobs[0]} |')
    print('|---|---|---|---|---|')
    table = []
    for j in jobs:
        wall = statistics.median(x['wall_s'] for x in runs[j])
        fps = statistics.median(x['frames_per_s'] for x in runs[j])
        table.append({'jobs': j, 'wall_s': wall, 'frames_per_s': fps, 'ratio': base / wall,
                      'runs': runs[j]})
        each = ', '.join(f"{x['wall_s']:.2f}" for x in runs[j])
        print(f'| {j} | {wall:.2f} | {each} | {fps:.2f} | {base / wall:.2f}x |')
    if args.json:
        Path(args.json).write_text(json.dumps(table, indent=2))
    return 0


if __name__ == '__main__':
    sys.exit(main())
