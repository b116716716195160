"""DSPR (core.nrsfm.dspr): the batched state fit, the batch clustering, self- and
cross-convergence of the per-frame solver, recurrence detection and compression on a periodic
sequence, accuracy against the static oracle, bad inputs; the periodic synthetic sequence."""
from __future__ import annotations

import numpy as np
import pytest

from nrsfm_ros.core.metrics import frame_e3d
from nrsfm_ros.core.nrsfm.dspr import (DynamicShapePrior, cluster_states, fit_states,
                                       shape_distance)
from nrsfm_ros.core.nrsfm.stream import StreamNRSfM, _solve_default
from nrsfm_ros.io.synth import SynthConfig, deformation_time, dense_tracks, generate

PX = 500.0          # dense_tracks' orthographic image units per metre (focal 2000 / distance 4)
PERIOD = 20


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q * np.linalg.det(q)


@pytest.fixture(scope='module')
def periodic():
    return dense_tracks('flag', frames=100, points=800, camera_motion_deg=30,
                        period_frames=PERIOD, seed=1)


@pytest.fixture(scope='module')
def flag_states():
    """Four states of the waving flag (object frame, image units), a quarter period apart."""
    d = dense_tracks('flag', frames=16, points=600, seed=3)
    return d['S_world'][[0, 5, 10, 15]] * PX


def test_fit_states_recovers_the_camera_of_the_true_state_and_ignores_invisible(flag_states):
    rng = np.random.default_rng(0)
    R = _rotation(rng)
    k, s, t = 2, 1.3, np.array([120.0, 80.0])
    uv = s * flag_states[k] @ R[:2].T + t
    vis = np.ones(uv.shape[0])
    vis[::7] = 0.0
    uv[::7] = rng.normal(size=uv[::7].shape) * 1e3      # garbage where invisible
    fit = fit_states(flag_states, uv, vis)
    assert int(np.argmin(fit.residual_px)) == k
    assert fit.residual_px[k] < 1e-6
    assert np.sort(fit.residual_px)[1] > 1.0            # the others do not explain it
    np.testing.assert_allclose(fit.R2[k], R[:2], atol=1e-7)
    assert fit.scale[k] == pytest.approx(s, rel=1e-9)
    c = vis @ flag_states[k] / vis.sum()
    np.testing.assert_allclose(fit.t[k], s * R[:2] @ c + t, atol=1e-6)


def test_cluster_states_merges_rotated_scaled_copies():
    rng = np.random.default_rng(1)
    base = rng.normal(size=(3, 200, 3)) * [100, 80, 30]
    order = [0, 1, 0, 2, 1, 2, 0]
    shapes = np.stack([rng.uniform(0.8, 1.2) * base[i] @ _rotation(rng).T
                       + rng.normal(size=3) * 50 + rng.normal(size=(200, 3)) * 0.01
                       for i in order])
    states, labels = cluster_states(shapes, distinct=0.01)
    assert states.shape == (3, 200, 3)
    assert labels.tolist() == [0, 1, 0, 2, 1, 2, 0]
    for i in range(3):
        assert shape_distance(base[i], states[i:i + 1])[0] < 1e-3


@pytest.mark.parametrize('k', range(4))
def test_self_convergence(flag_states, k):
    """Started from the true state, the per-frame solver stays there (exactly)."""
    rng = np.random.default_rng(10 + k)
    R = _rotation(rng)
    uv = 0.9 * flag_states[k] @ R[:2].T + [60.0, 40.0]
    prior = DynamicShapePrior(flag_states)
    X, alpha, reached = prior.refine(uv, None, start=k)
    assert reached == k
    assert np.abs(alpha / alpha[k] - np.eye(4)[k]).max() < 1e-4
    assert frame_e3d(X, flag_states[k] @ R.T) < 1e-6


@pytest.mark.parametrize('k,start', [(0, 3), (1, 0), (2, 1), (3, 0), (3, 2)])
def test_cross_convergence(flag_states, k, start):
    """Started from another state (its camera fit and its shape), it reaches the right one."""
    rng = np.random.default_rng(20 + k)
    R = _rotation(rng)
    uv = flag_states[k] @ R[:2].T + rng.normal(size=(flag_states.shape[1], 2)) * 0.2
    prior = DynamicShapePrior(flag_states)
    X, alpha, reached = prior.refine(uv, None, start=start)
    assert reached == k
    assert frame_e3d(X, flag_states[k] @ R.T) < 0.01
    assert frame_e3d(flag_states[start], flag_states[k]) > 0.03     # the start was wrong


def test_recurrence_detected_with_the_right_states_on_a_periodic_sequence(periodic):
    """A prior of the first period's true shapes: every later frame is a recurrence of the
    state of its phase (f and PERIOD - f deform alike), seen by a new camera."""
    S_world = periodic['S_world'] * PX
    states, labels = cluster_states(S_world[:PERIOD], distinct=1e-6)
    assert len(states) == PERIOD // 2 + 1                    # the sweep goes forth and back
    prior = DynamicShapePrior(states, frames=PERIOD, recurrence_px=0.01)
    W, S = periodic['W'], periodic['S']
    for f in range(PERIOD, 100):
        out = prior.step(W[2 * f:2 * f + 2].T)
        assert out.recurring and out.state == labels[f % PERIOD], f
        assert out.residual_px < 1e-4
        assert frame_e3d(out.X, S[f]) < 1e-6
    assert prior.compression_ratio == pytest.approx(100 / (PERIOD // 2 + 1))
    assert len(prior.states) == PERIOD // 2 + 1 and prior.recurrences == 100 - PERIOD


def test_recurrence_survives_noise_and_occlusion(periodic):
    """The same with 0.3 px track noise and a third of the tracks occluded (garbage positions,
    visibility 0) in every frame: still every frame recurs, with the right state."""
    S_world = periodic['S_world'] * PX
    states, labels = cluster_states(S_world[:PERIOD], distinct=1e-6)
    prior = DynamicShapePrior(states, frames=PERIOD, recurrence_px=0.6)
    W, S = periodic['W'], periodic['S']
    rng = np.random.default_rng(7)
    P = W.shape[1]
    for f in range(PERIOD, 100):
        uv = W[2 * f:2 * f + 2].T + rng.normal(size=(P, 2)) * 0.3
        vis = (rng.random(P) > 0.33).astype(float)
        uv[vis == 0] = rng.normal(size=((vis == 0).sum(), 2)) * 300
        out = prior.step(uv, vis)
        assert out.recurring and out.state == labels[f % PERIOD], f
        assert frame_e3d(out.X, S[f]) < 2e-3


def test_periodic_sequence_from_a_solved_batch_beats_static_and_compresses(periodic):
    """The prior from the first period solved by the batch solver (stream's default, here
    'auto' -> planar), then frame by frame: e3D well under the static oracle (ground-truth
    frame 0 repeated), compression >= 5x, and within 10% of the same run without
    recurrence (every frame through the per-frame energy)."""
    W, V, S = periodic['W'], periodic['V'], periodic['S']
    res = _solve_default(W[:2 * PERIOD], V[:PERIOD], 'auto', 2)
    runs = {}
    for name, rp in (('compressed', 1.5 * res.residual_px), ('uncompressed', 0.0)):
        prior, _ = DynamicShapePrior.from_batch(res, distinct=0.05, recurrence_px=rp)
        e3d, recurring = [], 0
        for f in range(PERIOD, 100):
            out = prior.step(W[2 * f:2 * f + 2].T, V[f])
            e3d.append(frame_e3d(out.X, S[f]))
            recurring += out.recurring
        runs[name] = (float(np.mean(e3d)), prior.compression_ratio, recurring)
    static = float(np.mean([frame_e3d(S[0], S[f]) for f in range(PERIOD, 100)]))
    e3d, ratio, recurring = runs['compressed']
    assert e3d < 0.6 * static, (e3d, static)               # measured 0.0308 vs 0.0652
    assert ratio >= 5.0 and recurring >= 25, runs           # measured 11.1x, 35 of 80
    assert e3d <= 1.1 * runs['uncompressed'][0], runs       # measured 0.0308 vs 0.0299


def test_new_frame_joins_the_prior_only_when_distinct(flag_states):
    rng = np.random.default_rng(5)
    R = _rotation(rng)
    prior = DynamicShapePrior(flag_states[:2], recurrence_px=0.5, distinct=0.01)
    mid = 0.5 * (flag_states[0] + flag_states[1])
    far = flag_states[3]
    out = prior.step(far @ R[:2].T)
    assert not out.recurring and out.added and out.state == 2
    assert len(prior.states) == 3
    again = prior.step(far @ R[:2].T + [5.0, -3.0])          # now it is a recurrence
    assert again.recurring and again.state == 2 and again.residual_px < 0.1
    near = prior.step(mid @ R[:2].T + rng.normal(size=(mid.shape[0], 2)) * 0.6)
    assert not near.recurring
    assert prior.compression_ratio == pytest.approx(prior.frames / len(prior.states))


def test_bad_inputs_name_the_field(flag_states):
    with pytest.raises(ValueError, match='states'):
        DynamicShapePrior(np.zeros((2, 10, 2)))
    with pytest.raises(ValueError, match='distinct'):
        DynamicShapePrior(flag_states, distinct=-1.0)
    with pytest.raises(ValueError, match='prior_weight'):
        DynamicShapePrior(flag_states, prior_weight=0.0)
    with pytest.raises(ValueError, match='distinct'):
        cluster_states(flag_states, distinct=float('nan'))
    prior = DynamicShapePrior(flag_states)
    P = flag_states.shape[1]
    with pytest.raises(ValueError, match='uv'):
        prior.step(np.zeros((P, 3)))
    with pytest.raises(ValueError, match='vis'):
        prior.step(np.zeros((P, 2)), np.full(P, 2.0))
    with pytest.raises(ValueError, match='vis'):
        prior.step(np.zeros((P, 2)), np.zeros(P))           # nothing visible
    with pytest.raises(ValueError, match='start'):
        prior.refine(np.zeros((P, 2)), None, start=9)
    with pytest.raises(ValueError, match='dspr_distinct'):
        StreamNRSfM(mode='dspr', dspr_distinct=-0.1)
    with pytest.raises(ValueError, match='dspr_prior_weight'):
        StreamNRSfM(mode='dspr', dspr_prior_weight=0.0)


# ---------------------------------------------------------------- periodic synthetic sequence

def test_periodic_deformation_repeats_while_the_camera_moves(periodic):
    Sw, S = periodic['S_world'], periodic['S']
    for f in (0, 3, 7, 10):
        np.testing.assert_allclose(Sw[f + PERIOD], Sw[f], atol=1e-12)
        np.testing.assert_allclose(Sw[PERIOD - f], Sw[f], atol=1e-12)    # forth and back
        assert np.abs(S[f + PERIOD] - S[f]).max() > 0.01                   # a new view
    assert frame_e3d(Sw[0], Sw[PERIOD // 2]) > 0.03                       # it deforms
    off = dense_tracks('flag', frames=10, points=50, seed=1)
    again = dense_tracks('flag', frames=10, points=50, seed=1, period_frames=0)
    for key in off:
        np.testing.assert_array_equal(off[key], again[key])
    assert deformation_time(7, 10.0) == 7 / 10.0


def test_rendered_periodic_sequence_repeats():
    cfg = dict(width=96, height=72, frames=10, surface='face', period_frames=4)
    seq = generate(SynthConfig(**cfg))
    np.testing.assert_allclose(seq.S_world[5], seq.S_world[1], atol=1e-12)
    np.testing.assert_allclose(seq.S_world[3], seq.S_world[1], atol=1e-12)
    assert int(seq.npz_dict()['period_frames']) == 4
    assert 'period_frames' not in generate(SynthConfig(**{**cfg, 'period_frames': 0})
                                           ).npz_dict()


@pytest.mark.parametrize('value', [1, 3, -2, True, 2.5, 'x'])
def test_period_validation_names_the_field(value):
    with pytest.raises(ValueError, match='period_frames'):
        SynthConfig(period_frames=value).validate()
    with pytest.raises(ValueError, match='period_frames'):
        dense_tracks('flag', frames=5, points=10, period_frames=value)


def test_pinhole_recurrence_poses_the_state_by_the_camera(flag_states):
    """A state seen again by a close pinhole camera (the flag ~1.2 focal lengths wide at a
    depth of 2 of its widths: strong perspective): the orthographic fit leaves pixels of
    residual, so without the camera the frame is not a recurrence; with it (``camera=``) every
    state is posed by the pinhole camera, the right one explains the image to ~0 px, and the
    frame comes back as that state in that pose (image units, centred, the centroid's depth as
    the scale: the stream's convention)."""
    focal, c = 300.0, np.array([160.0, 120.0])
    rng = np.random.default_rng(4)
    R = _rotation(rng)
    k = 1
    O = flag_states[k] / focal                         # units of the focal length
    width = np.ptp(O[:, 0])
    T = np.array([0.05, -0.03, 2.0 * width])
    X = O @ R.T + T
    uv = c + focal * X[:, :2] / X[:, 2:3]
    prior = DynamicShapePrior(flag_states, recurrence_px=0.5)
    assert not prior.step(uv, None).recurring
    out = prior.step(uv, None, camera=(focal, c))
    assert out.recurring and out.state == k and out.residual_px < 1e-3
    mean = X.mean(axis=0)
    np.testing.assert_allclose(out.X, (X - mean) * focal / mean[2], atol=1e-3 * focal)
    np.testing.assert_allclose(out.t, c + mean[:2] * focal / mean[2], atol=1e-3)
    assert prior.recurrences == 1 and prior.frames == 2


def test_steps_take_the_depth_sign_the_pinhole_camera_sees():
    """dspr through the stream with the camera, on the ground-truth tracks of a rendered
    periodic flag (30 deg sweep): the frames after the prior keep the true depth sign (a
    near-planar shape's orthographic energy leaves it to chance; the pinhole-posed best state
    decides).  Measured: 0 of 60 reflected (6 before; through the tracker, 256x192, 120
    frames: 22 -> 1 of 60 on the flag, 10 -> 2 on the sheet)."""
    from tests_helpers import reflected_frames_of_a_periodic_flag
    assert sum(reflected_frames_of_a_periodic_flag('dspr')[30:]) <= 2
