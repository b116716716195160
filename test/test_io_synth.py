"""The synthetic renderer (io.synth): every surface, the isometric sheet, the occluder, rigid
amplitude 0, determinism, config validation and the `synth` CLI flags."""
from __future__ import annotations

import numpy as np
import pytest

from nrsfm_ros.cli import main
from nrsfm_ros.io.synth import (EXTENT, SURFACES, SynthConfig, SynthSequence, _surface,
                                dense_tracks, generate, pixel_truth, rasterise)

SMALL = dict(width=96, height=72, frames=10)


def _gen(**kw) -> SynthSequence:
    return generate(SynthConfig(**{**SMALL, **kw}))


@pytest.mark.parametrize('surface', SURFACES)
def test_every_surface_renders_with_finite_ground_truth(surface):
    seq = _gen(surface=surface, camera_motion_deg=30.0)
    covered = np.isfinite(seq.depth[0])
    assert 0.25 < covered.mean() < 0.8, covered.mean()
    cols = np.nonzero(covered.any(axis=0))[0]
    assert 0.45 < (cols[-1] - cols[0] + 1) / 96 < 0.9       # ~75% of the width (face: less)
    for a in (seq.W, seq.S, seq.S_world, seq.V):
        assert np.isfinite(a).all()
    assert seq.V[0].mean() > 0.99 and seq.V.mean() > 0.8
    assert np.all(seq.S[..., 2] > 3.0) and np.all(seq.S[..., 2] < 5.0)
    assert seq.K[0, 0] == pytest.approx(0.75 * 96 * 4.0 / EXTENT[surface])
    # the reference tracks start on their own pixels (up to the mesh's facets) and follow the
    # projection of S
    ys, xs = np.divmod(seq.track_ids.astype(np.int64), 96)
    np.testing.assert_allclose(seq.W[0], xs, atol=0.25)
    np.testing.assert_allclose(seq.W[1], ys, atol=0.25)
    f = seq.K[0, 0]
    np.testing.assert_allclose(seq.W[0::2], f * seq.S[..., 0] / seq.S[..., 2] + seq.K[0, 2])


def test_rasterise_keeps_the_nearest_triangle_and_interpolates_its_attributes():
    """Known answers on a 6 x 5 image: the nearer of two overlapping triangles wins where both
    cover a pixel (the first one on a tie), attributes are exact at the vertices and linear
    between them, pixels off every triangle stay empty (inf / NaN), a triangle partly off the
    image is clipped and one wholly off it is skipped."""
    uv = np.array([[0, 0], [4, 0], [0, 4],            # A: lower-left half of the 5 x 5 square
                   [4, 0], [4, 4], [0, 4],            # B: its upper-right half (shares A's edge)
                   [2, 0], [7, 0], [2, 5],            # C: overlaps A and B, partly off the image
                   [20, 20], [30, 20], [20, 30]], float)   # D: wholly off the image
    depth = np.array([2.0, 2, 2, 3, 3, 3, 1, 1, 5, 0.5, 0.5, 0.5])
    attrs = np.stack([uv[:, 0], uv[:, 1], depth], 1)      # x, y and depth as attributes
    tris = np.arange(12).reshape(4, 3)
    zbuf, out = rasterise(uv, depth, attrs, tris, 6, 5)
    assert zbuf.shape == (5, 6) and out.shape == (5, 6, 3)
    # C's depth at (x, y): 1 + 4 y / 5; it wins over A (2) and B (3) where nearer
    ys, xs = np.mgrid[0:5, 0:6]
    inC = (xs >= 2) & (xs + ys <= 7)
    zc = 1 + 4 * ys / 5
    inA, inB = xs + ys <= 4, (xs <= 4) & (xs + ys >= 4)
    want = np.full((5, 6), np.inf)
    want[inB] = 3.0
    want[inA] = 2.0                                   # nearer than B on their shared edge
    want[inC] = np.minimum(want[inC], zc[inC])
    np.testing.assert_allclose(zbuf, want, rtol=0, atol=1e-12)
    hit = np.isfinite(want)
    np.testing.assert_allclose(out[hit][:, :2], np.stack([xs, ys], -1)[hit], atol=1e-12)
    np.testing.assert_allclose(out[hit][:, 2], want[hit], atol=1e-12)
    assert np.isnan(out[~hit]).all() and (~hit).sum() == 2     # (5, 3), (5, 4); D drew nothing
    # a tie: the same triangle twice with other attributes: the first one drawn wins
    z2, o2 = rasterise(uv[:3].repeat(2, 0)[[0, 2, 4, 1, 3, 5]], depth[:6] * 0 + 2,
                       np.array([[1.0]] * 3 + [[7.0]] * 3), np.arange(6).reshape(2, 3), 6, 5)
    assert set(np.unique(o2[np.isfinite(z2)])) == {1.0}


def test_deterministic_per_seed():
    kw = dict(surface='sphere', occluder=True, noise=2.0, amplitude=2.0, frames=6)
    a, b = _gen(**kw).npz_dict(), _gen(**kw).npz_dict()
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    c = _gen(**kw, seed=1)
    assert not np.array_equal(a['images'], c.images)


def test_sheet_is_isometric_and_bends():
    seq = _gen(surface='sheet', amplitude=2.0, camera_motion_deg=30.0, frames=12, fps=2.0)
    ids = seq.track_ids.astype(np.int64)
    right = np.searchsorted(ids, ids + 2)       # the next GT point on the row (stride 2)
    ok = (right < ids.size) & (ids[np.minimum(right, ids.size - 1)] == ids + 2)
    a, b = np.nonzero(ok)[0], right[ok]
    d = np.linalg.norm(seq.S_world[:, a] - seq.S_world[:, b], axis=2)
    assert a.size > 500
    assert np.max(np.abs(d / d[0] - 1)) < 0.01
    sag = np.ptp(seq.S_world[..., 2], axis=1)   # the bend shows as depth relief
    assert sag.max() > 0.1 and np.ptp(sag) > 0.05


def test_sheet_flat_limit_is_exact():
    s, t = np.random.default_rng(0).uniform(0, 1, (2, 200))
    phase = np.array([0.3, 1.0, 2.0])
    flat = np.stack([s - 0.5, (t - 0.5) * 0.7, np.zeros_like(s)], axis=1)
    np.testing.assert_allclose(_surface('sheet', s, t, 1.7, 0.0, phase), flat, atol=1e-15)
    tiny = _surface('sheet', s, t, 1.7, 1e-9, phase)
    assert np.isfinite(tiny).all() and np.abs(tiny - flat).max() < 1e-8


def test_occluder_hides_points_only_in_the_middle_and_only_where_drawn():
    kw = dict(surface='flag', frames=12, camera_motion_deg=30.0)
    clean, occ = _gen(**kw), _gen(**kw, occluder=True)
    np.testing.assert_array_equal(clean.images[0], occ.images[0])
    np.testing.assert_array_equal(clean.V[0], occ.V[0])
    np.testing.assert_array_equal(clean.W, occ.W)
    assert clean.occluder is None and occ.occluder is not None and occ.occluder.shape == (12, 4)
    dropped = (clean.V > 0) & (occ.V == 0)
    assert not np.any((occ.V > 0) & (clean.V == 0))
    frac = dropped.mean(axis=1)
    assert frac[0] == 0 and frac[5] > 0.1 and frac[-1] == 0
    r = occ.occluder[0, 2]
    assert 0.25 < np.pi * r ** 2 / np.isfinite(clean.depth[0]).sum() < 0.35
    for f in range(1, 11):
        u = np.clip(np.rint(occ.W[2 * f]).astype(int), 0, 95)
        v = np.clip(np.rint(occ.W[2 * f + 1]).astype(int), 0, 71)
        differs = np.any(occ.images[f, v, u] != clean.images[f, v, u], axis=1)
        if dropped[f].any():
            assert differs[dropped[f]].mean() > 0.9
            np.testing.assert_allclose(occ.depth[f, v, u][dropped[f]], 2.0)
        still = occ.V[f] > 0
        assert differs[still].mean() < 0.01
        # the image changes only inside the disc, which is textured
        changed = np.any(occ.images[f] != clean.images[f], axis=2)
        yy, xx = np.nonzero(changed)
        if yy.size:
            cu, cv, rr, _ = occ.occluder[f]
            assert np.all(np.hypot(xx - cu, yy - cv) <= rr + 1e-9)
            assert occ.images[f][changed].std() > 20


@pytest.mark.parametrize('surface', SURFACES)
def test_pixel_truth_of_any_frame_follows_the_surface_point_seen_there(surface):
    """``pixel_truth``: the pixels of frame 0 that carry ground-truth tracks get exactly
    those tracks' truth; a pixel of a later frame gets a point that projects onto it in that
    frame and follows the surface (it moves with the deformation and the camera); pixels off
    the surface or behind the occluder get NaN; bad frames and pixels are named."""
    seq = _gen(surface=surface, camera_motion_deg=30.0, occluder=True, amplitude=2.0)
    W_ = seq.config.width
    xy0 = np.stack([seq.track_ids % W_, seq.track_ids // W_], axis=1)
    np.testing.assert_allclose(pixel_truth(seq, 0, xy0), seq.S, atol=1e-6)
    f = 7
    ys, xs = np.nonzero(np.isfinite(seq.surface_st[f, ..., 0]))
    X = pixel_truth(seq, f, np.stack([xs, ys], axis=1))
    assert np.isfinite(X).all()
    uv = X[f, :, :2] / X[f, :, 2:] * seq.K[0, 0] + seq.K[:2, 2]
    off = np.hypot(*(uv - np.stack([xs, ys], axis=1)).T)   # the mesh's linear facets and
    assert np.median(off) < 0.05 and off.max() < 0.3        # attributes, as for frame 0's
    np.testing.assert_allclose(X[f, :, 2], seq.depth[f, ys, xs], rtol=2e-3)
    assert np.linalg.norm(X[0] - X[f], axis=1).mean() > 0.01       # it moved
    hidden = ~np.isfinite(seq.depth[f]) | (seq.depth[f] == seq.occluder[f, 3])
    yh, xh = np.nonzero(hidden)
    assert yh.size and np.isnan(pixel_truth(seq, f, np.stack([xh, yh], axis=1))).all()
    with pytest.raises(ValueError, match='frame=10'):
        pixel_truth(seq, 10, xy0[:3])
    with pytest.raises(ValueError, match='outside'):
        pixel_truth(seq, 0, [[W_, 0]])


@pytest.mark.parametrize('surface', SURFACES)
def test_amplitude_zero_is_rigid(surface):
    seq = generate(SynthConfig(surface=surface, width=64, height=48, frames=5, amplitude=0.0,
                               camera_motion_deg=20.0))
    np.testing.assert_allclose(seq.S_world, np.broadcast_to(seq.S_world[0], seq.S_world.shape),
                               atol=1e-12)
    moving = generate(SynthConfig(surface=surface, width=64, height=48, frames=5))
    assert np.abs(moving.S_world - moving.S_world[0]).max() > 1e-3


def test_camera_motion_and_distance_reach_every_surface():
    for surface in SURFACES:
        still = generate(SynthConfig(surface=surface, width=64, height=48, frames=4,
                                     camera_motion_deg=0.0, distance=6.0))
        np.testing.assert_allclose(still.T_camera_world, still.T_camera_world[:1].repeat(4, 0))
        assert abs(np.mean(still.S[0, :, 2]) - 6.0) < 0.2
        swing = generate(SynthConfig(surface=surface, width=64, height=48, frames=20, fps=2.0,
                                     camera_motion_deg=60.0))
        z_axis = swing.T_camera_world[:, 2, :3]          # camera optical axis, world frame
        yaw = np.degrees(np.arctan2(-z_axis[:, 0], z_axis[:, 2]))
        assert np.ptp(yaw) > 40


@pytest.mark.parametrize('surface', ['sheet', 'sphere'])
def test_dense_tracks_new_surfaces(surface):
    d = dense_tracks(surface, frames=6, points=300)
    assert d['W'].shape == (12, 300) and np.isfinite(d['S']).all()
    rigid = dense_tracks(surface, frames=6, points=300, amplitude=0.0)
    np.testing.assert_allclose(rigid['S_world'], rigid['S_world'][:1].repeat(6, 0), atol=1e-12)


@pytest.mark.parametrize('field, value, text', [
    ('surface', 'cube', "surface='cube'"),
    ('amplitude', -1.0, 'amplitude=-1.0'),
    ('amplitude', float('nan'), 'amplitude=nan'),
    ('camera_motion_deg', 95.0, 'camera_motion_deg=95.0'),
    ('distance', 1.0, 'distance=1.0'),
    ('noise', -0.5, 'noise=-0.5'),
    ('occluder', 'yes', "occluder='yes'"),
    ('fps', 0.0, 'fps=0.0'),
])
def test_validate_names_field_and_value(field, value, text):
    with pytest.raises(ValueError, match=text.replace('(', r'\(')):
        SynthConfig(**{field: value}).validate()


def test_cli_synth_flags_reach_the_config(tmp_path, capsys):
    out = tmp_path / 'seq'
    assert main(['synth', '--surface', 'sphere', '--size', '96x72', '--frames', '8',
                 '--camera-motion', '45', '--amplitude', '0', '--occluder', '--distance', '6',
                 '--noise', '2', '--seed', '3', '--out', str(out)]) == 0
    d = np.load(tmp_path / 'seq.npz')
    assert str(d['surface']) == 'sphere' and float(d['camera_motion_deg']) == 45.0
    assert float(d['amplitude']) == 0.0 and float(d['distance']) == 6.0
    assert float(d['noise']) == 2.0 and bool(d['occluder_on']) and int(d['seed']) == 3
    assert d['K'][0, 0] == pytest.approx(0.75 * 96 * 6.0 / EXTENT['sphere'])
    np.testing.assert_allclose(d['S_world'], d['S_world'][:1].repeat(8, 0), atol=1e-12)
    assert d['occluder'].shape == (8, 4) and d['V'][0].mean() > 0.99
    assert d['V'][2:6].mean() < 0.95
    assert out.is_dir()


@pytest.mark.parametrize('args, text', [
    (['--camera-motion', '120'], '--camera-motion 120.0: expected 0..90'),
    (['--amplitude', '-1'], '--amplitude -1.0: expected 0..'),
    (['--distance', '0.5'], '--distance 0.5: expected >= 1.5'),
    (['--noise', '-2'], '--noise -2.0: expected >= 0'),
])
def test_cli_synth_bad_values_one_error_line(args, text, tmp_path, capsys):
    out = tmp_path / 'seq'
    assert main(['synth', *args, '--out', str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and err.startswith('error: ') and text in err
    assert not out.exists()
