from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from nrsfm_ros.cli import EXAMPLES, main
from nrsfm_ros.io.export import write_ply


def run(*args):
    return subprocess.run([sys.executable, '-m', 'nrsfm_ros.cli', *args], capture_output=True,
                          text=True, timeout=120)


@pytest.mark.parametrize('verb', sorted(EXAMPLES))
def test_every_verb_has_help_with_example(verb, capsys):
    with pytest.raises(SystemExit) as e:
        main([verb, '--help'])
    assert e.value.code == 0
    assert 'example: nrsfm-ros' in capsys.readouterr().out


def test_a_verb_builds_only_its_own_flags_so_a_light_verb_starts_light():
    # the parser of `topic` must not import the core (params pulls in SciPy and numba: ~1.4 s
    # of every cold start), and every verb's own parser keeps all of its flags
    code = ('import sys; from nrsfm_ros.cli import _parser; '
            "a = _parser('topic').parse_args(['topic', 'list']); "
            "assert a.seconds is None and a.verb == 'topic'; "
            "print(sorted(m for m in sys.modules if m.startswith('nrsfm_ros.')))")
    r = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert 'nrsfm_ros.params' not in r.stdout and 'nrsfm_ros.core' not in r.stdout, r.stdout
    import argparse

    from nrsfm_ros.cli import _parser

    def flags(p: argparse.ArgumentParser, verb: str) -> set[str]:
        sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
        return {o for a in sub.choices[verb]._actions for o in a.option_strings}
    whole = _parser()
    for verb in EXAMPLES:
        assert flags(_parser(verb), verb) == flags(whole, verb), verb


@pytest.mark.parametrize('args, text', [
    (['reconstruct', 'missing.npz', '--out', 'x.npz'], 'does not exist'),
    (['register', 'a.ply', 'b.ply', '--out', 'x.npz'], 'does not exist'),
    (['synth', '--size', 'big', '--out', 'x'], '--size'),
    (['track', 'missing_dir', '--out', 'x.npz'], 'does not exist'),
])
def test_bad_input_one_error_line(args, text, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    r = run(*args)
    assert r.returncode != 0
    lines = [line for line in r.stderr.strip().splitlines() if line]
    assert len(lines) == 1 and lines[0].startswith('error:') and text in lines[0]


def test_reconstruct_and_register_files(tmp_path):
    sys.path.insert(0, str(__import__('pathlib').Path(__file__).parent))
    from tests_helpers import low_rank_sequence
    W, S, _ = low_rank_sequence(K=1, F=20, P=80)
    np.savez(tmp_path / 'tracks.npz', W=W)
    assert main(['reconstruct', str(tmp_path / 'tracks.npz'), '--method', 'rigid', '--out',
                 str(tmp_path / 'shapes.npz')]) == 0
    out = np.load(tmp_path / 'shapes.npz')
    assert out['S'].shape == (20, 80, 3) and out['R'].shape == (20, 3, 3)
    np.savez(tmp_path / 'bad.npz', X=W)
    assert main(['reconstruct', str(tmp_path / 'bad.npz'), '--out', 'y.npz']) == 2
    X = S[0]
    write_ply(tmp_path / 'a.ply', X)
    np.save(tmp_path / 'b.npy', X + [0.1, 0, 0])
    assert main(['register', str(tmp_path / 'a.ply'), str(tmp_path / 'b.npy'), '--out',
                 str(tmp_path / 'r.npz')]) == 0
    T = np.load(tmp_path / 'r.npz')['T_target_source']
    np.testing.assert_allclose(T[:3, 3], [0.1, 0, 0], atol=1e-6)


def test_track_on_image_folder(tmp_path):
    import cv2

    from nrsfm_ros.io.synth import SynthConfig, generate
    seq = generate(SynthConfig(surface='face', width=96, height=72, frames=5))
    for i, im in enumerate(seq.images):
        cv2.imwrite(str(tmp_path / f'{i:03d}.png'), im[..., ::-1])
    assert main(['track', str(tmp_path), '--out', str(tmp_path / 't.npz')]) == 0
    d = np.load(tmp_path / 't.npz')
    assert d['W'].shape[0] == 10 and d['V'].shape == (5, d['W'].shape[1])
    assert d['O'].shape == d['V'].shape and d['track_ids'].size == d['W'].shape[1]
    assert main(['track', str(tmp_path), '--method', 'reference', '--streaming', '--out',
                 str(tmp_path / 'r.npz')]) == 0
    r = np.load(tmp_path / 'r.npz')
    assert 'O' not in r.files and r['W'].shape[0] == 10
    # the tracks follow the ground truth of the synthetic face
    ids = d['track_ids'].astype(np.int64)
    common, ia, ib = np.intersect1d(ids, seq.track_ids, return_indices=True)
    err = np.hypot(d['W'][0::2, ia] - seq.W[0::2, ib], d['W'][1::2, ia] - seq.W[1::2, ib])
    assert common.size > 100 and np.median(err[seq.V[:, ib] > 0]) < 0.5


def test_track_rejects_bad_options(tmp_path, capsys):
    import cv2
    for i in range(3):
        cv2.imwrite(str(tmp_path / f'{i}.png'), np.full((40, 50), 100 + i, np.uint8))
    assert main(['track', str(tmp_path), '--rank', '-1', '--out', str(tmp_path / 't.npz')]) != 0
    err = capsys.readouterr().err
    assert 'rank=-1' in err and err.count('\n') == 1


def test_reconstruct_default_bmm_and_register_cpd(tmp_path, capsys):
    sys.path.insert(0, str(__import__('pathlib').Path(__file__).parent))
    from tests_helpers import low_rank_sequence

    from nrsfm_ros.core.metrics import e3d_frobenius
    W, S, _ = low_rank_sequence(K=1, F=30, P=60)
    np.savez(tmp_path / 'tracks.npz', W=W)
    assert main(['reconstruct', str(tmp_path / 'tracks.npz'), '--out',
                 str(tmp_path / 's.npz')]) == 0
    assert e3d_frobenius(np.load(tmp_path / 's.npz')['S'], S, 'global') < 1e-6
    V = np.ones((30, 60))
    V[5:9, :10] = 0
    np.savez(tmp_path / 'occluded.npz', W=W, V=V)
    assert main(['reconstruct', str(tmp_path / 'occluded.npz'), '--method', 'cdf', '--out',
                 str(tmp_path / 'c.npz')]) == 0
    assert np.load(tmp_path / 'c.npz')['S'].shape == S.shape
    capsys.readouterr()
    assert main(['reconstruct', str(tmp_path / 'occluded.npz'), '--method', 'cdf', '--rank',
                 '2', '--out', str(tmp_path / 'c.npz')]) != 0
    assert '--rank does not apply' in capsys.readouterr().err
    assert main(['reconstruct', str(tmp_path / 'tracks.npz'), '--method', 'hdsm', '--rank', '4',
                 '--out', str(tmp_path / 'h.npz')]) == 0
    assert 'hdsm, rank 4' in capsys.readouterr().out and (tmp_path / 'h.npz').exists()
    X = S[0]
    write_ply(tmp_path / 'a.ply', X)
    np.save(tmp_path / 'b.npy', X + [0.1, 0, 0])
    assert main(['register', str(tmp_path / 'a.ply'), str(tmp_path / 'b.npy'), '--method',
                 'cpd-rigid', '--w', '0.05', '--out', str(tmp_path / 'r.npz')]) == 0
    T = np.load(tmp_path / 'r.npz')['T_target_source']
    np.testing.assert_allclose(T[:3, 3], [0.1, 0, 0], atol=1e-3)
    capsys.readouterr()
    assert main(['register', str(tmp_path / 'a.ply'), str(tmp_path / 'b.npy'), '--w', '0.1',
                 '--out', str(tmp_path / 'x.npz')]) != 0
    assert 'applies to the cpd methods' in capsys.readouterr().err


def test_register_global_init_and_big_endian_ply(tmp_path, capsys):
    """`register --init global` recovers a 150-degree pose that the centroid start misses; the
    source is a binary big-endian PLY (as the horse scan of ../shared/data ships)."""
    from scipy.spatial.transform import Rotation

    from nrsfm_ros.core.metrics import rotation_error_deg
    rng = np.random.default_rng(0)
    u, v = rng.uniform(-1, 1, (2, 3000))
    X = np.stack([u, v, 0.5 * np.sin(2 * u) * np.cos(1.5 * v) + 0.3 * u * v + 0.2 * u ** 2], 1)
    header = ('ply\nformat binary_big_endian 1.0\nelement vertex 3000\nproperty float x\n'
              'property float y\nproperty float z\nproperty uchar red\nend_header\n').encode()
    body = np.zeros(3000, [('x', '>f4'), ('y', '>f4'), ('z', '>f4'), ('red', 'u1')])
    body['x'], body['y'], body['z'] = X.T
    (tmp_path / 'a.ply').write_bytes(header + body.tobytes())
    R = Rotation.from_rotvec(np.radians(150) * np.array([0.0, 0.6, 0.8])).as_matrix()
    np.save(tmp_path / 'b.npy', X @ R.T)
    for init, ok in (('centroid', False), ('global', True)):
        assert main(['register', str(tmp_path / 'a.ply'), str(tmp_path / 'b.npy'), '--method',
                     'icp-point-to-plane', '--voxel', '0.05', '--init', init, '--out',
                     str(tmp_path / 'r.npz')]) == 0
        T = np.load(tmp_path / 'r.npz')['T_target_source']
        assert (rotation_error_deg(T[:3, :3], R) < 1.0) == ok
    capsys.readouterr()
    assert main(['register', str(tmp_path / 'a.ply'), str(tmp_path / 'b.npy'), '--method',
                 'cpd-rigid', '--init', 'global', '--out', str(tmp_path / 'r.npz')]) != 0
    assert 'applies to the icp methods' in capsys.readouterr().err


def test_reconstruct_va(tmp_path, capsys):
    sys.path.insert(0, str(__import__('pathlib').Path(__file__).parent))
    from tests_helpers import low_rank_sequence
    W, S, _ = low_rank_sequence(K=2, F=20, P=150)
    np.savez(tmp_path / 'tracks.npz', W=W)
    assert main(['reconstruct', str(tmp_path / 'tracks.npz'), '--method', 'va', '--out',
                 str(tmp_path / 'v.npz')]) == 0
    assert np.load(tmp_path / 'v.npz')['S'].shape == S.shape
    capsys.readouterr()
    assert main(['reconstruct', str(tmp_path / 'tracks.npz'), '--method', 'va', '--rank', '3',
                 '--out', str(tmp_path / 'v.npz')]) != 0
    assert '--rank does not apply' in capsys.readouterr().err


def test_reconstruct_camera_model_flags(tmp_path, capsys):
    from conftest import shared_data

    from nrsfm_ros.core.metrics import e3d_normalized
    d = np.load(shared_data('nrsfm', 'pickup.npz'))
    np.savez(tmp_path / 'pickup.npz', W=d['W'])
    errs = {}
    for flags in ([], ['--camera-model', 'free'], ['--camera-model', 'orbit', '--smooth', '0']):
        capsys.readouterr()
        assert main(['reconstruct', str(tmp_path / 'pickup.npz'), '--out',
                     str(tmp_path / 's.npz')] + flags) == 0
        out = capsys.readouterr().out
        assert ('free cameras' if 'free' in flags else 'orbit cameras') in out
        r = np.load(tmp_path / 's.npz')
        errs[' '.join(flags)] = e3d_normalized(np.einsum('fji,fpj->fpi', r['R'], r['S']),
                                               d['S_world'])
    # measured metric A: orbit + trajectory prior 0.029, orbit alone 0.053, free 0.11
    assert errs[''] < 0.04 < errs['--camera-model orbit --smooth 0'] < errs['--camera-model free']
    assert main(['reconstruct', str(tmp_path / 'pickup.npz'), '--method', 'rigid', '--smooth',
                 '10', '--out', str(tmp_path / 'x.npz')]) != 0
    assert '--smooth applies to --method bmm and cdf' in capsys.readouterr().err


def test_reconstruct_robust_rigid_flag(tmp_path, capsys):
    """`--robust K` fits the rigid factorisation with Huber weights: on rigid tracks with 5%
    gross errors its shape is far closer to the truth than the plain fit; other methods refuse
    the flag."""
    sys.path.insert(0, str(__import__('pathlib').Path(__file__).parent))
    from tests_helpers import low_rank_sequence

    from nrsfm_ros.core.metrics import e3d_frobenius
    W, S, _ = low_rank_sequence(K=1)
    F, P = W.shape[0] // 2, W.shape[1]
    rng = np.random.default_rng(1)
    bad = rng.uniform(size=(F, P)) < 0.05
    W = (W.reshape(F, 2, P) + 8 * W.std() * bad[:, None] * rng.normal(size=(F, 2, P)))
    np.savez(tmp_path / 't.npz', W=W.reshape(2 * F, P))
    errs = []
    for flags in ([], ['--robust', '1.5'], ['--robust', '2', '--robust-loss', 'cauchy']):
        assert main(['reconstruct', str(tmp_path / 't.npz'), '--method', 'rigid', '--out',
                     str(tmp_path / 's.npz')] + flags) == 0
        errs.append(e3d_frobenius(np.load(tmp_path / 's.npz')['S'], S, 'frame', scale=True))
    assert errs[1] < 0.2 * errs[0] and errs[2] < 0.2 * errs[1]     # cauchy: redescending
    capsys.readouterr()
    assert main(['reconstruct', str(tmp_path / 't.npz'), '--method', 'bmm', '--robust', '1',
                 '--out', str(tmp_path / 'x.npz')]) != 0
    assert '--robust applies to --method rigid' in capsys.readouterr().err
    assert main(['reconstruct', str(tmp_path / 't.npz'), '--method', 'rigid', '--robust-loss',
                 'cauchy', '--out', str(tmp_path / 'x.npz')]) != 0
    assert '--robust-loss needs --robust K' in capsys.readouterr().err
    from nrsfm_ros.core.nrsfm.factorization import ROBUST_LOSSES   # the flag's choices
    for loss in ROBUST_LOSSES:
        assert main(['reconstruct', str(tmp_path / 't.npz'), '--method', 'rigid', '--robust',
                     '2', '--robust-loss', loss, '--out', str(tmp_path / 'x.npz')]) == 0
    with pytest.raises(SystemExit):
        main(['reconstruct', str(tmp_path / 't.npz'), '--method', 'rigid', '--robust', '2',
              '--robust-loss', 'tukey', '--out', str(tmp_path / 'x.npz')])


def test_reconstruct_every_method_on_tracks_with_visibility(tmp_path, capsys):
    """`nrsfm-ros reconstruct --method M` works for every method on a W/V npz."""
    sys.path.insert(0, str(__import__('pathlib').Path(__file__).parent))
    from tests_helpers import low_rank_sequence

    from nrsfm_ros.core.nrsfm import METHODS
    W, S, _ = low_rank_sequence(K=2, F=24, P=90)
    V = np.ones((24, 90))
    V[6:10, :12] = 0
    np.savez(tmp_path / 'tracks.npz', W=W, V=V)
    for method in sorted(METHODS):
        out = tmp_path / f'{method}.npz'
        assert main(['reconstruct', str(tmp_path / 'tracks.npz'), '--method', method, '--out',
                     str(out)]) == 0, method
        r = np.load(out)
        assert r['S'].shape == S.shape and np.isfinite(r['S']).all(), method
        assert f'({method}, rank' in capsys.readouterr().out


def test_reconstruct_dspr_and_synth_periodic(tmp_path, capsys):
    """`synth --periodic N` repeats the deformation; `reconstruct --method dspr` on its tracks
    compresses the recurring states and beats the static baseline computed here."""
    from nrsfm_ros.core.metrics import e3d_frobenius
    out = tmp_path / 'p'
    assert main(['synth', '--size', '96x72', '--frames', '60', '--periodic', '20',
                 '--camera-motion', '30', '--out', str(out)]) == 0
    gt = np.load(tmp_path / 'p.npz')
    S_w = gt['S_world']
    assert np.abs(S_w[0] - S_w[20]).max() < 1e-9 and np.abs(S_w[0] - S_w[10]).max() > 1e-3
    np.savez(tmp_path / 'tracks.npz', W=gt['W'], V=np.maximum(gt['V'], 1e-3))
    capsys.readouterr()
    assert main(['reconstruct', str(tmp_path / 'tracks.npz'), '--method', 'dspr',
                 '--batch-frames', '20', '--out', str(tmp_path / 'd.npz')]) == 0
    assert '(dspr, prior from 20 frames, compression' in capsys.readouterr().out
    r = np.load(tmp_path / 'd.npz')
    assert r['S'].shape == gt['S'].shape and np.isfinite(r['S']).all()
    assert float(r['compression']) > 1.5
    static = e3d_frobenius(np.repeat(gt['S'][:1], 60, axis=0), gt['S'], 'frame', scale=True)
    # measured: 0.045 against static 0.067 (planar on the whole sequence 0.049)
    assert e3d_frobenius(r['S'], gt['S'], 'frame', scale=True) < 0.8 * static
    for bad, text in ((['--method', 'dspr', '--batch-frames', '2'], '--batch-frames 2'),
                      (['--method', 'dspr', '--rank', '3'], '--rank does not apply'),
                      (['--method', 'bmm', '--batch-frames', '10'], 'applies to --method dspr')):
        assert main(['reconstruct', str(tmp_path / 'tracks.npz'), *bad, '--out',
                     str(tmp_path / 'x.npz')]) == 2
        assert text in capsys.readouterr().err
    assert main(['synth', '--periodic', '2', '--out', str(tmp_path / 'q')]) == 2
    assert '--periodic' in capsys.readouterr().err
