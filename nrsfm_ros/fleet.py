"""Many bags through the offline pipeline, each in its own worker process.

``process_bags`` runs :func:`~nrsfm_ros.pipeline.process_bag` once per input bag in a
``ProcessPoolExecutor`` (workers forked from a clean fork server that imported the pipeline
and loaded the numba kernels once: no forked ROS or parent state, no per-worker imports or
kernel loads), writes one output bag per
input under one folder and returns one combined report.  A bag that fails (not a bag, damaged,
an exception, even a worker process that dies) is reported with its error line and the others
go on.  Each worker's native thread pools (OpenBLAS/OpenMP, OpenCV) get one thread by default:
the parallelism is the workers.  Measured on 4 synthetic bags (bench/bench_fleet.py, 2 shared
cores): a worker with 2 BLAS/OpenCV threads spent 7x the CPU time of a single-threaded one on
the same bags (22 s against 3 s), most of it in the reconstructor's solves.

``process_bags(..., ray='')`` runs the same jobs as Ray tasks instead (one task per bag, one CPU
each): ``''`` starts a private Ray instance on this machine bound to 127.0.0.1 only (no
dashboard, no usage statistics, a small object store), an address (``HOST:PORT`` of the head)
connects to a running cluster whose nodes have this package installed and see the bags and the
output folder at the same paths (a shared filesystem).  The report is the same;
a task whose worker dies fails its bag alone (no retries: a bag that kills its worker would kill
the next one too).  Ray is an optional extra (``pip install nrsfm_ros[ray]``).

This module imports nothing heavy at the top: a worker loads what it needs.
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
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
THREAD_VARS = ('OMP_NUM_THREADS', 'OPENBLAS_NUM_THREADS', 'MKL_NUM_THREADS',
               'NUMBA_NUM_THREADS')      # numba: the tracker's parallel refinement kernel


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
    """The combined report: one entry per bag (input order), wall time and throughput.
    ``engine``: 'processes' (a local process pool) or 'ray'; ``ray``: the cluster it ran on
    (address, nodes' IPs, CPUs, seconds to start or connect)."""

    jobs: int
    bags: list[dict[str, Any]] = field(default_factory=list)
    wall_s: float = 0.0
    engine: str = 'processes'
    ray: dict[str, Any] | None = None

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
        out: dict[str, Any] = {
            'jobs': self.jobs, 'engine': self.engine, 'wall_s': round(wall, 3),
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
        if self.ray is not None:
            out['ray'] = self.ray
        return out


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


def input_bytes(path: str | Path) -> int:
    """Size of a bag on disk (a folder: its files; 0 where it cannot be read): the measure of
    its work that the scheduler has before opening it."""
    p = Path(path)
    try:
        if p.is_dir():
            return sum(f.stat().st_size for f in p.rglob('*') if f.is_file())
        return p.stat().st_size
    except OSError:
        return 0


def largest_first(jobs: Sequence[BagJob]) -> list[BagJob]:
    """The jobs in the order they are handed to the workers: the largest bags first (ties in
    input order), so that a long bag does not start last and leave the other workers idle at
    the end (longest-processing-time-first scheduling; the report keeps the input order)."""
    size = {j.index: input_bytes(j.bag) for j in jobs}
    return sorted(jobs, key=lambda j: (-size[j.index], j.index))


def _init_worker(threads: int) -> None:
    from .core.threads import set_workers
    set_workers(threads)          # the batch solves' candidate threads too
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
_forkserver_env: tuple[str | None, ...] | None = None   # THREAD_VARS its server started with
# what the fork server imports before forking workers: the pipeline, and the numba kernels
# loaded (nrsfm_ros.warm: ~0.3-0.5 s a worker otherwise; bench_fleet 4 bags, --jobs 1 6.5 ->
# 4.8 s, --jobs 2 4.3 -> 2.7 s, 1.54x -> 1.76x)
FORKSERVER_PRELOAD = ('nrsfm_ros.pipeline', 'nrsfm_ros.warm')


def _pool_context() -> Any:
    """The workers' start method: a fork server that has imported the pipeline once (a clean
    process started for the purpose: no ROS or parent state), so that each worker starts
    without the ~1 s of imports a spawned one pays (bench_fleet, 4 bags, ``--jobs 2`` against
    1: 1.55x -> 1.70x).  The server keeps the thread variables (THREAD_VARS) it started with
    for the life of this process, so a later call with other values spawns its workers."""
    import multiprocessing
    global _forkserver_env
    env = tuple(os.environ.get(v) for v in THREAD_VARS)
    if _forkserver_env is None and 'forkserver' in multiprocessing.get_all_start_methods():
        _forkserver_env = env
        ctx = multiprocessing.get_context('forkserver')
        ctx.set_forkserver_preload(list(FORKSERVER_PRELOAD))
        return ctx
    if _forkserver_env == env:
        return multiprocessing.get_context('forkserver')
    return multiprocessing.get_context('spawn')


def _run_pool(jobs: Sequence[BagJob], workers: int, threads: int, worker: Worker,
              on_done: Callable[[dict[str, Any]], None] | None,
              results: dict[int, dict[str, Any]]) -> list[BagJob]:
    """Run ``jobs`` on a pool; returns the jobs lost to a broken pool (a worker died)."""
    lost: list[BagJob] = []
    with ProcessPoolExecutor(max_workers=workers, mp_context=_pool_context(),
                             initializer=_init_worker, initargs=(threads,)) as pool:
        futures = {pool.submit(worker, job): job for job in largest_first(jobs)}
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
                 params: Mapping[str, Any] | None = None, jobs: int | None = None,
                 copy_inputs: bool = False,
                 on_done: Callable[[dict[str, Any]], None] | None = None,
                 worker: Worker = run_job, threads: int | None = None,
                 ray: str | None = None) -> FleetReport:
    """Process each bag into ``out_dir/<its name>`` on ``jobs`` worker processes (default 1),
    or, with ``ray`` set, as Ray tasks (see :func:`ray_session`: ``''`` a private local
    instance with ``jobs`` CPUs, default all cores; an address: that cluster, at most ``jobs``
    bags at a time when given).

    ``on_done(entry)`` is called in this process as each bag finishes.  When a pool worker dies
    (BrokenProcessPool), the bags it took down are run again one per fresh pool, so only the
    bag that kills its worker is reported as failed; a Ray task is never retried and a dead
    Ray worker fails its own bag only.  ``worker`` (a module-level function, it is pickled to
    the workers) processes one :class:`BagJob`; tests replace it.  ``threads``: each worker's
    OpenCV threads and, unless the environment sets them, its OpenMP/OpenBLAS threads (default
    1, see the module notes)."""
    if jobs is not None and jobs < 1:
        raise ValueError(f'--jobs {jobs}: expected >= 1')
    if not bags:
        raise ValueError('no input bag given')
    if threads is None:
        threads = 1
    elif threads < 1:
        raise ValueError(f'threads={threads}: expected >= 1')
    outs = output_paths(bags, out_dir)
    todo = [BagJob(i, str(b), str(o), tuple(stages), params, copy_inputs)
            for i, (b, o) in enumerate(zip(bags, outs))]
    results: dict[int, dict[str, Any]] = {}
    saved = {v: os.environ.get(v) for v in THREAD_VARS}
    t0 = time.perf_counter()
    try:
        for v in THREAD_VARS:     # inherited by the workers (a value set wins)
            os.environ.setdefault(v, str(threads))
        if ray is not None:
            with ray_session(ray, num_cpus=jobs) as info:
                Path(out_dir).mkdir(parents=True, exist_ok=True)
                limit = len(todo) if jobs is None or ray == '' else jobs
                workers = min(limit, max(1, int(info['cpus'])), len(todo))
                _run_ray(todo, workers, threads, worker, on_done, results,
                         remote_env=bool(ray) and not info['reused'])
            report = FleetReport(jobs=workers, engine='ray', ray=info)
        else:
            Path(out_dir).mkdir(parents=True, exist_ok=True)
            workers = min(jobs or 1, len(todo))
            report = FleetReport(jobs=workers)
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


# ------------------------------------------------------------------ Ray

RAY_OBJECT_STORE_BYTES = 80 * 2 ** 20     # Ray's minimum is 75 MiB; the jobs pass only paths
RAY_INSTALL_HINT = "pip install 'nrsfm_ros[ray]' (Ray 2.58.0)"


class RayUnavailableError(RuntimeError):
    """Ray is not installed, or the cluster cannot be started or reached."""


RAY_CLUSTER_ENV = 'RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER'


def _import_ray() -> Any:
    os.environ['RAY_USAGE_STATS_ENABLED'] = '0'
    try:
        import ray
        from ray._private import ray_constants  # noqa: F401 -- checked here, used later
    except ImportError as err:
        raise RayUnavailableError(f'Ray is not installed: {RAY_INSTALL_HINT}') from err
    return ray


@contextlib.contextmanager
def _loopback_nodes(local: bool) -> Iterator[None]:
    """While active (``local``: a private instance, or a head on 127.0.0.1), Ray keeps the
    loopback address (it otherwise swaps 127.0.0.1 for this machine's address, in a head's
    address too), so new Ray nodes of this process get the loopback address: with
    ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER`` off (read once, when Ray is imported; set on the
    module as well) Ray gives a node 127.0.0.1, and its gRPC servers, object manager and agents
    bind there only, instead of this machine's first non-loopback address.  Restores Ray's own
    setting on exit (a later session may join a cluster by address)."""
    if not local:
        yield
        return
    before = os.environ.get(RAY_CLUSTER_ENV)
    os.environ[RAY_CLUSTER_ENV] = '0'
    from ray._private import ray_constants
    own = before.lower() in ('1', 'true') if before is not None else \
        not ray_constants.IS_WINDOWS_OR_OSX
    ray_constants.ENABLE_RAY_CLUSTER = False
    try:
        yield
    finally:
        ray_constants.ENABLE_RAY_CLUSTER = own
        if before is None:
            os.environ.pop(RAY_CLUSTER_ENV, None)
        else:
            os.environ[RAY_CLUSTER_ENV] = before


LOOPBACK_HOSTS = ('', '127.0.0.1', 'localhost', '::1')


def _split_address(address: str) -> tuple[str, int | None]:
    """(host, port) of ``HOST:PORT``; ('', None) for a local instance."""
    if not address:
        return '', None
    host, sep, port = address.rpartition(':')
    if not sep or not host or '/' in host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f'--ray {address}: expected HOST:PORT of the Ray head (e.g. '
                         '10.0.0.5:6379)')
    return host.strip('[]'), int(port)


def _probe(host: str, port: int | None, address: str, timeout_s: float = 5.0) -> None:
    """Fail fast when nothing listens at the head's address (Ray itself retries for minutes)."""
    if port is None:
        return
    import socket
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except OSError as err:
        raise RayUnavailableError(f'could not connect to the Ray cluster at {address}: '
                                  f'{_error_line(err)}') from err


def _cluster_info(ray: Any, address: str, started_s: float, reused: bool) -> dict[str, Any]:
    nodes = [n for n in ray.nodes() if n.get('Alive')]
    return {'address': address or 'local', 'reused': reused,
            'nodes': sorted(n['NodeManagerAddress'] for n in nodes),
            'cpus': ray.cluster_resources().get('CPU', 0.0),
            'start_s': round(started_s, 3)}


@contextlib.contextmanager
def ray_session(address: str = '', num_cpus: int | None = None) -> Iterator[dict[str, Any]]:
    """Ray for one fleet run; yields the cluster's info (address, nodes, CPUs, start_s).

    ``address=''``: start a private Ray instance on this machine with ``num_cpus`` CPUs
    (default: all cores), bound to 127.0.0.1, without dashboard or usage statistics and with
    an object store of :data:`RAY_OBJECT_STORE_BYTES`; it stops on exit.  Otherwise connect to
    the cluster at ``address`` (``HOST:PORT`` of its head) and disconnect on
    exit.  When this process is already connected to Ray, that connection is used and left
    open.  Raises :class:`RayUnavailableError` when Ray is missing or cannot start/connect."""
    if num_cpus is not None and num_cpus < 1:
        raise ValueError(f'num_cpus={num_cpus}: expected >= 1')
    host, port = _split_address(address)
    ray = _import_ray()
    if ray.is_initialized():
        yield _cluster_info(ray, address, 0.0, reused=True)
        return
    import logging
    t0 = time.perf_counter()
    kwargs: dict[str, Any] = dict(include_dashboard=False, log_to_driver=False,
                                  configure_logging=True, logging_level=logging.WARNING)
    _probe(host, port, address)
    with _loopback_nodes(local=host in LOOPBACK_HOSTS):
        try:
            if address:
                ray.init(address=address, **kwargs)
            else:
                ray.init(address='local', num_cpus=num_cpus or os.cpu_count() or 1,
                         object_store_memory=RAY_OBJECT_STORE_BYTES,
                         _node_ip_address='127.0.0.1', **kwargs)
        except Exception as err:  # noqa: BLE001 -- Ray raises many kinds (ConnectionError..)
            where = f'connect to the Ray cluster at {address}' if address else \
                'start a local Ray instance'
            raise RayUnavailableError(f'could not {where}: {_error_line(err)}') from err
        try:
            info = _cluster_info(ray, address, time.perf_counter() - t0, reused=False)
            if not address and info['nodes'] != ['127.0.0.1']:
                raise RayUnavailableError(f'the local Ray instance took address(es) '
                                          f'{info["nodes"]}, not 127.0.0.1; not using it')
            yield info
        finally:
            ray.shutdown()


def _ray_task(job: BagJob, threads: int, worker: Worker) -> dict[str, Any]:
    """One bag in a Ray worker (a long-lived process: OpenCV's thread count is set per task)."""
    _init_worker(threads)
    return worker(job)


def _failed(job: BagJob, error: str) -> dict[str, Any]:
    entry = _crashed(job, RuntimeError())
    entry['error'] = error
    return entry


def _run_ray(jobs: Sequence[BagJob], limit: int, threads: int, worker: Worker,
             on_done: Callable[[dict[str, Any]], None] | None,
             results: dict[int, dict[str, Any]], remote_env: bool) -> None:
    """Run ``jobs`` as Ray tasks (one CPU each, no retries), at most ``limit`` at a time.
    ``remote_env``: the workers were not started from this process's environment (a cluster
    joined by address), so the thread variables travel in the task's runtime_env."""
    import ray
    from ray.exceptions import RayTaskError
    options: dict[str, Any] = {'num_cpus': 1, 'max_retries': 0}
    if remote_env:
        options['runtime_env'] = {'env_vars': {v: os.environ[v] for v in THREAD_VARS}}
    task = ray.remote(_ray_task).options(**options)
    queue = largest_first(jobs)
    pending: dict[Any, BagJob] = {}
    while queue or pending:
        while queue and len(pending) < limit:
            job = queue.pop(0)
            pending[task.remote(job, threads, worker)] = job
        ready, _ = ray.wait(list(pending), num_returns=1)
        for ref in ready:
            job = pending.pop(ref)
            try:
                entry = ray.get(ref)
            except RayTaskError as err:        # the worker function raised
                cause = err.cause if getattr(err, 'cause', None) is not None else err
                entry = _failed(job, f'task raised {_error_line(cause)}')
            except ray.exceptions.RayError as err:    # the worker process died, ...
                entry = _failed(job, f'worker process died ({type(err).__name__})')
            results[job.index] = entry
            if on_done is not None:
                on_done(entry)


def write_fleet_report(report: FleetReport, path: str | Path) -> None:
    Path(path).write_text(json.dumps(report.as_dict(), indent=2))
