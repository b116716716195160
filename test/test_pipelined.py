"""`process` with each stage in its own process or thread (nrsfm_ros.pipelined): the same output
bag as the one-process pipeline, message for message; a dead stage and Ctrl-C end it cleanly."""
from __future__ import annotations

import multiprocessing
import os
import time
from pathlib import Path

import pytest

from nrsfm_ros import pipelined
from nrsfm_ros.io.bag import read_messages
from nrsfm_ros.pipeline import STAGES, process_bag
from nrsfm_ros.pipelined import chain_order, outputs_first, process_bag_pipelined


@pytest.fixture(scope='module')
def bag(tmp_path_factory) -> Path:
    from nrsfm_ros.io.sequence_bag import write_sequence_bag
    from nrsfm_ros.io.synth import SynthConfig, generate
    d = tmp_path_factory.mktemp('pipelined') / 'in'
    write_sequence_bag(generate(SynthConfig(surface='flag', width=96, height=72, frames=24,
                                            fps=20.0, seed=1)), d)
    return d


def _messages(path: Path) -> dict[str, list[tuple[int, bytes]]]:
    out: dict[str, list[tuple[int, bytes]]] = {}
    for m in read_messages(path):
        out.setdefault(m.topic, []).append((m.stamp_ns, bytes(m.raw)))
    return out


@pytest.mark.parametrize('workers', [True, 'threads'])
def test_pipelined_writes_the_same_messages_as_one_process(bag, tmp_path, workers):
    seq = process_bag(bag, tmp_path / 'seq', progress=False, copy_inputs=True)
    par = process_bag(bag, tmp_path / 'par', progress=False, copy_inputs=True,
                      pipelined=workers)
    a, b = _messages(tmp_path / 'seq'), _messages(tmp_path / 'par')
    assert set(a) == set(b) and len(a) > 10
    for topic in a:       # per topic the same messages in the same order, byte for byte
        assert a[topic] == b[topic], topic
    assert par.outputs == seq.outputs and par.inputs == seq.inputs
    assert par.failures == seq.failures == []
    assert par.status == seq.status
    calls = {s: {k: t['calls'] for k, t in kinds.items()} for s, kinds in par.timing.items()}
    assert calls == {s: {k: t['calls'] for k, t in kinds.items()}
                     for s, kinds in seq.timing.items()}
    assert par.cpu_s > 0 and par.seconds > 0


def test_process_cli_runs_the_stages_at_once_by_default(bag, tmp_path, capsys, monkeypatch):
    import nrsfm_ros.pipelined as pl
    from nrsfm_ros.cli import main
    used = []
    run = pl.process_bag_pipelined

    def spy(*a, **k):
        used.append(a[7] if len(a) > 7 else k.get('workers'))
        return run(*a, **k)
    monkeypatch.setattr(pl, 'process_bag_pipelined', spy)
    report = tmp_path / 'r.json'
    assert main(['process', str(bag), '--out', str(tmp_path / 'o'),
                 '--pipeline', 'tracker,reconstructor', '--no-progress', '--report',
                 str(report)]) == 0
    out = capsys.readouterr().out
    assert 'nrsfm/points: 24' in out and 'nrsfm/tracks: 24' in out
    import json
    assert set(json.loads(report.read_text())['timing']) == {'tracker', 'reconstructor'}
    assert used == ['threads']
    # none: one stage at a time (the pipelined module not used), the same outputs
    assert main(['process', str(bag), '--out', str(tmp_path / 'n'), '--stage-workers', 'none',
                 '--pipeline', 'tracker,reconstructor', '--no-progress']) == 0
    assert 'nrsfm/points: 24' in capsys.readouterr().out and used == ['threads']


def test_process_cli_stage_processes(bag, tmp_path, capsys):
    from nrsfm_ros.cli import main
    assert main(['process', str(bag), '--out', str(tmp_path / 'o'),
                 '--stage-workers', 'processes', '--pipeline', 'tracker,reconstructor',
                 '--no-progress']) == 0
    assert 'nrsfm/points: 24' in capsys.readouterr().out


def test_stage_workers_are_for_one_bag(bag, tmp_path, capsys):
    from nrsfm_ros.cli import main
    rc = main(['process', str(bag), str(bag), '--out', str(tmp_path / 'o'),
               '--stage-workers', 'threads'])
    assert rc != 0 and '--stage-workers threads: one bag only' in capsys.readouterr().err
    assert not (tmp_path / 'o').exists()


def test_order_rule_follows_the_routes():
    chain = chain_order(['scene_flow', 'tracker', 'registrar', 'reconstructor'])
    assert chain == list(STAGES)
    # the tracker's tracks of an image go down before the image (scene_flow takes both, and
    # the one-process pipeline walks the tracker's outputs first) ...
    assert outputs_first('tracker', 'camera/image_raw', chain)
    # ... the reconstructor's outputs of an image (mode hdmnet) after it: scene_flow comes
    # before the reconstructor in the image's routes
    assert not outputs_first('reconstructor', 'camera/image_raw', chain)


class _Dies:
    """Wraps a processor: the process exits (as a crash would) at its 5th tracks message, its
    outputs before it sent (a crash loses what its queue's feeder thread had not sent yet)."""

    def __init__(self, proc):
        self.proc, self.n = proc, 0
        self.stats = proc.stats

    def handle(self, kind, msg):
        if kind == 'tracks':
            self.n += 1
            if self.n == 5:
                time.sleep(1.0)
                os._exit(3)
        return self.proc.handle(kind, msg)

    def status(self):
        return self.proc.status()


def test_a_dead_stage_is_reported_and_the_run_ends(bag, tmp_path, monkeypatch):
    if 'fork' not in multiprocessing.get_all_start_methods():
        pytest.skip('needs the fork start method (the patch must reach the stage process)')
    real = pipelined.make_processors

    def dying(stages, params=None, factory=None):
        procs = real(stages, params, factory)
        return {s: _Dies(p) if s == 'reconstructor' else p for s, p in procs.items()}
    monkeypatch.setattr(pipelined, 'make_processors', dying)
    monkeypatch.setattr(pipelined, '_context', lambda: multiprocessing.get_context('fork'))
    rep = process_bag_pipelined(bag, tmp_path / 'o', progress=False)
    died = [f for f in rep.failures if f['stage'] == 'reconstructor']
    assert len(died) == 1 and 'process died (exit code 3)' in died[0]['error']
    # what got through was written: the stages after it were sent the end, and reported
    assert rep.outputs['nrsfm/tracks'] == 4 and rep.outputs.get('nrsfm/points', 0) < 24
    assert set(rep.timing) == {'registrar', 'scene_flow'}
    assert not multiprocessing.active_children()


@pytest.mark.parametrize('workers', ['processes', 'threads'])
def test_ctrl_c_ends_every_stage(bag, tmp_path, monkeypatch, workers):
    real = pipelined.read_messages

    def interrupted(path, *a, **k):
        for i, m in enumerate(real(path, *a, **k)):
            if i == 40:
                raise KeyboardInterrupt
            yield m
    monkeypatch.setattr(pipelined, 'read_messages', interrupted)
    with pytest.raises(KeyboardInterrupt):
        process_bag_pipelined(bag, tmp_path / 'o', progress=False, workers=workers)
    assert not multiprocessing.active_children() and _stage_threads() == []


def test_no_fork_from_a_process_with_other_threads(bag, tmp_path, rclpy_context):
    """A process with DDS threads (rclpy) forks no stage: its locks could be copied held (a
    child deadlocked in the full suite); the stages come from a clean fork server instead and
    the run ends with the same outputs."""
    import rclpy
    node = rclpy.create_node('pipelined_probe', context=rclpy_context)
    try:
        assert not pipelined._single_threaded()
        assert pipelined._context().get_start_method() != 'fork'
        rep = process_bag_pipelined(bag, tmp_path / 'o', ('tracker', 'reconstructor'),
                                    progress=False)
    finally:
        node.destroy_node()
    assert rep.outputs['nrsfm/points'] == 24 and rep.failures == []
    assert not multiprocessing.active_children()


def _stage_threads() -> list:
    import threading
    return [t for t in threading.enumerate() if t.name.startswith('nrsfm-') and
            t.name != 'nrsfm-writer']


class _Raises(_Dies):
    """Wraps a processor: an error no processor contains, at its 5th tracks message."""

    def handle(self, kind, msg):
        if kind == 'tracks':
            self.n += 1
            if self.n == 5:
                raise RuntimeError('stage bug')
        return self.proc.handle(kind, msg)


def test_a_failed_stage_thread_is_reported_and_every_thread_ends(bag, tmp_path, monkeypatch):
    real = pipelined.make_processors

    def failing(stages, params=None, factory=None):
        procs = real(stages, params, factory)
        return {s: _Raises(p) if s == 'reconstructor' else p for s, p in procs.items()}
    monkeypatch.setattr(pipelined, 'make_processors', failing)
    rep = process_bag_pipelined(bag, tmp_path / 'o', progress=False, workers='threads')
    died = [f for f in rep.failures if f['stage'] == 'reconstructor']
    assert len(died) == 1 and 'thread failed (RuntimeError: stage bug)' in died[0]['error']
    assert rep.outputs['nrsfm/tracks'] == 4 and rep.outputs.get('nrsfm/points', 0) < 24
    assert set(rep.timing) == {'registrar', 'scene_flow'}
    assert _stage_threads() == []


def test_workers_must_be_named(bag, tmp_path):
    with pytest.raises(ValueError, match="workers='fibres'"):
        process_bag_pipelined(bag, tmp_path / 'o', progress=False, workers='fibres')


def test_the_reconstructor_is_told_the_bags_length(bag, tmp_path, monkeypatch):
    """``process`` tells the reconstructor how many frames the bag holds (its camera images
    where the tracker runs, else its tracks), one process or pipelined alike, and with a
    batch that waits for the bag's last frames both write the same clouds."""
    from nrsfm_ros.core.nrsfm.stream import StreamNRSfM
    from nrsfm_ros.params import ReconstructorParams
    from nrsfm_ros.pipeline import expected_frames
    assert expected_frames(bag, ['tracker', 'reconstructor']) == 24
    assert expected_frames(bag, ['reconstructor']) == 0        # no tracks in a camera bag
    seen: list[int] = []
    original = StreamNRSfM.expect

    def expect(self, frames):
        seen.append(frames)
        original(self, frames)
    monkeypatch.setattr(StreamNRSfM, 'expect', expect)
    params = {'reconstructor': ReconstructorParams(batch_frames=16)}   # 8 left: it waits
    stages = ['tracker', 'reconstructor']
    out = {w: tmp_path / str(w) for w in (False, 'threads')}
    for w, path in out.items():
        process_bag(bag, path, stages=stages, params=params, progress=False, pipelined=w)
    assert seen == [24, 24]
    a, b = (_messages(p)['nrsfm/points'] for p in out.values())
    assert len(a) == 24 and a == b
