"""``process`` with its stages in separate processes or threads, so that one bag uses every core.

Each stage is sequential in time; the stages are not: while the reconstructor solves a batch,
the tracker goes on tracking and the registrar and scene_flow work on the clouds already
published.  The stages form a chain of worker processes in graph order (tracker ->
reconstructor -> registrar -> scene_flow); the main process reads the bag into the first and
writes what leaves the last.  Every event (a bag message or a stage's output) travels down the
chain; a stage handles the events routed to it (:data:`pipeline.ROUTES`) and passes its outputs
on.  **Each stage sees its inputs in exactly the order of the one-process pipeline** (a
depth-first walk: an output's consumers run before the next consumer of the message that caused
it), so the outputs are the same messages: where a message has consumers further down the
chain, a stage passes its own outputs of that message on first when it comes before those
consumers in the message's route list, else after it (:func:`outputs_first`).

``workers='threads'``: the stages run as threads of this process instead, handing the same
events over in-process queues (nothing pickled, nothing started).  The stages overlap only
where they release the GIL -- OpenCV's flow, NumPy's BLAS and element-wise loops, the numba
kernels of ``bmm`` and the planar refinement (compiled ``nogil``) -- which is most of the
tracker's and much of the reconstructor's time: on 2 cores it overlaps the tracker with the
reconstructor's batch solve without the processes' start-up and pickling (BENCHMARKS issue 17).
With threads the per-stage CPU times of the report are the process' CPU time over each call,
which then includes the other stages' work done meanwhile (wall times are each call's own).

Messages cross the process boundaries pickled (rosbags message classes pickle; NumPy arrays
go as buffers).  The queues are bounded (``QUEUE_SIZE`` events), so a slow stage holds the
reader back instead of the bag piling up in memory.  A stage process that dies is reported as
a failure of its stage; the stages after it are sent the end, so that what got through it is
processed, flushed and written as after the bag's end, and the run ends there.
"""
from __future__ import annotations

import multiprocessing
import os
import queue
import signal
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .io.bag import BagWriter, read_messages
from .io.errors import MessageError
from .io.msgtypes import stamp_ns
from .params import Params
from .pipeline import (ROUTES, STAGES, ProcessReport, _progress, expected_frames,
                       make_processors, new_report, read_input)
from .processing import ReconstructorProcessor, SceneFlowProcessor

QUEUE_SIZE = 64          # events in flight between two processes
POLL_S = 0.5             # how often a blocked process checks that the others are alive
FORWARD_S = 30.0         # how long the END sent past a dead stage may take to leave


@dataclass
class Event:
    """One message on its way down the chain.  ``producer``: the stage that published it
    ('' for a bag message); ``write``: the writer at the end writes it (every output; bag
    messages with ``copy_inputs``); ``raw``: a bag message's serialized bytes (copied as
    they are)."""

    topic: str
    msgtype: str
    msg: Any
    stamp: int
    producer: str = ''
    write: bool = False
    raw: bytes | None = None


@dataclass
class StageDone:
    """A stage's part of the report, sent down the chain after its last output."""

    stage: str
    timing: dict[str, dict[str, float]]
    status: dict[str, str]
    failures: list[dict[str, Any]]
    cpu_s: float


END = 'end'              # sent after the last bag message, and by each stage after its flush


def chain_order(stages: Sequence[str]) -> list[str]:
    """``stages`` in graph order (every stage after the stages whose outputs it takes)."""
    return [s for s in STAGES if s in stages]


def outputs_first(stage: str, topic: str, chain: Sequence[str]) -> bool:
    """Whether ``stage`` passes its outputs of a ``topic`` message on before the message
    itself: true unless a consumer of ``topic`` further down the chain comes before ``stage``
    in the topic's route list (the one-process pipeline hands the message to that consumer
    before it walks ``stage``'s outputs)."""
    routes = [s for s, _ in ROUTES.get(topic, [])]
    if stage not in routes:
        return True
    later = chain[chain.index(stage) + 1:]
    return all(routes.index(s) > routes.index(stage) for s in later if s in routes)


def _downstream_needs(topic: str, chain: Sequence[str], i: int) -> bool:
    return any(s in chain[i + 1:] for s, _ in ROUTES.get(topic, []))


class _Stopped(Exception):
    """A stage thread told to end (``_StageThread.terminate``)."""


def _stage_main(stage: str, params: Params | None, chain: list[str], inq: Any,
                outq: Any, frames: int | None = None, stop: threading.Event | None = None
                ) -> None:
    """A stage process (or thread): handle the events routed to it, pass everything on in
    order.  Ctrl-C is the main process' to handle (it ends the stages), not each stage's."""
    threaded = threading.current_thread() is not threading.main_thread()
    if not threaded:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)   # a forked parent's handler (rclpy) goes
    proc = make_processors([stage], {stage: params} if params is not None else None)[stage]
    proc.stats.timing_window = None
    if frames is not None and isinstance(proc, ReconstructorProcessor):
        proc.expect_frames(frames)       # the bag's length (pipeline.expected_frames)
    i = chain.index(stage)
    kinds = {t: k for t, routes in ROUTES.items() for s, k in routes if s == stage}
    failures: list[dict[str, Any]] = []
    cpu = time.thread_time if threaded else time.process_time
    c0 = cpu()

    def put(item: Any) -> None:
        if stop is None:
            outq.put(item)
            return
        while not stop.is_set():            # a thread ends when told to (``terminate``)
            try:
                outq.put(item, timeout=POLL_S)
                return
            except queue.Full:
                continue
        raise _Stopped

    def get() -> Any:
        if stop is None:
            return inq.get()
        while not stop.is_set():
            try:
                return inq.get(timeout=POLL_S)
            except queue.Empty:
                continue
        raise _Stopped

    def outputs_of(outputs: list[Any], stamp: int) -> list[Event]:
        return [Event(t, mt, m, stamp_ns(m.header) if hasattr(m, 'header') else stamp,
                      producer=stage, write=True) for t, mt, m in outputs]

    while True:
        item = get()
        if isinstance(item, StageDone):
            put(item)
            continue
        if item == END:
            if isinstance(proc, ReconstructorProcessor):
                tf, cf = time.perf_counter(), time.process_time()
                try:
                    flushed = proc.flush()
                except Exception as err:  # noqa: BLE001 -- contained like every message
                    flushed = []
                    failures.append({'stage': 'reconstructor (flush)', 'topic': '',
                                     'stamp_ns': 0, 'error': f'{type(err).__name__}: {err}'})
                else:
                    proc.stats.add_time('flush', time.perf_counter() - tf,
                                        time.process_time() - cf)
                for ev in outputs_of(flushed, 0):
                    put(ev)
            elif isinstance(proc, SceneFlowProcessor):    # clouds waiting: pose, look-ahead
                for ev in outputs_of(proc.flush(), 0):
                    put(ev)
            put(StageDone(stage, {k: t.summary() for k, t in proc.stats.timing.items()},
                          proc.status(), failures, cpu() - c0))
            put(END)
            return
        ev: Event = item
        passed = ev.write or _downstream_needs(ev.topic, chain, i)
        kind = kinds.get(ev.topic) if ev.msg is not None else None   # None: a copy to write
        if kind is None:
            if passed:
                put(ev)
            continue
        try:
            outs = outputs_of(proc.handle(kind, ev.msg), ev.stamp)
        except MessageError as err:
            failures.append({'stage': stage, 'topic': ev.topic, 'stamp_ns': ev.stamp,
                             'error': str(err)})
            outs = []
        first = outputs_first(stage, ev.topic, chain)
        for e in (outs + [ev] if first else [ev] + outs) if passed else outs:
            put(e)


def _single_threaded() -> bool:
    """Whether this process runs one OS thread (native ones included: a DDS participant's, a
    BLAS pool's), so that a fork cannot copy a lock another thread holds."""
    try:
        return len(os.listdir('/proc/self/task')) == 1
    except OSError:
        return False


def _context() -> Any:
    """Fork from this process when it runs a single OS thread (it has imported the stages
    already: the workers start at once); else a fork server, which starts clean (a fork of a
    process with DDS threads can deadlock in the child: seen in the test suite after rclpy
    tests)."""
    methods = multiprocessing.get_all_start_methods()
    if 'fork' in methods and _single_threaded():
        return multiprocessing.get_context('fork')
    if 'forkserver' in methods:
        ctx = multiprocessing.get_context('forkserver')
        ctx.set_forkserver_preload(['nrsfm_ros.pipelined'])
        return ctx
    return multiprocessing.get_context('spawn')


class _StageThread:
    """A stage as a thread, with the part of ``multiprocessing.Process`` that
    :func:`process_bag_pipelined` uses: ``exitcode`` None while running, 0 after a normal
    end, 1 after an exception, -SIGTERM once stopped by ``terminate`` (the stop event every
    stage thread polls between events)."""

    def __init__(self, target: Any, name: str, daemon: bool, args: tuple,
                 stop: threading.Event) -> None:
        self.exitcode: int | None = None
        self.error: BaseException | None = None
        self._stop = stop

        def run() -> None:
            try:
                target(*args, stop)
                self.exitcode = 0
            except _Stopped:
                self.exitcode = -signal.SIGTERM        # as a terminated process reads
            except BaseException as err:  # noqa: BLE001 -- reported as the stage dying
                self.error = err
                self.exitcode = 1
        self._thread = threading.Thread(target=run, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def join(self, timeout: float | None = None) -> None:
        self._thread.join(timeout)

    def is_alive(self) -> bool:
        return self._thread.is_alive()

    def terminate(self) -> None:
        """Tell every stage thread to end (they poll between events)."""
        self._stop.set()

    kill = terminate


class _ThreadQueue(queue.Queue):
    """``queue.Queue`` with the two calls of ``multiprocessing.Queue`` used at the end."""

    def cancel_join_thread(self) -> None:
        """Nothing to do: no feeder thread."""

    def close(self) -> None:
        """Nothing to do: no pipe."""

    def join_thread(self) -> None:
        """Nothing to do: no feeder thread."""


class _ThreadContext:
    """The stand-in for a multiprocessing context when the stages are threads: one stop
    event for all of them."""

    def __init__(self) -> None:
        self.stop = threading.Event()

    def Process(self, target: Any, name: str, daemon: bool,  # noqa: N802 -- multiprocessing's
                args: tuple) -> _StageThread:
        return _StageThread(target, name, daemon, args, self.stop)

    @staticmethod
    def Queue(maxsize: int) -> _ThreadQueue:  # noqa: N802 -- multiprocessing's name
        return _ThreadQueue(maxsize)


WORKERS = ('processes', 'threads')


def _send_end(q: Any) -> threading.Thread:
    """END into a dead stage's output queue, from a thread (the writer goes on draining): the
    stages after it flush and end as after the bag's end.  The thread ends once END is in the
    pipe; it never does when the dead process died holding the pipe's lock."""
    def send() -> None:
        q.put(END)
        q.close()
        q.join_thread()
    t = threading.Thread(target=send, name='nrsfm-end', daemon=True)
    t.start()
    return t


def _reap(procs: list[Any]) -> None:
    """Wait for the stage processes; one that has not ended is terminated, then killed."""
    for p in procs:
        p.join(timeout=5 * POLL_S)
        if p.is_alive():
            p.terminate()
            p.join(timeout=5 * POLL_S)
        if p.is_alive():
            p.kill()
            p.join()


def process_bag_pipelined(in_path: str | Path, out_path: str | Path,
                          stages: Sequence[str] = STAGES,
                          params: Mapping[str, Params] | None = None, storage: str = 'mcap',
                          progress: bool = True, copy_inputs: bool = False,
                          workers: str = 'processes') -> ProcessReport:
    """:func:`pipeline.process_bag` with one process (``workers='threads'``: one thread) per
    stage (module doc): the same outputs and report, in less wall time where there are cores
    to spare."""
    if workers not in WORKERS:
        raise ValueError(f'workers={workers!r}: expected one of {WORKERS}')
    threads = workers == 'threads'
    chain = chain_order(stages)
    make_processors(chain, params)          # parameter errors here, before any process
    report, total = new_report(in_path)
    frames = expected_frames(in_path, chain)
    io_s = report.io_s
    t0, c0 = time.perf_counter(), time.process_time()
    ctx: Any = _ThreadContext() if threads else _context()
    queues = [ctx.Queue(QUEUE_SIZE) for _ in range(len(chain) + 1)]
    procs = [ctx.Process(target=_stage_main, name=f'nrsfm-{s}', daemon=True,
                         args=(s, (params or {}).get(s), chain, queues[k], queues[k + 1],
                               frames if s == 'reconstructor' else None))
             for k, s in enumerate(chain)]
    for p in procs:
        p.start()
    done: list[StageDone] = []
    lost: list[str] = []             # stages whose process died
    writer_error: list[BaseException] = []

    def dead() -> list[str]:
        return [s for s, p in zip(chain, procs) if p.exitcode not in (None, 0)]

    def write_all(writer: BagWriter) -> None:
        last = queues[-1]
        ended: dict[int, tuple[threading.Thread, float]] = {}   # dead stage -> its END sent
        while True:
            try:
                item = last.get(timeout=POLL_S)
            except queue.Empty:
                gone = dead()
                if not gone:
                    continue
                lost.extend(s for s in gone if s not in lost)
                j = max(chain.index(s) for s in gone)
                if j == len(chain) - 1:
                    return               # the last stage: nothing after it to wait for
                if j not in ended:       # the stages after it finish what got through
                    ended[j] = _send_end(queues[j + 1]), time.perf_counter()
                    continue
                t, since = ended[j]
                if t.is_alive() and time.perf_counter() - since > FORWARD_S:
                    return               # undeliverable (the dead process held the pipe)
                continue
            if item == END:
                return
            if isinstance(item, StageDone):
                done.append(item)
                continue
            ev: Event = item
            tw = time.perf_counter()
            try:
                writer.write(ev.topic, ev.msgtype, ev.raw if ev.raw is not None else ev.msg,
                             ev.stamp)
            except Exception as err:  # noqa: BLE001 -- e.g. a value the CDR type cannot hold
                io_s['write'] += time.perf_counter() - tw
                report.failures.append({'stage': f'{ev.producer} (write)', 'topic': ev.topic,
                                        'stamp_ns': ev.stamp,
                                        'error': f'{type(err).__name__}: {err}'})
                continue
            io_s['write'] += time.perf_counter() - tw
            if ev.producer:
                report.outputs[ev.topic] = report.outputs.get(ev.topic, 0) + 1

    def send(item: Any) -> bool:
        while True:
            try:
                queues[0].put(item, timeout=POLL_S)
                return True
            except queue.Full:
                if dead() or lost or writer_error:
                    return False

    with BagWriter(out_path, storage) as writer:
        def run_writer() -> None:
            try:
                write_all(writer)
            except BaseException as err:  # noqa: BLE001 -- reported below
                writer_error.append(err)

        wt = threading.Thread(target=run_writer, name='nrsfm-writer', daemon=True)
        wt.start()
        consumed = {t for t in ROUTES if any(s in chain for s, _ in ROUTES[t])}
        mark = time.perf_counter()
        try:
            for n, m in enumerate(read_messages(in_path, damage=report.damage)):
                io_s['read'] += time.perf_counter() - mark
                report.inputs[m.topic] = report.inputs.get(m.topic, 0) + 1
                msg = read_input(m, report)
                if copy_inputs:
                    ok = send(Event(m.topic, m.msgtype, None, m.stamp_ns, write=True,
                                    raw=bytes(m.raw)))
                    if not ok:
                        break
                if msg is not None and m.topic in consumed and \
                        not send(Event(m.topic, m.msgtype, msg, m.stamp_ns)):
                    break
                if progress:
                    _progress(n + 1, total, t0)
                mark = time.perf_counter()
        except BaseException:      # Ctrl-C or a reader error: the stages end now, unflushed
            for p in procs:
                p.terminate()
            wt.join()
            _reap(procs)
            raise
        finally:
            if all(p.exitcode is None for p in procs):
                send(END)
            wt.join()
            _reap(procs)
            for q in queues:       # what a dead stage never read must not block our exit
                q.cancel_join_thread()
                q.close()
    if progress:
        sys.stderr.write('\n')
    for s in dict.fromkeys(lost + dead()):
        p = procs[chain.index(s)]
        if not threads:
            why = f'the {s} process died (exit code {p.exitcode})'
        elif p.error is None:
            why = f'the {s} thread was stopped after another stage failed'
        else:
            why = f'the {s} thread failed ({type(p.error).__name__}: {p.error})'
        report.failures.append({'stage': s, 'topic': '', 'stamp_ns': 0,
                                'error': f'{why}; the outputs after it are missing'})
    if writer_error:
        err = writer_error[0]
        report.failures.append({'stage': 'writer', 'topic': '', 'stamp_ns': 0,
                                'error': f'{type(err).__name__}: {err}'})
    by_stage = {d.stage: d for d in done}
    # the reader's (deserialize) and the writer's failures, then each stage's in chain order
    report.failures += [f for s in chain if s in by_stage for f in by_stage[s].failures]
    report.seconds = time.perf_counter() - t0
    # threads: this process' CPU time already holds the stages'
    report.cpu_s = time.process_time() - c0 + (0.0 if threads else sum(d.cpu_s for d in done))
    report.timing = {s: by_stage[s].timing for s in chain if s in by_stage}
    report.status = {s: by_stage[s].status for s in chain
                     if s in by_stage and by_stage[s].status}
    return report
