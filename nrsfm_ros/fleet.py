"""Many bags through the offline pipeline, each in its own worker process.

``process_bags`` runs :func:`~nrsfm_ros.pipeline.process_bag` once per input bag in a
``ProcessPoolExecutor`` (spawn context: no forked ROS or BLAS state), writes one output bag per
input under one folder and returns one combined report.  A bag that fails (not a bag, damaged,
an exception, even a worker process that dies) is reported with its error line and the others
go on.  Each worker's native thread pools (OpenBLAS/OpenMP, OpenCV) get one thread by default:
the parallelism is the workers.  Measured on 4 synthetic bags (bench/bench_fleet.py, 2 shared
cores): a worker with 2 BLAS/OpenCV threads spent 7x the CPU time of a single-threaded one on
the same bags (22 s against 3 s), most of it in the reconstructor's solves.

This module imports nothing heavy at the top: a spawned worker loads what it needs.
"""
from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

# what counts as a frame: the first stage's frame input, the last stage's frame output
FRAME_INPUTS = {'tracker': ('camera/image_raw', 'camera/image_raw/compressed'),
                'reconstructor': ('nrsfm/tracks',), 'registrar': ('nrsfm/points',),
                'scene_flow': ('nrsfm/points', 'camera/image_raw')}
FRAME_OUTPUTS = {'tracker': 'nrsfm/tracks', 'reconstructor': 'nrsfm/points',
                 'registrar': 'registration/aligned', 'scene_flow': 'scene_flow/points'}
THREAD_VARS = ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS')


@dataclass(frozen=True)
class BagJob:
    """One input bag and the output bag it is processed into."""

    index: int
    bag: str
    out: str
    stages: tuple[str, ...]
    params: Mapping[str, Any] | None = None
    copy_inputs: bool = False


@dataclass
class FleetReport:
    """The combined report: one entry per bag (input order), wall time and throughput."""

    jobs: int
    bags: list[dict[str, Any]] = field(default_factory=list)
    wall_s: float = 0.0

    @property
    def failed(self) -> list[dict[str, Any]]:
        return [b for b in self.bags if b['status'] == 'failed']

    def exit_code(self) -> int:
        """0 all processed cleanly; 1 some frames could not be processed; 2 a bag failed."""
        if self.failed:
            return 2
        return 1 if any(b['status'] != 'ok' for b in self.bags) else 0

    def as_dict(self) -> dict[str, Any]:
        frames_in = sum(b['frames_in'] for b in self.bags)
        frames_out = sum(b['frames_out'] for b in self.bags)
        messages = sum(b['messages_in'] for b in self.bags)
        wall = self.wall_s
        return {
            'jobs': self.jobs, 'wall_s': round(wall, 3),
            'total': {'bags': len(self.bags), 'ok': sum(b['status'] == 'ok' for b in self.bags),
                      'frame_failures': sum(b['status'] == 'frame failures'
                                            for b in self.bags),
                      'failed': len(self.failed), 'frames_in': frames_in,
                      'frames_out': frames_out, 'messages_in': messages,
                      'worker_s': round(sum(b['seconds'] for b in self.bags), 3),
                      'worker_cpu_s': round(sum(b['cpu_s'] for b in self.bags), 3)},
            'throughput': {'bags_per_s': round(len(self.bags) / wall, 3) if wall else None,
                           'frames_per_s': round(frames_in / wall, 2) if wall else None,
                           'messages_per_s': round(messages / wall, 1) if wall else None},
            'bags': self.bags,
        }


def output_paths(bags: Sequence[str | Path], out_dir: str | Path) -> list[Path]:
    """``out_dir/<input bag name>`` for each input; raises ValueError on a name used twice or
    an output that already exists."""
    out_dir = Path(out_dir)
    names = [Path(b).name or Path(b).resolve().name for b in bags]
    seen: dict[str, str] = {}
    for bag, name in zip(bags, names):
        if name in seen:
            raise ValueError(f'--out {out_dir}: inputs {seen[name]} and {bag} would both write '
                             f'{out_dir / name}; give the bags different folder names')
        seen[name] = str(bag)
    outs = [out_dir / n for n in names]
    exist = [str(p) for p in outs if p.exists()]
    if exist:
        raise ValueError(f'--out {out_dir}: {", ".join(exist)} exist(s); choose another --out '
                         'or delete them')
    return outs


def _frames(report: Mapping[str, Any], stages: Sequence[str]) -> tuple[int, int]:
    inputs, outputs = report.get('inputs', {}), report.get('outputs', {})
    order = [s for s in FRAME_OUTPUTS if s in stages]        # pipeline order
    first, last = order[0], order[-1]
    frames_in = max((inputs.get(t, 0) for t in FRAME_INPUTS[first]), default=0)
    return frames_in, outputs.get(FRAME_OUTPUTS[last], 0)


def _error_line(err: BaseException) -> str:
    text = ' '.join(str(err).split())
    return f'{type(err).__name__}: {text}' if text else type(err).__name__


def run_job(job: BagJob) -> dict[str, Any]:
    """Process one bag (in a worker); never raises: an error becomes the entry's ``error``."""
    from .pipeline import process_bag
    entry: dict[str, Any] = {'bag': job.bag, 'out': job.out, 'status': 'failed', 'error': '',
                             'frames_in': 0, 'frames_out': 0, 'messages_in': 0, 'failures': 0,
                             'first_failures': [], 'seconds': 0.0, 'cpu_s': 0.0,
                             'pid': os.getpid()}
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        report = process_bag(job.bag, job.out, job.stages, job.params, progress=False,
                             copy_inputs=job.copy_inputs)
    except Exception as err:  # noqa: BLE001 -- one bad bag never stops the others
        entry['error'] = _error_line(err)
        entry['seconds'] = round(time.perf_counter() - t0, 3)
        entry['cpu_s'] = round(time.process_time() - c0, 3)
        return entry
    d = report.as_dict()
    entry['frames_in'], entry['frames_out'] = _frames(d, job.stages)
    entry['messages_in'] = sum(d['inputs'].values())
    entry['failures'] = len(d['failures'])
    entry['first_failures'] = [f"stamp {f['stamp_ns']} {f['stage']} ({f['topic']}): "
                               f"{f['error']}" for f in d['failures'][:5]]
    entry['seconds'] = d['seconds']
    entry['cpu_s'] = round(time.process_time() - c0, 3)     # well below seconds: shared CPU
    entry['report'] = d
    if report.damage:
        entry['error'] = report.damage[0]
    else:
        entry['status'] = 'frame failures' if d['failures'] else 'ok'
        if d['failures']:
            entry['error'] = entry['first_failures'][0]
    return entry


def _init_worker(threads: int) -> None:
    try:
        import cv2
        cv2.setNumThreads(threads)
    except ImportError:  # pragma: no cover -- OpenCV is a dependency
        pass


def _crashed(job: BagJob, err: BaseException) -> dict[str, Any]:
    return {'bag': job.bag, 'out': job.out, 'status': 'failed',
            'error': f'worker process died ({_error_line(err)})', 'frames_in': 0,
            'frames_out': 0, 'messages_in': 0, 'failures': 0, 'first_failures': [],
            'seconds': 0.0, 'cpu_s': 0.0, 'pid': None}


Worker = Callable[[BagJob], dict[str, Any]]


def _run_pool(jobs: Sequence[BagJob], workers: int, threads: int, worker: Worker,
              on_done: Callable[[dict[str, Any]], None] | None,
              results: dict[int, dict[str, Any]]) -> list[BagJob]:
    """Run ``jobs`` on a pool; returns the jobs lost to a broken pool (a worker died)."""
    import multiprocessing
    lost: list[BagJob] = []
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context('spawn'),
                             initializer=_init_worker, initargs=(threads,)) as pool:
        futures = {pool.submit(worker, job): job for job in jobs}
        for fut in as_completed(futures):
            job = futures[fut]
            try:
                entry = fut.result()
            except BrokenProcessPool:
                lost.append(job)
                continue
            results[job.index] = entry
            if on_done is not None:
                on_done(entry)
    return lost


def process_bags(bags: Sequence[str | Path], out_dir: str | Path, stages: Sequence[str],
                 params: Mapping[str, Any] | None = None, jobs: int = 1,
                 copy_inputs: bool = False,
                 on_done: Callable[[dict[str, Any]], None] | None = None,
                 worker: Worker = run_job, threads: int | None = None) -> FleetReport:
    """Process each bag into ``out_dir/<its name>`` on ``jobs`` worker processes.

    ``on_done(entry)`` is called in this process as each bag finishes.  When a worker dies
    (BrokenProcessPool), the bags it took down are run again one per fresh pool, so only the
    bag that kills its worker is reported as failed.  ``worker`` (a module-level function, it
    is pickled to the workers) processes one :class:`BagJob`; tests replace it.  ``threads``:
    each worker's OpenCV threads and, unless the environment sets them, its OpenMP/OpenBLAS
    threads (default 1, see the module notes)."""
    if jobs < 1:
        raise ValueError(f'--jobs {jobs}: expected >= 1')
    if not bags:
        raise ValueError('no input bag given')
    outs = output_paths(bags, out_dir)
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    todo = [BagJob(i, str(b), str(o), tuple(stages), params, copy_inputs)
            for i, (b, o) in enumerate(zip(bags, outs))]
    workers = min(jobs, len(todo))
    if threads is None:
        threads = 1
    elif threads < 1:
        raise ValueError(f'threads={threads}: expected >= 1')
    report = FleetReport(jobs=workers)
    results: dict[int, dict[str, Any]] = {}
    saved = {v: os.environ.get(v) for v in THREAD_VARS}
    t0 = time.perf_counter()
    try:
        for v in THREAD_VARS:     # inherited by the spawned workers (a value set wins)
            os.environ.setdefault(v, str(threads))
        lost = _run_pool(todo, workers, threads, worker, on_done, results)
        for job in lost:          # isolate: the bag that kills a worker alone fails
            if Path(job.out).exists():      # its partial output (checked absent up front)
                shutil.rmtree(job.out)
            again = _run_pool([job], 1, threads, worker, on_done, results)
            if again:
                entry = _crashed(job, BrokenProcessPool('a worker process died abruptly'))
                results[job.index] = entry
                if on_done is not None:
                    on_done(entry)
    finally:
        for v, value in saved.items():
            if value is None:
                os.environ.pop(v, None)
            else:
                os.environ[v] = value
    report.wall_s = time.perf_counter() - t0
    report.bags = [results[j.index] for j in todo]
    return report


def write_fleet_report(report: FleetReport, path: str | Path) -> None:
    Path(path).write_text(json.dumps(report.as_dict(), indent=2))
