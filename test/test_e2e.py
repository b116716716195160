"""End to end on a short synthetic bag: offline `process` and the live graph over real DDS."""
from __future__ import annotations

import json

import pytest

from nrsfm_ros.cli import main
from nrsfm_ros.demo import run_live, summarise
from nrsfm_ros.io.sequence_bag import write_sequence_bag
from nrsfm_ros.io.synth import SynthConfig, generate

# seed 1 gives a camera that barely rotates in the first window, where the orthographic depth
# is unobservable and the current factorisation fails (noted on issue 3); seed 0 rotates.
CFG = SynthConfig(surface='flag', width=192, height=144, frames=30, fps=10.0, seed=0)


@pytest.fixture(scope='module')
def sample(tmp_path_factory):
    root = tmp_path_factory.mktemp('e2e')
    seq = generate(CFG)
    write_sequence_bag(seq, root / 'in')
    return root, seq


def test_offline_process_bag(sample):
    root, seq = sample
    code = main(['process', str(root / 'in'), '--out', str(root / 'offline'), '--report',
                 str(root / 'report.json'), '--no-progress'])
    assert code == 0
    report = json.loads((root / 'report.json').read_text())
    assert report['failures'] == []
    for topic in ('nrsfm/tracks', 'nrsfm/points', 'registration/aligned', 'scene_flow/points'):
        assert report['outputs'][topic] == CFG.frames
    s = summarise(root / 'offline', seq, root / 'offline_render')
    assert s['e3d_B_frame_scaled'] < 0.15  # measured 0.08 on the 60-frame sample


def test_live_graph(sample):
    root, seq = sample
    live = run_live(root / 'in', root / 'live', CFG.frames, rate=1.0, timeout=40,
                    overrides={'tracker': {'reliable': True},
                               'reconstructor': {'mean_depth': CFG.distance}})
    assert not live['graph_exit']
    s = summarise(root / 'live', seq, root / 'render')
    for topic in ('nrsfm/tracks', 'nrsfm/points', 'registration/aligned', 'scene_flow/points',
                  'registration/transform', 'scene_flow/markers'):
        assert s['outputs'].get(topic) == CFG.frames, topic
    assert s['e3d_B_frame_scaled'] < 0.15
    assert set(s['latency_ms']) == {'tracker', 'reconstructor', 'registrar', 'scene_flow'}
    assert (root / 'render' / 'points_000.ply').exists()
