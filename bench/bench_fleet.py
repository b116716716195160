"""Throughput of ``nrsfm-ros process BAG ... --jobs N`` against ``--jobs 1``, and of ``--ray``.

    .venv/bin/python bench/bench_fleet.py [--bags 4] [--size 320x240] [--frames 80]
                                          [--jobs 1,2] [--repeat 2] [--ray] [--json out.json]

Writes ``--bags`` synthetic bags (flag surface, seeds 0.., in a temporary folder; ``--frames``
one count for all or a comma list cycled over the bags, e.g. ``20,20,20,60`` for a fleet of
mixed lengths), then runs
``fleet.process_bags`` over all of them (the full four-stage pipeline, default parameters) for
each ``--jobs`` value, ``--repeat`` times in alternating order so that both settings see the
same machine load.  Reports wall time (median and every run), frames/s and the ratio to the
first ``--jobs`` value.  Wall time includes starting the spawned workers (about a second each:
imports), which is part of what a user waits for.

``--ray`` adds a row: the same bags as Ray tasks on one local Ray instance with the largest
``--jobs`` CPUs, started once before the runs (as a cluster is; its start-up time is printed
apart) and reused by every run, in the same alternating order.  Its workers stay up between
runs, so only its first run pays their imports; the row also gives the ratio to the largest
``--jobs``.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from nrsfm_ros.fleet import process_bags, ray_session  # noqa: E402
from nrsfm_ros.io.sequence_bag import write_sequence_bag  # noqa: E402
from nrsfm_ros.io.synth import SynthConfig, generate  # noqa: E402
from nrsfm_ros.pipeline import STAGES  # noqa: E402


def _run_all(args: argparse.Namespace, bags: list[Path], d: Path, settings: list[int | str],
             runs: dict[int | str, list[dict]]) -> bool:
    """Every setting --repeat times, in alternating order; False when a bag failed."""
    for r in range(args.repeat):
        for j in (settings if r % 2 == 0 else settings[::-1]):
            out = d / f'out_{j}_r{r}'
            if j == 'ray':
                rep = process_bags(bags, out, STAGES, threads=args.threads, ray='').as_dict()
                name = 'ray'
            else:
                rep = process_bags(bags, out, STAGES, jobs=int(j),
                                   threads=args.threads).as_dict()
                name = f'jobs {j}'
            bad = [b for b in rep['bags'] if b['status'] != 'ok']
            if bad:
                print(f'bag failed: {bad[0]["bag"]}: {bad[0]["error"]}', file=sys.stderr)
                return False
            runs[j].append({'wall_s': rep['wall_s'],
                            'frames_per_s': rep['throughput']['frames_per_s'],
                            'worker_s': rep['total']['worker_s'],
                            'worker_cpu_s': rep['total']['worker_cpu_s'],
                            'load': os.getloadavg()[0]})
            print(f'{name} run {r}: {rep["wall_s"]:.2f} s wall, '
                  f'{rep["throughput"]["frames_per_s"]:.2f} frames/s, '
                  f'worker time {rep["total"]["worker_s"]:.2f} s, '
                  f'worker CPU {rep["total"]["worker_cpu_s"]:.2f} s, '
                  f'load {os.getloadavg()[0]:.2f}', flush=True)
    return True


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--bags', type=int, default=4)
    p.add_argument('--size', default='320x240')   # the `process` targets' bags (issue 17)
    p.add_argument('--frames', default='80',
                   help='frames per bag: one count, or a comma list cycled over the bags')
    p.add_argument('--jobs', default='1,2')
    p.add_argument('--repeat', type=int, default=2)
    p.add_argument('--threads', type=int, default=None,
                   help='native threads per worker for every --jobs value (default: the '
                   'fleet default, 1); also sets OMP/OPENBLAS/MKL_NUM_THREADS')
    p.add_argument('--ray', action='store_true',
                   help='also time the bags as Ray tasks on a local Ray instance (pip install '
                   'nrsfm_ros[ray])')
    p.add_argument('--json', default=None)
    args = p.parse_args()
    w, h = (int(v) for v in args.size.split('x'))
    jobs = [int(j) for j in args.jobs.split(',')]
    frames = [int(f) for f in str(args.frames).split(',')]
    if args.threads is not None:
        for v in ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS'):
            os.environ[v] = str(args.threads)
    with tempfile.TemporaryDirectory(prefix='bench_fleet_') as tmp:
        d = Path(tmp)
        bags = []
        for i in range(args.bags):
            bags.append(d / f'bag{i}')
            write_sequence_bag(generate(SynthConfig(surface='flag', width=w, height=h,
                                                    frames=frames[i % len(frames)], seed=i)),
                               bags[-1])
        settings: list[int | str] = [*jobs, 'ray'] if args.ray else list(jobs)
        runs: dict[int | str, list[dict]] = {j: [] for j in settings}
        with contextlib.ExitStack() as stack:
            if args.ray:
                info = stack.enter_context(ray_session('', num_cpus=max(jobs)))
                print(f"local Ray instance: {info['cpus']:g} CPU(s) on {info['nodes']}, "
                      f"started in {info['start_s']:.2f} s", flush=True)
            if not _run_all(args, bags, d, settings, runs):
                return 1
    base = statistics.median(x['wall_s'] for x in runs[jobs[0]])
    threads = args.threads or 'default (1)'
    print(f'\n{args.bags} bags, {w}x{h}, {args.frames} frames, all four stages; threads per '
          f'worker {threads}; {os.cpu_count()} CPUs (load average {os.getloadavg()[0]:.2f} at '
          'the end)')
    print('| --jobs | wall s (median) | runs | frames/s (median) | throughput vs '
          f'--jobs {jobs[0]} |')
    print('|---|---|---|---|---|')
    table = []
    for j in settings:
        wall = statistics.median(x['wall_s'] for x in runs[j])
        fps = statistics.median(x['frames_per_s'] for x in runs[j])
        table.append({'jobs': j, 'wall_s': wall, 'frames_per_s': fps, 'ratio': base / wall,
                      'runs': runs[j]})
        each = ', '.join(f"{x['wall_s']:.2f}" for x in runs[j])
        print(f'| {j} | {wall:.2f} | {each} | {fps:.2f} | {base / wall:.2f}x |')
    if args.ray:
        top = statistics.median(x['wall_s'] for x in runs[max(jobs)])
        ray_wall = statistics.median(x['wall_s'] for x in runs['ray'])
        print(f'ray / --jobs {max(jobs)} wall time: {ray_wall / top:.3f} (target <= 1.10)')
    if args.json:
        Path(args.json).write_text(json.dumps(table, indent=2))
    return 0


if __name__ == '__main__':
    sys.exit(main())
