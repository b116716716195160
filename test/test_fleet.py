"""`nrsfm-ros process BAG BAG ... --out DIR --jobs N` (one worker process per bag, a combined
report, failures isolated) and the per-stage timing of `process` and /diagnostics."""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from nrsfm_ros.cli import main
from nrsfm_ros.fleet import BagJob, process_bags, run_job
from nrsfm_ros.io.bag import bag_info, read_messages

FRAMES = 12


@pytest.fixture(scope='module')
def bags(tmp_path_factory) -> dict[str, Path]:
    from nrsfm_ros.io.sequence_bag import write_sequence_bag
    from nrsfm_ros.io.synth import SynthConfig, generate
    d = tmp_path_factory.mktemp('fleet')
    for i, surface in enumerate(('face', 'flag')):
        write_sequence_bag(generate(SynthConfig(surface=surface, width=64, height=48,
                                                frames=FRAMES, fps=20.0, seed=i)), d / f'good{i}')
    shutil.copytree(d / 'good0', d / 'trunc')          # damaged: the MCAP cut at 60 %
    mcap = next((d / 'trunc').glob('*.mcap'))
    os.truncate(mcap, int(mcap.stat().st_size * 0.6))
    (d / 'garbage').mkdir()                              # not a bag at all
    (d / 'garbage' / 'garbage.mcap').write_bytes(os.urandom(4096))
    return {'dir': d, 'good0': d / 'good0', 'good1': d / 'good1', 'trunc': d / 'trunc',
            'garbage': d / 'garbage'}


def test_many_bags_one_report_failures_isolated(bags, tmp_path, capsys):
    out = tmp_path / 'out'
    order = ['good0', 'garbage', 'trunc', 'good1']
    rc = main(['process', *(str(bags[k]) for k in order), '--out', str(out), '--jobs', '2',
               '--pipeline', 'tracker,reconstructor', '--no-progress'])
    stdout = capsys.readouterr().out
    assert rc == 2                                       # a failed bag: non-zero
    rep = json.loads((out / 'report.json').read_text())
    assert rep['jobs'] == 2 and rep['wall_s'] > 0
    by = {Path(b['bag']).name: b for b in rep['bags']}
    assert [Path(b['bag']).name for b in rep['bags']] == order     # input order kept
    for k in ('good0', 'good1'):
        b = by[k]
        assert b['status'] == 'ok' and b['error'] == '' and b['failures'] == 0
        assert b['frames_in'] == FRAMES and b['frames_out'] == FRAMES
        assert b['report']['timing']['tracker']['image']['calls'] == FRAMES
        counts = bag_info(out / k)['topics']
        assert counts['nrsfm/tracks']['count'] == FRAMES
        assert counts['nrsfm/points']['count'] == FRAMES
    g = by['garbage']
    assert g['status'] == 'failed' and 'not a bag' in g['error'] and g['frames_in'] == 0
    t = by['trunc']
    read = sum(1 for _ in read_messages(bags['trunc'], ['camera/image_raw'], damage=[]))
    assert t['status'] == 'failed' and 'is damaged' in t['error'] and 'lost' in t['error']
    assert 3 <= read < FRAMES and t['frames_in'] == read
    assert bag_info(out / 'trunc')['topics']['nrsfm/tracks']['count'] == read   # kept
    tot = rep['total']
    assert (tot['bags'], tot['ok'], tot['failed'], tot['frames_in']) == (4, 2, 2,
                                                                        2 * FRAMES + read)
    assert rep['throughput']['frames_per_s'] > 0 and rep['throughput']['bags_per_s'] > 0
    # the summary names every bag, the failed ones with their error line
    assert '4 bag(s) on 2 worker(s)' in stdout and '2 ok' in stdout and '2 failed' in stdout
    lines = {name: line for line in stdout.splitlines()
             for name in order if line.strip().startswith(name + ' ')}
    assert 'not a bag' in lines['garbage'] and 'is damaged' in lines['trunc']
    assert lines['good1'].split()[1] == 'ok'


def test_many_bags_all_good_exit_zero_and_report_path(bags, tmp_path, capsys):
    report = tmp_path / 'combined.json'
    rc = main(['process', str(bags['good0']), str(bags['good1']), '--out', str(tmp_path / 'o'),
               '--jobs', '2', '--pipeline', 'tracker', '--report', str(report)])
    stdout = capsys.readouterr().out
    assert rc == 0
    assert '[1/2]' in stdout and '[2/2]' in stdout          # one line per finished bag
    rep = json.loads(report.read_text())
    assert [b['status'] for b in rep['bags']] == ['ok', 'ok']
    assert all(b['frames_out'] == FRAMES for b in rep['bags'])
    assert not (tmp_path / 'o' / 'report.json').exists()


@pytest.mark.parametrize('case, text', [
    ('same_name', 'would both write'),
    ('exists', 'exist'),
    ('jobs', '--jobs 0'),
])
def test_many_bags_bad_input_one_error_line(bags, tmp_path, capsys, case, text):
    out = tmp_path / 'o'
    args = ['process', str(bags['good0']), str(bags['good1']), '--out', str(out)]
    if case == 'same_name':
        shutil.copytree(bags['good1'], tmp_path / 'elsewhere' / 'good0')
        args[2] = str(tmp_path / 'elsewhere' / 'good0')
    elif case == 'exists':
        (out / 'good1').mkdir(parents=True)
    else:
        args += ['--jobs', '0']
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and err.startswith('error:') and text in err
    assert not (out / 'good0').exists()                  # nothing processed


def crash_on_good1(job: BagJob) -> dict:
    """A worker that dies (as a segfault would) on one bag; module level: it is pickled."""
    if Path(job.bag).name == 'good1':
        os._exit(7)
    return run_job(job)


def test_dead_worker_fails_only_its_bag(bags, tmp_path):
    done: list[str] = []
    rep = process_bags([bags['good0'], bags['good1']], tmp_path / 'o', ['tracker'], jobs=2,
                       worker=crash_on_good1, on_done=lambda e: done.append(Path(e['bag']).name))
    st = {Path(b['bag']).name: b for b in rep.bags}
    assert st['good1']['status'] == 'failed' and 'worker process died' in st['good1']['error']
    assert st['good0']['status'] == 'ok' and st['good0']['frames_out'] == FRAMES
    assert sorted(done) == ['good0', 'good1'] and rep.exit_code() == 2


def test_single_bag_report_has_per_stage_timing(bags, tmp_path, capsys):
    report = tmp_path / 'r.json'
    rc = main(['process', str(bags['good0']), '--out', str(tmp_path / 'o'), '--report',
               str(report), '--no-progress'])
    stdout = capsys.readouterr().out
    assert rc == 0
    rep = json.loads(report.read_text())
    timing = rep['timing']
    assert set(timing) == {'tracker', 'reconstructor', 'registrar', 'scene_flow'}
    for stage, kind in (('tracker', 'image'), ('reconstructor', 'tracks'),
                        ('registrar', 'points'), ('scene_flow', 'points')):
        t = timing[stage][kind]
        assert t['calls'] == FRAMES, (stage, kind)
        assert 0 < t['p50_ms'] <= t['p90_ms'] <= t['max_ms']
        assert t['mean_ms'] <= t['max_ms'] and t['total_s'] > 0
    assert timing['reconstructor']['flush']['calls'] == 1
    assert set(rep['io_s']) == {'read', 'deserialize', 'write'}
    # the stages' own time never exceeds the run's
    stage_s = sum(t['total_s'] for kinds in timing.values() for t in kinds.values())
    assert stage_s + sum(rep['io_s'].values()) <= rep['seconds'] * 1.01 + 0.01
    assert 'per-stage processing time' in stdout
    assert any(line.split()[:2] == ['tracker', 'image'] for line in stdout.splitlines())


def test_diagnostics_carry_per_kind_timing():
    from nrsfm_ros.io.msgtypes import RosbagsFactory
    from nrsfm_ros.processing import Stats, diagnostics_msg
    stats = Stats(timing_window=3)
    for ms in (5.0, 1.0, 2.0, 3.0, 4.0):           # the window keeps 2, 3, 4
        stats.add_time('tracks', ms / 1e3)
    t = stats.timing['tracks'].summary()
    assert t['calls'] == 5 and t['max_ms'] == 5.0 and t['mean_ms'] == 3.0
    assert t['p50_ms'] == 3.0
    msg = diagnostics_msg(RosbagsFactory(), 'reconstructor', stats, 0)
    values = {kv.key: kv.value for kv in msg.status[0].values}
    assert values['tracks_calls'] == '5' and values['tracks_ms_p50'] == '3.00'
    assert values['tracks_ms_max'] == '5.00' and values['tracks_ms_mean'] == '3.00'
    assert 'tracks_ms_p90' in values


def test_node_diagnostics_time_each_input_kind_and_publishing(rclpy_context):
    import numpy as np

    from nrsfm_ros.io import pointcloud2 as pc2
    from nrsfm_ros.io.msgtypes import RclpyFactory
    from nrsfm_ros.nodes.common import ProcessorNode
    from nrsfm_ros.processing import SceneFlowProcessor, diagnostics_msg
    node = ProcessorNode('scene_flow', SceneFlowProcessor,
                         [('scene_flow', 'sensor_msgs/msg/PointCloud2')], context=rclpy_context)
    try:
        X = np.random.default_rng(0).normal(size=(200, 3)).astype(np.float32) + [0, 0, 4]
        for f in range(3):
            cloud = pc2.to_msg({'x': X[:, 0], 'y': X[:, 1], 'z': X[:, 2] + 0.01 * f,
                                'track_id': np.arange(200, dtype=np.uint32)},
                               RclpyFactory(), 10 ** 9 + f * 10 ** 8, 'cam')
            node._on_message('points', cloud)         # what the worker thread does
        timing = node.processor.stats.timing
        assert timing['points'].count == 3 and timing['publish'].count == 3
        values = {kv.key: kv.value for kv in diagnostics_msg(
            node.factory, 'scene_flow', node.processor.stats, 0).status[0].values}
        assert values['points_calls'] == '3' and float(values['points_ms_p50']) > 0
        assert float(values['publish_ms_max']) >= float(values['publish_ms_p50']) > 0
        node.publish_diagnostics()                    # the node's own 1 Hz path
    finally:
        node.destroy_node()
