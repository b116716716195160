"""`nrsfm-ros process BAG BAG ... --out DIR --jobs N` (one worker process per bag, a combined
report, failures isolated) and the per-stage timing of `process` and /diagnostics."""
from __future__ import annotations

import json
import os
import shutil
import sys
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


def where_am_i(job: BagJob) -> dict:
    """A worker that reports its parent process, whether the pipeline was imported before the
    job arrived and its BLAS thread variable (module level: it is pickled)."""
    import sys
    return {'bag': job.bag, 'out': job.out, 'status': 'ok', 'ppid': os.getppid(),
            'preloaded': 'nrsfm_ros.pipeline' in sys.modules,
            'blas': os.environ.get('OPENBLAS_NUM_THREADS')}


def when_started(job: BagJob) -> dict:
    """A worker that only notes when it took its job (module level: it is pickled)."""
    import time
    return {'bag': job.bag, 'out': job.out, 'status': 'ok', 'started_ns': time.monotonic_ns()}


def test_largest_bags_are_handed_out_first_report_in_input_order(tmp_path):
    """Longest-processing-time first: the workers take the bags by size, largest first
    (ties in input order), and the report lists them in input order."""
    from nrsfm_ros.fleet import input_bytes, largest_first
    sizes = {'small': 1000, 'big': 50_000, 'mid': 9000, 'mid2': 9000}
    paths = []
    for name, n in sizes.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / 'x.mcap').write_bytes(b'0' * n)
        (tmp_path / name / 'metadata.yaml').write_bytes(b'1' * 10)
        paths.append(tmp_path / name)
    assert input_bytes(tmp_path / 'big') == 50_010
    assert input_bytes(tmp_path / 'big' / 'x.mcap') == 50_000
    assert input_bytes(tmp_path / 'nothing') == 0
    jobs = [BagJob(i, str(p), str(tmp_path / 'out' / p.name), ('tracker',))
            for i, p in enumerate(paths)]
    assert [Path(j.bag).name for j in largest_first(jobs)] == ['big', 'mid', 'mid2', 'small']
    rep = process_bags(paths, tmp_path / 'out', ['tracker'], jobs=1, worker=when_started)
    assert [Path(b['bag']).name for b in rep.bags] == list(sizes)
    order = sorted(rep.bags, key=lambda b: b['started_ns'])
    assert [Path(b['bag']).name for b in order] == ['big', 'mid', 'mid2', 'small']


def test_workers_fork_from_a_server_that_imported_the_pipeline(bags, tmp_path, monkeypatch):
    import multiprocessing.forkserver

    import nrsfm_ros.fleet as fleet
    for v in fleet.THREAD_VARS:
        monkeypatch.delenv(v, raising=False)
    # a server an earlier test started (maybe with other variables) goes: this one starts it
    getattr(multiprocessing.forkserver._forkserver, '_stop', lambda: None)()
    monkeypatch.setattr(fleet, '_forkserver_env', None)
    rep = process_bags([bags['good0'], bags['good1']], tmp_path / 'a', ['tracker'], jobs=2,
                       worker=where_am_i)
    for b in rep.bags:      # not children of this process: of the fork server
        assert b['ppid'] != os.getpid() and b['preloaded'] and b['blas'] == '1'
    # other thread settings than the server's: spawned workers, with those settings
    rep = process_bags([bags['good0']], tmp_path / 'b', ['tracker'], jobs=1, threads=2,
                       worker=where_am_i)
    assert rep.bags[0]['ppid'] == os.getpid() and rep.bags[0]['blas'] == '2'


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
    # one stage at a time: the stages' times then add up within the run's (the default runs
    # the stages at once, whose times overlap; test_pipelined checks its report's calls)
    rc = main(['process', str(bags['good0']), '--out', str(tmp_path / 'o'), '--report',
               str(report), '--no-progress', '--stage-workers', 'none'])
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
        assert t['mean_ms'] <= t['max_ms'] and t['total_s'] > 0 and t['cpu_s'] > 0
    assert timing['reconstructor']['flush']['calls'] == 1
    # CPU time per stage: within the run's CPU time (and the tracker's work is CPU-bound)
    stage_cpu = sum(t['cpu_s'] for kinds in timing.values() for t in kinds.values())
    assert stage_cpu <= rep['cpu_s'] * 1.01 + 0.01
    assert timing['tracker']['image']['cpu_s'] > 0.3 * timing['tracker']['image']['total_s']
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
    from rclpy.parameter import Parameter
    node = ProcessorNode('scene_flow', SceneFlowProcessor,
                         [('scene_flow', 'sensor_msgs/msg/PointCloud2')], context=rclpy_context,
                         parameter_overrides=[Parameter('lookahead', value=0)])  # 1 out a cloud
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


# ------------------------------------------------------------------ --ray (optional extra)

def _tcp_listeners_of_ray() -> list[tuple[str, str]]:
    """(process, local address) of every listening TCP socket of a Ray process on this machine
    (raylet, gcs_server, ray::* workers and agents, Ray's Python services)."""
    inodes: dict[str, str] = {}
    for proc in Path('/proc').iterdir():
        if not proc.name.isdigit() or int(proc.name) == os.getpid():
            continue
        try:
            cmd = (proc / 'cmdline').read_bytes().replace(b'\0', b' ').decode(errors='replace')
            exe = Path(cmd.split(' ')[0]).name
            if not (exe in ('raylet', 'gcs_server') or cmd.startswith('ray::')
                    or '/site-packages/ray/' in cmd):
                continue
            for fd in (proc / 'fd').iterdir():
                link = os.readlink(fd)
                if link.startswith('socket:['):
                    inodes[link[8:-1]] = cmd.split(' ')[0]
        except OSError:
            continue
    out = []
    for table in ('/proc/net/tcp', '/proc/net/tcp6'):
        for line in Path(table).read_text().splitlines()[1:]:
            f = line.split()
            if f[3] == '0A' and f[9] in inodes:          # LISTEN
                out.append((inodes[f[9]], f[1]))
    return out


def _is_loopback(hex_addr: str) -> bool:
    ip = hex_addr.split(':')[0]
    if len(ip) == 8:                                      # IPv4, little-endian 127.x.x.x
        return ip.endswith('7F')
    return ip in ('00000000000000000000000001000000',       # ::1
                  '0000000000000000FFFF00000100007F')       # ::ffff:127.0.0.1


@pytest.fixture(scope='module')
def ray_head():
    """A Ray head started like a cluster's (ray start --head), on 127.0.0.1 only, 2 CPUs."""
    import signal
    import socket
    import subprocess
    import sys
    import time
    pytest.importorskip('ray')
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        port = s.getsockname()[1]
    env = dict(os.environ, RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER='0', RAY_USAGE_STATS_ENABLED='0')
    proc = subprocess.Popen(
        [sys.executable, '-m', 'ray.scripts.scripts', 'start', '--head', '--block',
         '--node-ip-address=127.0.0.1', f'--port={port}', '--num-cpus=2',
         '--include-dashboard=false', '--object-store-memory=83886080', '--disable-usage-stats'],
        env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        end = time.monotonic() + 60
        while True:
            try:
                socket.create_connection(('127.0.0.1', port), timeout=1).close()
                break
            except OSError:
                if proc.poll() is not None or time.monotonic() > end:
                    pytest.fail(f'ray start --head exited ({proc.returncode}) or timed out')
                time.sleep(0.2)
        yield f'127.0.0.1:{port}'
    finally:
        os.killpg(proc.pid, signal.SIGKILL)      # the head, its raylet, agents and workers
        proc.wait()


SAME = ('status', 'error', 'frames_in', 'frames_out', 'messages_in', 'failures',
        'first_failures')


def test_ray_cluster_report_matches_jobs(bags, ray_head, tmp_path, capsys):
    """2 good bags + 1 broken on a Ray cluster: the same per-bag report and byte-identical
    output bags as --jobs 2, the broken bag failed alone, every Ray socket on loopback."""
    order = ['good0', 'garbage', 'good1']
    common = ['--pipeline', 'tracker,reconstructor', '--no-progress']
    args = ['process', *(str(bags[k]) for k in order)]
    assert main([*args, '--out', str(tmp_path / 'jobs'), '--jobs', '2', *common]) == 2
    assert main([*args, '--out', str(tmp_path / 'ray'), f'--ray={ray_head}', *common]) == 2
    stdout = capsys.readouterr().out
    jobs = json.loads((tmp_path / 'jobs' / 'report.json').read_text())
    rep = json.loads((tmp_path / 'ray' / 'report.json').read_text())
    assert jobs['engine'] == 'processes' and 'ray' not in jobs
    assert rep['engine'] == 'ray' and rep['jobs'] == 2
    assert rep['ray']['address'] == ray_head and rep['ray']['nodes'] == ['127.0.0.1']
    assert rep['ray']['cpus'] == 2 and not rep['ray']['reused']
    assert [Path(b['bag']).name for b in rep['bags']] == order
    for a, b in zip(jobs['bags'], rep['bags']):
        assert {k: a[k] for k in SAME} == {k: b[k] for k in SAME}, a['bag']
    assert [b['status'] for b in rep['bags']] == ['ok', 'failed', 'ok']
    assert 'not a bag' in rep['bags'][1]['error']
    assert rep['total'] == {**jobs['total'], 'worker_s': rep['total']['worker_s'],
                            'worker_cpu_s': rep['total']['worker_cpu_s']}
    assert all(b['pid'] != os.getpid() for b in rep['bags'])      # ran in Ray workers
    for k in ('good0', 'good1'):
        want = list(read_messages(tmp_path / 'jobs' / k))
        got = list(read_messages(tmp_path / 'ray' / k))
        assert len(got) >= 2 * FRAMES and got == want, k             # same bytes
    assert f'3 bag(s) on 2 worker(s) (Ray {ray_head}: 1 node(s), 2 CPU(s))' in stdout
    listeners = _tcp_listeners_of_ray()
    assert listeners and all(_is_loopback(a) for _, a in listeners), listeners


def timed_job(job: BagJob) -> dict:
    """run_job with its wall-clock interval (module level: it is pickled to the workers)."""
    import time
    t0 = time.time()
    entry = run_job(job)
    entry['interval'] = (t0, time.time())
    return entry


def test_ray_cluster_jobs_caps_bags_at_a_time(bags, ray_head, tmp_path):
    """--jobs 1 on a 2-CPU cluster: one bag at a time (the tasks' intervals never overlap)."""
    import sys

    from ray import cloudpickle
    here = sys.modules[timed_job.__module__]           # Ray workers cannot import test modules
    cloudpickle.register_pickle_by_value(here)
    try:
        rep = process_bags([bags['good0'], bags['good1'], bags['garbage']], tmp_path / 'o',
                           ['tracker'], jobs=1, worker=timed_job, ray=ray_head)
    finally:
        cloudpickle.unregister_pickle_by_value(here)
    assert rep.jobs == 1 and [b['status'] for b in rep.bags] == ['ok', 'ok', 'failed']
    spans = sorted(b['interval'] for b in rep.bags)
    assert all(a[1] <= b[0] for a, b in zip(spans, spans[1:])), spans


def test_ray_local_instance_dead_worker_fails_only_its_bag(bags, tmp_path):
    """No address: a private Ray instance with --jobs CPUs on 127.0.0.1 (checked while it
    runs), stopped afterwards; a Ray worker that dies fails its own bag only."""
    pytest.importorskip('ray')
    import ray
    seen: list[list[tuple[str, str]]] = []

    def on_done(entry: dict) -> None:
        seen.append(_tcp_listeners_of_ray())

    import sys
    from ray import cloudpickle
    here = sys.modules[crash_on_good1.__module__]      # Ray workers cannot import test modules
    cloudpickle.register_pickle_by_value(here)
    try:
        rep = process_bags([bags['good0'], bags['good1']], tmp_path / 'o', ['tracker'], jobs=2,
                           worker=crash_on_good1, on_done=on_done, ray='')
    finally:
        cloudpickle.unregister_pickle_by_value(here)
    d = rep.as_dict()
    assert d['engine'] == 'ray' and d['ray']['address'] == 'local'
    assert d['ray']['nodes'] == ['127.0.0.1'] and d['ray']['cpus'] == 2 and d['jobs'] == 2
    st = {Path(b['bag']).name: b for b in rep.bags}
    assert st['good1']['status'] == 'failed' and 'worker process died' in st['good1']['error']
    assert st['good0']['status'] == 'ok' and st['good0']['frames_out'] == FRAMES
    assert rep.exit_code() == 2 and len(seen) == 2
    assert all(ls and all(_is_loopback(a) for _, a in ls) for ls in seen), seen
    assert not ray.is_initialized()                       # the private instance is gone
    assert os.environ.get('RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER') is None   # restored


def test_ray_flag_parses_with_and_without_address(bags):
    from nrsfm_ros.cli import _parser
    p = _parser()
    assert p.parse_args(['process', 'a', 'b', '--out', 'o', '--ray']).ray == ''
    assert p.parse_args(['process', 'a', '--out', 'o', '--ray=h:1']).ray == 'h:1'
    assert p.parse_args(['process', 'a', '--out', 'o']).ray is None


@pytest.mark.parametrize('case, text', [
    ('missing', "Ray is not installed: pip install 'nrsfm_ros[ray]'"),
    ('path', 'that is a path, not a Ray address'),
    ('malformed', 'expected HOST:PORT of the Ray head'),
    ('refused', 'could not connect to the Ray cluster at 127.0.0.1:'),
])
def test_ray_bad_setup_one_error_line(bags, tmp_path, capsys, monkeypatch, case, text):
    import socket
    import sys
    out = tmp_path / 'o'
    args = ['process', str(bags['good0']), '--out', str(out), '--pipeline', 'tracker']
    if case == 'missing':
        monkeypatch.setitem(sys.modules, 'ray', None)     # import ray -> ImportError
        args.append('--ray')
    elif case == 'path':
        args[1:2] = ['--ray', str(bags['good0'])]         # the bag taken as the address
        args.insert(1, str(bags['good1']))
    elif case == 'malformed':
        args.append('--ray=nohost')
    else:
        with socket.socket() as s:                         # a port nobody listens on
            s.bind(('127.0.0.1', 0))
            port = s.getsockname()[1]
        args.append(f'--ray=127.0.0.1:{port}')
    if case != 'missing':
        pytest.importorskip('ray')
    assert main(args) == 2
    err = capsys.readouterr().err
    err_lines = [line for line in err.splitlines() if line.startswith('error:')]
    assert len(err_lines) == 1 and text in err_lines[0], err
    assert not (out / 'good0').exists()                   # nothing processed


WARM_CHECK = r"""
import json, os, sys
import numpy as np
if os.environ.get('WARM') == '1':
    import nrsfm_ros.warm  # noqa: F401 -- the import warms
from numba.core.registry import CPUDispatcher
from nrsfm_ros.core.nrsfm.stream import StreamNRSfM


def signatures():
    return {f'{n}.{k}': {str(s) for s in v.signatures}
            for n, m in list(sys.modules.items()) if n.startswith('nrsfm_ros')
            for k, v in vars(m).items() if isinstance(v, CPUDispatcher)}


def rot_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


before = signatures()
rng = np.random.default_rng(0)
focal, principal, F, P = 500.0, np.array([320.0, 240.0]), 20, 300
methods = []
for relief in (0.4, 0.0):       # a curved surface (bmm) and a flat one (planar)
    X = np.c_[rng.uniform(-0.5, 0.5, (P, 2)), rng.uniform(-relief / 2, relief / 2, P)]
    s = StreamNRSfM(mode='batch', batch_frames=F, projection='perspective')
    s.set_intrinsics(focal, principal)
    for f, a in enumerate(np.radians(np.linspace(-20, 20, F))):
        Y = X @ rot_y(a).T + [0.05, -0.03, 2.0]
        uv = focal * Y[:, :2] / Y[:, 2:] + principal + rng.normal(0, 0.2, (P, 2))
        s.push(np.arange(P), uv, np.ones(P))
    methods.append(s.last_method)
after = signatures()
print(json.dumps({'methods': methods, 'new': sorted({
    k.rsplit('.', 1)[1] for k in after if after[k] - before.get(k, set())})}))
"""


def test_the_warm_up_loads_every_kernel_a_batch_solve_uses():
    """nrsfm_ros.warm (preloaded by the fleet's fork server, so forked workers do not each
    load the kernels on their first bag: bench_fleet 4 bags, --jobs 1 6.5 -> 4.8 s, --jobs 2
    4.3 -> 2.7 s; imported in a thread by the reconstructor at start) loads every numba kernel
    of a perspective batch solve (bmm and planar) with the argument types the solvers pass:
    in a fresh process, the solves after it add no specialisation; without it they do."""
    import subprocess
    from nrsfm_ros.fleet import FORKSERVER_PRELOAD
    out = {}
    for warm in ('1', '0'):
        env = dict(os.environ, WARM=warm)
        run = subprocess.run([sys.executable, '-c', WARM_CHECK], env=env, capture_output=True,
                             text=True, timeout=300)
        assert run.returncode == 0, run.stderr
        out[warm] = json.loads(run.stdout.strip().splitlines()[-1])
    assert out['1']['methods'] == ['bmm', 'planar'] == out['0']['methods']
    assert out['1']['new'] == []
    for kernel in ('data_step', 'fista_psd_trace', 'bundle_normal_equations',
                   'bundle_residuals', 'frame_error_table', 'pose_normal_equations',
                   'weak_image_error'):
        assert kernel in out['0']['new'], out['0']['new']
    assert 'nrsfm_ros.warm' in FORKSERVER_PRELOAD


def test_the_reconstructor_warms_the_kernels_in_a_thread_at_start():
    from nrsfm_ros.processing import _WARMING, ReconstructorProcessor
    from nrsfm_ros.io.msgtypes import RosbagsFactory
    ReconstructorProcessor(RosbagsFactory())
    assert _WARMING.is_set() or 'nrsfm_ros.warm' in sys.modules
