"""Bad input on the command line: every case is one ``error:`` line and a non-zero exit, never
a traceback or a silent success; a damaged bag is processed as far as it reads."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from nrsfm_ros.cli import main
from nrsfm_ros.io import image as img_io
from nrsfm_ros.io.bag import BagWriter, bag_info, read_messages
from nrsfm_ros.io.export import write_ply
from nrsfm_ros.io.msgtypes import RosbagsFactory


def truncate_bag(src: Path, dst: Path, fraction: float) -> None:
    shutil.copytree(src, dst)
    mcap = next(dst.glob('*.mcap'))
    os.truncate(mcap, int(mcap.stat().st_size * fraction))


@pytest.fixture(scope='module')
def inputs(tmp_path_factory) -> dict[str, Path]:
    from nrsfm_ros.io.sequence_bag import write_sequence_bag
    from nrsfm_ros.io.synth import SynthConfig, generate
    d = tmp_path_factory.mktemp('bad')
    write_sequence_bag(generate(SynthConfig(surface='face', width=64, height=48, frames=12)),
                       d / 'bag')
    truncate_bag(d / 'bag', d / 'trunc', 0.6)
    cv2.imwrite(str(d / 'img.png'), np.zeros((8, 8), np.uint8))
    for name, text in (('yaml_bad', 'tracker: {ros__parameters: [1, 2'),
                       ('yaml_type', 'tracker:\n  ros__parameters:\n    stride: two\n'),
                       ('yaml_shape', '- just\n- a list\n')):
        (d / name).mkdir()
        (d / name / 'tracker.yaml').write_text(text)
    (d / 'empty_dir').mkdir()
    np.savez(d / 'w.npz', W=np.zeros((20, 50)))
    (d / 'trunc.npz').write_bytes((d / 'w.npz').read_bytes()[:300])
    X = np.random.default_rng(0).normal(size=(100, 3))
    write_ply(d / 'a.ply', X)
    (d / 'trunc.ply').write_bytes((d / 'a.ply').read_bytes()[:-600])
    ascii_ply = ('ply\nformat ascii 1.0\nelement vertex 100\nproperty float x\n'
                 'property float y\nproperty float z\nend_header\n'
                 + '\n'.join(' '.join(map(str, r)) for r in X[:60]) + '\n')
    (d / 'trunc_ascii.ply').write_text(ascii_ply)
    return {'dir': d, 'bag': d / 'bag', 'trunc': d / 'trunc', 'png': d / 'img.png'}


# (args with {placeholders}, text expected in the error line); run in-process
TABLE = [
    (['process', '{png}', '--out', '{out}', '--no-progress'], 'not a bag'),
    (['export', '{png}', '--out', '{out}'], 'not a bag'),
    (['process', '{dir}/nope', '--out', '{out}', '--no-progress'], 'does not exist'),
    (['process', '{bag}', '--out', '{out}', '--params', '{dir}/yaml_bad', '--no-progress'],
     'not valid YAML'),
    (['process', '{bag}', '--out', '{out}', '--params', '{dir}/yaml_type', '--no-progress'],
     "stride='two': expected a int"),
    (['process', '{bag}', '--out', '{out}', '--params', '{dir}/yaml_shape', '--no-progress'],
     'expected "tracker: ros__parameters'),
    (['process', '{bag}', '--out', '{out}', '--params', '/nonexistent', '--no-progress'],
     'not a folder'),
    (['process', '{bag}', '--out', '{out}', '--params', '{dir}/empty_dir', '--no-progress'],
     'no <node>.yaml file'),
    (['process', '{bag}', '--out', '{out}', '--pipeline', ',', '--no-progress'],
     'name at least one'),
    (['process', '{bag}', '--out', '{out}', '--pipeline', 'tracker,magic', '--no-progress'],
     "unknown stage(s) ['magic']"),
    (['export', '{bag}', '--out', '{out}', '--topic', 'camera/image_raw'],
     'is a sensor_msgs/msg/Image, not a PointCloud2'),
    (['export', '{bag}', '--out', '{out}', '--topic', 'no/such'], "'no/such' is not in"),
    (['export', '{trunc}', '--out', '{out}', '--topic', 'ground_truth/points'], 'is damaged'),
    (['record', 'x', '--out', '{out}', '--duration', '-1'], '--duration -1.0: must be >= 0'),
    (['reconstruct', '{dir}/trunc.npz', '--out', '{out}.npz'], 'not a readable .npz'),
    (['reconstruct', '{dir}/img.png', '--out', '{out}.npz'], 'not a readable .npz'),
    (['register', '{dir}/trunc.ply', '{dir}/a.ply', '--out', '{out}.npz'], 'truncated'),
    (['register', '{dir}/trunc_ascii.ply', '{dir}/a.ply', '--out', '{out}.npz'], 'truncated'),
    (['register', '{png}', '{dir}/a.ply', '--out', '{out}.npz'], ''),
]


@pytest.mark.parametrize('args, text', TABLE, ids=[' '.join(a[:1] + [t]) for a, t in TABLE])
def test_bad_input_table_one_error_line(args, text, inputs, tmp_path, capsys):
    values = {k: str(v) for k, v in inputs.items()} | {'out': str(tmp_path / 'out')}
    rc = main([a.format(**values) for a in args])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert rc != 0, err
    assert len(lines) == 1 and lines[0].startswith('error:') and text in lines[0], err


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, '-m', 'nrsfm_ros.cli', *args], capture_output=True,
                          text=True, timeout=60, env=dict(os.environ))


def test_replay_bad_input_one_error_line(inputs):
    """The DDS verb in its own process: not a bag, unknown topic, damaged bag."""
    for args, text in ((['replay', str(inputs['png'])], 'not a bag'),
                       (['replay', str(inputs['bag']), '--topics', 'no/such'], 'is not in'),
                       (['replay', str(inputs['trunc']), '--rate', '20',
                         '--wait-for-subscribers', '0'], 'is damaged')):
        r = cli(*args)
        lines = [line for line in r.stderr.splitlines() if line.strip()]
        assert r.returncode != 0 and len(lines) == 1, r.stderr
        assert lines[0].startswith('error:') and text in lines[0], r.stderr
        assert 'Traceback' not in r.stderr


def test_process_damaged_bag_keeps_everything_read(inputs, tmp_path, capsys):
    """A truncated MCAP: outputs and report for every frame read, one line naming the loss."""
    out, report = tmp_path / 'out', tmp_path / 'r.json'
    rc = main(['process', str(inputs['trunc']), '--out', str(out), '--report', str(report),
               '--no-progress'])
    err = capsys.readouterr().err
    assert rc != 0 and err.count('\n') == 1 and 'is damaged' in err and 'lost' in err
    frames = sum(1 for m in read_messages(inputs['trunc'], ['camera/image_raw'], damage=[]))
    assert 3 <= frames < 12
    rep = json.loads(report.read_text())
    assert rep['inputs']['camera/image_raw'] == frames and rep['damage']
    assert bag_info(out)['topics']['nrsfm/tracks']['count'] == frames


def test_process_blank_frame_mid_stream(inputs, tmp_path, capsys):
    """A blank frame in the middle is skipped and reported; every other frame is processed."""
    fac = RosbagsFactory()
    msgs = list(read_messages(inputs['bag'], ['camera/image_raw']))
    from nrsfm_ros.io.bag import deserialize
    with BagWriter(tmp_path / 'blank') as w:
        for i, m in enumerate(msgs):
            msg = deserialize(m.raw, m.msgtype)
            if i == 6:
                msg = img_io.array_to_image(np.zeros((48, 64, 3), np.uint8), 'rgb8', fac,
                                            m.stamp_ns, 'cam')
            w.write(m.topic, m.msgtype, msg, m.stamp_ns)
    rc = main(['process', str(tmp_path / 'blank'), '--out', str(tmp_path / 'o'),
               '--pipeline', 'tracker', '--report', str(tmp_path / 'r.json'), '--no-progress'])
    out = capsys.readouterr().out
    assert rc == 1 and 'untrackable frame' in out
    rep = json.loads((tmp_path / 'r.json').read_text())
    assert rep['outputs']['nrsfm/tracks'] == len(msgs) - 1 and len(rep['failures']) == 1
