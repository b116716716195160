"""`nrsfm-ros evaluate`: synth -> process -> evaluate prints the numbers the benchmarks compute
(evaluation.score on the same bag, as bench/bench_pipeline.py does) and the demo summary holds;
frames it cannot match are listed, never scored; bad input is one `error:` line."""
from __future__ import annotations

import dataclasses
import json
import struct
import zlib

import numpy as np
import pytest

from nrsfm_ros.cli import main
from nrsfm_ros.demo import summarise
from nrsfm_ros.evaluation import load_ground_truth, read_clouds, score
from nrsfm_ros.io.bag import BagWriter, deserialize, read_messages, serialize

FRAMES = 20
DROPPED = (3, 7)        # nrsfm/points clouds left out of the damaged copy
RESTAMPED = 11          # and one whose stamp is moved off every ground-truth frame


@pytest.fixture(scope='module')
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp('evaluate')
    assert main(['synth', '--size', '96x72', '--frames', str(FRAMES), '--camera-motion', '30',
                 '--out', str(root / 'in')]) == 0
    assert (root / 'in.npz').exists()           # the ground truth synth writes beside its bag
    assert main(['process', str(root / 'in'), '--out', str(root / 'out'), '--no-progress']) == 0
    return root, load_ground_truth(root / 'in.npz')


def evaluate(capsys, *argv: str) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(['evaluate', *map(str, argv)])
    out, err = capsys.readouterr()
    return code, out, err


def is_png(path) -> tuple[int, int]:
    """(width, height) of a PNG whose signature and IHDR chunk (with its CRC) are valid."""
    data = path.read_bytes()
    assert data[:8] == b'\x89PNG\r\n\x1a\n', 'not a PNG signature'
    length, kind = struct.unpack('>I4s', data[8:16])
    assert kind == b'IHDR' and length == 13
    crc = struct.unpack('>I', data[16 + length:20 + length])[0]
    assert crc == zlib.crc32(data[12:16 + length]), 'IHDR CRC mismatch'
    assert data.endswith(b'IEND\xaeB`\x82'), 'no IEND chunk'
    return struct.unpack('>II', data[16:24])


def test_prints_the_benchmark_numbers(run, capsys):
    root, seq = run
    code, out, err = evaluate(capsys, root / 'out', '--ground-truth', root / 'in.npz',
                              '--json', root / 'e.json', '--plot', root / 'e.png')
    assert code == 0, err
    d = json.loads((root / 'e.json').read_text())
    bench = score(read_clouds(root / 'out', seq.stamps_ns), seq).summary()
    assert d['e3d_B_frame_scaled'] == bench['e3d']
    assert d['e3d_static_oracle'] == bench['static'] and d['e3d_flat_plane'] == bench['flat']
    assert d['ratio_static'] == pytest.approx(bench['e3d'] / bench['static'])
    assert d['frames_in'] == FRAMES and d['frames_scored'] == FRAMES
    assert d['frames_unscored'] == [] and d['unscored'] == []
    assert [p['frame'] for p in d['per_frame']] == list(range(FRAMES))
    assert np.mean([p['e3d'] for p in d['per_frame']]) == pytest.approx(bench['e3d'], rel=1e-12)
    for line in (f"{bench['e3d']:.4f}", f"{bench['static']:.4f}", f"{bench['flat']:.4f}"):
        assert line in out
    assert 'static oracle' in out and 'flat plane' in out
    assert 0 <= d['frames_depth_reflected'] <= FRAMES
    assert f"reflected against the truth (metric B forgives them) {d['frames_depth_reflected']}" \
        in out
    assert f'{FRAMES} of {FRAMES} frames scored' in out
    # every output topic of the graph is counted, as in the demo summary
    from nrsfm_ros.demo import OUTPUT_TOPICS
    counted = out.split('frames out: ')[1].split('\n')[0]
    assert [c.rsplit(' ', 1)[0] for c in counted.split(', ')] == list(OUTPUT_TOPICS)
    # registration and scene flow: the same numbers as the demo summary of the same bag
    demo = summarise(root / 'out', seq, root / 'render')
    for key in ('e3d_B_frame_scaled', 'frames_depth_reflected', 'registration_rmse_m',
                'registration_rotation_error_deg_median', 'scene_flow_relative_epe'):
        assert d[key] == demo[key], key
    assert d['scene_flow_frames_scored'] == FRAMES - 1
    assert f"relative EPE {d['scene_flow_relative_epe']:.3f}" in out
    assert f"RMSE to the frame-0 ground truth {d['registration_rmse_m']:.4f} m" in out
    w, h = is_png(root / 'e.png')
    assert w >= 400 and h >= 200


def test_missing_frames_are_listed_not_scored(run, capsys):
    root, seq = run
    gaps = root / 'gaps'
    moved = int(seq.stamps_ns[RESTAMPED]) + 1
    with BagWriter(gaps) as w:
        for m in read_messages(root / 'out'):
            raw = m.raw
            if m.topic == 'nrsfm/points':
                msg = deserialize(m.raw, m.msgtype)
                f = int(np.flatnonzero(seq.stamps_ns == msg.header.stamp.sec * 10**9
                                       + msg.header.stamp.nanosec)[0])
                if f in DROPPED:
                    continue
                if f == RESTAMPED:
                    stamp = dataclasses.replace(msg.header.stamp,
                                                nanosec=msg.header.stamp.nanosec + 1)
                    msg = dataclasses.replace(msg, header=dataclasses.replace(msg.header,
                                                                              stamp=stamp))
                    raw = serialize(msg, m.msgtype)
            w.write(m.topic, m.msgtype, raw, m.stamp_ns)
    code, out, err = evaluate(capsys, gaps, '--ground-truth', root / 'in.npz',
                              '--json', root / 'gaps.json', '--plot', root / 'gaps.png')
    assert code == 0, err
    d = json.loads((root / 'gaps.json').read_text())
    missing = sorted((*DROPPED, RESTAMPED))
    assert d['frames_unscored'] == missing
    assert [u['frame'] for u in d['unscored']] == missing
    assert all(u['reason'] == 'no cloud' for u in d['unscored'])
    assert d['frames_scored'] == FRAMES - len(missing)
    assert not {p['frame'] for p in d['per_frame']} & set(missing)   # never a score
    assert d['unmatched_stamps'] == {'nrsfm/points': [moved]}
    assert d['e3d_B_frame_scaled'] == score(read_clouds(gaps, seq.stamps_ns), seq).summary()['e3d']
    for f in missing:
        assert f'frame {f} (stamp {int(seq.stamps_ns[f])}): no cloud' in out
    assert f'{FRAMES - len(missing)} of {FRAMES} frames scored' in out
    assert str(moved) in out
    is_png(root / 'gaps.png')


def one_error_line(code: int, err: str, name: str) -> None:
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith('error: '), (code, err)
    assert name in lines[0], (name, lines[0])


def test_errors_name_the_file(run, capsys, tmp_path):
    root, seq = run
    gt = root / 'in.npz'
    code, _, err = evaluate(capsys, tmp_path / 'no_bag', '--ground-truth', gt)
    one_error_line(code, err, 'no_bag')
    # ground truth of the wrong kind: a tracks file, a text file, the bag folder itself
    np.savez(tmp_path / 'tracks.npz', W=np.zeros((4, 5)), V=np.ones((2, 5)))
    (tmp_path / 'notes.txt').write_text('not an archive\n')
    for wrong in (tmp_path / 'tracks.npz', tmp_path / 'notes.txt', root / 'in'):
        code, _, err = evaluate(capsys, root / 'out', '--ground-truth', wrong)
        one_error_line(code, err, str(wrong))
    # no matching frames: the same ground truth with every stamp moved
    d = dict(np.load(gt))
    d['stamps_ns'] = d['stamps_ns'] + 5
    np.savez(tmp_path / 'shifted.npz', **d)
    code, _, err = evaluate(capsys, root / 'out', '--ground-truth', tmp_path / 'shifted.npz')
    one_error_line(code, err, str(root / 'out'))
    assert 'shifted.npz' in err and 'stamp' in err
    # an input bag: no nrsfm/points to score
    code, _, err = evaluate(capsys, root / 'in', '--ground-truth', gt)
    one_error_line(code, err, 'nrsfm/points')


def test_read_tracks_and_tracker_split(run):
    """The tracker's published tracks as one (W, V) over their ids, and the split of its cost:
    fed the ground truth itself, the three reconstructions are the same and the pixel error 0;
    fed the tracker's tracks, its position errors are measured against the truth."""
    from nrsfm_ros.evaluation import read_tracks, tracker_split
    root, seq = run
    W, V, ids = read_tracks(root / 'out', seq.stamps_ns)
    F = seq.stamps_ns.size
    assert W.shape == (2 * F, ids.size) and V.shape == (F, ids.size)
    assert (np.diff(ids) > 0).all() and 0 <= V.min() and V.max() <= 1
    assert (V[0] > 0.5).mean() > 0.9                  # the reference frame sees its tracks
    assert np.isin(ids, seq.track_ids.astype(np.int64)).mean() > 0.5
    truth = tracker_split(seq.W, seq.V, seq.track_ids.astype(np.int64), seq)
    assert truth['trk'] == truth['gt_positions'] == truth['gt_visibility']
    assert truth['median_px'] == 0 and truth['over_3px'] == 0
    assert truth['visible_tracker'] == truth['visible_truth']
    s = tracker_split(W, V, ids, seq)
    assert 0 < s['median_px'] < 1.0 and s['p90_px'] >= s['median_px']
    assert 0 <= s['over_3px'] < 0.2 and 0.5 < s['visible_tracker'] <= 1
    assert all(np.isfinite(s[k]) for k in ('trk', 'gt_positions', 'gt_visibility'))
    with pytest.raises(ValueError, match='match ground truth'):
        tracker_split(W[:, :3], V[:, :3], ids[:3] + 10**9, seq)


def test_tracks_of_a_later_reference_are_scored_against_the_pixels_truth():
    """A stream whose tracker re-selected its reference at frame 5 (new ids ``H * W + y * W +
    x`` from there on): those frames are scored on the new tracks against the truth of the
    pixels they started on (``truth_for_clouds``), never left to the few carried ids; a
    cloud of the new tracks placed wrongly scores badly, and one published with its depths
    reflected is counted."""
    from nrsfm_ros.evaluation import depth_reflected_frames, truth_for_clouds
    from nrsfm_ros.io.synth import SynthConfig, generate, pixel_truth
    seq = generate(SynthConfig(surface='sphere', width=96, height=72, frames=10,
                               camera_motion_deg=30.0, amplitude=2.0))
    H, W_ = 72, 96
    ys, xs = np.nonzero(np.isfinite(seq.surface_st[5, ..., 0]))
    ys, xs = ys[::3], xs[::3]
    new_ids = (H * W_ + ys * W_ + xs).astype(np.uint32)
    X_new = pixel_truth(seq, 5, np.stack([xs, ys], axis=1))
    carried = seq.track_ids[:5]                  # too few to score a frame alone
    clouds = {f: (seq.S[f], seq.track_ids) for f in range(5)}
    for f in range(5, 10):
        clouds[f] = (np.concatenate([seq.S[f, :5], X_new[f]]),
                     np.concatenate([carried, new_ids]))
    ids, S = truth_for_clouds(clouds, seq)
    assert ids.size == seq.track_ids.size + new_ids.size
    good = score(clouds, seq)
    assert not good.unscored and good.summary()['e3d'] < 1e-6
    assert (good.matched[5:] == new_ids.size + 5).all()
    rng = np.random.default_rng(0)
    wrong = {**clouds, **{f: (clouds[f][0][rng.permutation(new_ids.size + 5)], clouds[f][1])
                          for f in range(5, 10)}}
    assert score(wrong, seq).e3d[5:].min() > 0.3
    mirrored = {**clouds, **{f: (clouds[f][0] * [1, 1, -1], clouds[f][1]) for f in range(5, 10)}}
    assert depth_reflected_frames(clouds, seq) == 0
    assert depth_reflected_frames(mirrored, seq) == 5
