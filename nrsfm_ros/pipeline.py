"""Offline processing of a bag through the node graph, with the live nodes' processors.

Messages are fed in log-time order; each processor's outputs go straight to the processors
downstream of it (tracker -> reconstructor -> registrar, scene_flow), exactly the topic graph of
the live nodes, and every output is written to the output bag.  Every input frame that a stage
could not process is listed in the report; a damaged input bag is read as far as possible and
the report names what it lost.
"""
from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .io.bag import BagWriter, bag_info, deserialize, read_messages
from .io.errors import MessageError
from .io.msgtypes import RosbagsFactory, stamp_ns
from .params import NODE_PARAMS, Params
from .processing import (TOPICS, Processor, ReconstructorProcessor, RegistrarProcessor,
                         SceneFlowProcessor, TrackerProcessor)

STAGES = ('tracker', 'reconstructor', 'registrar', 'scene_flow')

# input topic -> [(stage, kind)]
ROUTES: dict[str, list[tuple[str, str]]] = {
    TOPICS['image']: [('tracker', 'image'), ('scene_flow', 'image'), ('reconstructor', 'image')],
    TOPICS['image_compressed']: [('tracker', 'image_compressed'),
                                 ('reconstructor', 'image_compressed')],   # mode hdmnet
    TOPICS['mask']: [('tracker', 'mask')],      # tracker roi_mask
    TOPICS['camera_info']: [('reconstructor', 'camera_info'), ('scene_flow', 'camera_info')],
    TOPICS['depth']: [('scene_flow', 'depth')],   # scene_flow method msf (RGB-D)
    TOPICS['tracks']: [('reconstructor', 'tracks')],
    TOPICS['points']: [('registrar', 'points'), ('scene_flow', 'points')],
    TOPICS['object_pose']: [('scene_flow', 'object_pose')],
    TOPICS['reference']: [('registrar', 'reference')],
}


@dataclass
class ProcessReport:
    inputs: dict[str, int] = field(default_factory=dict)
    outputs: dict[str, int] = field(default_factory=dict)
    failures: list[dict[str, Any]] = field(default_factory=list)
    damage: list[str] = field(default_factory=list)   # what a damaged input bag lost
    seconds: float = 0.0
    cpu_s: float = 0.0          # the process' CPU time over the run (user + system)
    bag_duration_s: float = 0.0
    # stage -> input kind -> calls, total_s, cpu_s (the process' CPU time in them),
    # mean/p50/p90/max ms of its processing callbacks
    # (each stage's own work: its outputs' downstream processing is not in it); the
    # reconstructor's end-of-stream flush is its kind 'flush'
    timing: dict[str, dict[str, dict[str, float]]] = field(default_factory=dict)
    # seconds outside the stages: reading the bag, deserializing inputs, writing outputs
    io_s: dict[str, float] = field(default_factory=dict)
    # stage -> its method-specific values (Processor.status, as on /diagnostics)
    status: dict[str, dict[str, str]] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {'inputs': self.inputs, 'outputs': self.outputs, 'failures': self.failures,
                'damage': self.damage,
                'seconds': round(self.seconds, 3), 'cpu_s': round(self.cpu_s, 3),
                'bag_duration_s': self.bag_duration_s,
                'realtime_factor': round(self.bag_duration_s / self.seconds, 2)
                if self.seconds else None,
                'timing': self.timing, 'io_s': {k: round(v, 3) for k, v in self.io_s.items()},
                'status': self.status}


def new_report(in_path: str | Path) -> tuple[ProcessReport, int]:
    """An empty report for the bag (its duration, zeroed I/O times) and its message count."""
    info = bag_info(in_path)
    report = ProcessReport(bag_duration_s=info['duration_s'])
    report.io_s.update(read=0.0, deserialize=0.0, write=0.0)
    return report, info['messages']


def expected_frames(in_path: str | Path, stages: Sequence[str]) -> int:
    """The frames the reconstructor will see in a bag: its camera images where the tracker
    runs (one tracks message each), else its tracks messages."""
    topics = bag_info(in_path)['topics']
    source = ('image', 'image_compressed') if 'tracker' in stages else ('tracks',)
    return sum(topics.get(TOPICS[k], {}).get('count', 0) for k in source)


def expect_frames(proc: Processor, in_path: str | Path, stages: Sequence[str]) -> None:
    """Tell the reconstructor (``proc``, if it is one) the bag's length in frames."""
    if isinstance(proc, ReconstructorProcessor):
        proc.expect_frames(expected_frames(in_path, stages))


def read_input(m: Any, report: ProcessReport) -> Any | None:
    """The bag message ``m`` deserialized where a stage takes its topic (timed in the report's
    ``io_s``); None for other topics, and, with the failure recorded, where it cannot be read."""
    if m.topic not in ROUTES:
        return None
    td = time.perf_counter()
    try:
        return deserialize(m.raw, m.msgtype)
    except MessageError as err:
        report.failures.append({'stage': 'deserialize', 'topic': m.topic,
                                'stamp_ns': m.stamp_ns, 'error': str(err)})
        return None
    finally:
        report.io_s['deserialize'] += time.perf_counter() - td


def make_processors(stages: Sequence[str], params: Mapping[str, Params] | None = None,
                    factory: Any = None) -> dict[str, Processor]:
    factory = factory or RosbagsFactory()
    params = params or {}
    classes: dict[str, Callable[..., Processor]] = {
        'tracker': TrackerProcessor, 'reconstructor': ReconstructorProcessor,
        'registrar': RegistrarProcessor, 'scene_flow': SceneFlowProcessor}
    out = {}
    for s in stages:
        if s not in classes:
            raise ValueError(f'pipeline stage {s!r}: expected one of {list(STAGES)}')
        out[s] = classes[s](factory, params.get(s, NODE_PARAMS[s]()))
    return out


def process_bag(in_path: str | Path, out_path: str | Path, stages: Sequence[str] = STAGES,
                params: Mapping[str, Params] | None = None, storage: str = 'mcap',
                progress: bool = True, copy_inputs: bool = False,
                pipelined: bool | str = False) -> ProcessReport:
    """Run ``stages`` over the bag and write their outputs (and optionally the inputs).
    ``pipelined``: each stage in its own process (True or ``'processes'``) or thread
    (``'threads'``) (:mod:`.pipelined`; the same outputs, less wall time where cores are
    free)."""
    if pipelined and len(set(stages)) > 1:
        from .pipelined import process_bag_pipelined
        return process_bag_pipelined(in_path, out_path, stages, params, storage, progress,
                                     copy_inputs, 'processes' if pipelined is True
                                     else str(pipelined))
    procs = make_processors(stages, params)
    for proc in procs.values():
        proc.stats.timing_window = None          # the report's percentiles cover every call
        expect_frames(proc, in_path, stages)
    report, total = new_report(in_path)
    io_s = report.io_s
    t0, c0 = time.perf_counter(), time.process_time()

    def feed(topic: str, msg: Any, stamp: int, writer: BagWriter) -> None:
        for stage, kind in ROUTES.get(topic, []):
            if stage not in procs:
                continue
            try:
                outputs = procs[stage].handle(kind, msg)
            except MessageError as err:
                report.failures.append({'stage': stage, 'topic': topic, 'stamp_ns': stamp,
                                        'error': str(err)})
                continue
            for out_topic, out_type, out_msg in outputs:
                emit(out_topic, out_type, out_msg, stamp, writer, stage)

    def emit(topic: str, msgtype: str, msg: Any, stamp: int, writer: BagWriter,
             stage: str) -> None:
        out_stamp = stamp_ns(msg.header) if hasattr(msg, 'header') else stamp
        tw = time.perf_counter()
        try:
            writer.write(topic, msgtype, msg, out_stamp)
        except Exception as err:  # noqa: BLE001 -- e.g. a value the CDR type cannot hold
            io_s['write'] += time.perf_counter() - tw
            report.failures.append({'stage': f'{stage} (write)', 'topic': topic,
                                    'stamp_ns': out_stamp,
                                    'error': f'{type(err).__name__}: {err}'})
            return
        io_s['write'] += time.perf_counter() - tw
        report.outputs[topic] = report.outputs.get(topic, 0) + 1
        feed(topic, msg, out_stamp, writer)

    with BagWriter(out_path, storage) as writer:
        mark = time.perf_counter()
        for i, m in enumerate(read_messages(in_path, damage=report.damage)):
            io_s['read'] += time.perf_counter() - mark
            report.inputs[m.topic] = report.inputs.get(m.topic, 0) + 1
            if copy_inputs:
                tw = time.perf_counter()
                writer.write(m.topic, m.msgtype, m.raw, m.stamp_ns)
                io_s['write'] += time.perf_counter() - tw
            msg = read_input(m, report)
            if msg is not None:
                feed(m.topic, msg, m.stamp_ns, writer)
            if progress:
                _progress(i + 1, total, t0)
            mark = time.perf_counter()
        if 'reconstructor' in procs:
            rec = procs['reconstructor']
            assert isinstance(rec, ReconstructorProcessor)
            tf, cf = time.perf_counter(), time.process_time()
            try:
                flushed = rec.flush()
            except Exception as err:  # noqa: BLE001 -- contained like every message
                flushed = []
                report.failures.append({'stage': 'reconstructor (flush)', 'topic': '',
                                        'stamp_ns': 0, 'error': f'{type(err).__name__}: {err}'})
            else:
                rec.stats.add_time('flush', time.perf_counter() - tf, time.process_time() - cf)
            for out_topic, out_type, out_msg in flushed:
                emit(out_topic, out_type, out_msg, 0, writer, 'reconstructor')
        if 'scene_flow' in procs:       # clouds still waiting: object pose, look-ahead
            sf = procs['scene_flow']
            assert isinstance(sf, SceneFlowProcessor)
            for out_topic, out_type, out_msg in sf.flush():
                emit(out_topic, out_type, out_msg, 0, writer, 'scene_flow')
    if progress:
        sys.stderr.write('\n')
    report.seconds = time.perf_counter() - t0
    report.cpu_s = time.process_time() - c0
    report.timing = {name: {kind: t.summary() for kind, t in proc.stats.timing.items()}
                     for name, proc in procs.items()}
    report.status = {name: st for name, proc in procs.items() if (st := proc.status())}
    return report


def _progress(done: int, total: int, t0: float) -> None:
    if done != total and done % 10:
        return
    frac = done / max(total, 1)
    bar = '#' * int(30 * frac)
    rate = done / max(time.perf_counter() - t0, 1e-9)
    sys.stderr.write(f'\r[{bar:<30}] {done}/{total} messages  {rate:.0f} msg/s')
    sys.stderr.flush()


def write_report(report: ProcessReport, path: str | Path) -> None:
    Path(path).write_text(json.dumps(report.as_dict(), indent=2))
