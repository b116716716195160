"""The planar model refined under the pinhole camera (core/nrsfm/planar_pinhole.py)."""
from __future__ import annotations

import numpy as np
import pytest

from nrsfm_ros.core.metrics import e3d_frobenius
from nrsfm_ros.core.nrsfm import planar_pinhole, reconstruct
from nrsfm_ros.core.nrsfm.perspective import perspective_solve
from nrsfm_ros.core.nrsfm.planar_pinhole import refine_planar_pinhole
from nrsfm_ros.core.nrsfm import stream as stream_mod
from nrsfm_ros.core.nrsfm.stream import StreamNRSfM

FOCAL, PRINCIPAL = 300.0, np.array([160.0, 120.0])


def bending_sheet(distance: float = 1.6, frames: int = 24, side: int = 20,
                  orbit_deg: float = 40.0):
    """A unit sheet bending out of its plane (two height modes over the frames) on an orbit
    about the y axis and tilting about x at ``distance`` m (a 56 deg field of view, the sheet
    ~190 px wide):
    W (2F, P) px, S (F, P, 3) camera frame (m)."""
    g = np.linspace(-0.5, 0.5, side)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    t = np.linspace(0, np.pi, frames)
    h = 0.35 * np.sin(t)[:, None] * (x * x - 1 / 12) + 0.25 * np.cos(t)[:, None] * x * y
    W, S = np.zeros((2 * frames, x.size)), np.zeros((frames, x.size, 3))
    for f, a in enumerate(np.radians(np.linspace(-orbit_deg / 2, orbit_deg / 2, frames))):
        c, s = np.cos(a), np.sin(a)
        b = 0.5 * a + np.radians(15)            # and a tilt about x: two axes of rotation
        R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ \
            np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
        Xc = np.c_[x, y, h[f]] @ R.T + [0.03, -0.02, distance]
        W[2 * f] = FOCAL * Xc[:, 0] / Xc[:, 2] + PRINCIPAL[0]
        W[2 * f + 1] = FOCAL * Xc[:, 1] / Xc[:, 2] + PRINCIPAL[1]
        S[f] = Xc
    return W, np.ones((frames, x.size)), S


def planar_solve(W, V):
    return reconstruct(W, V, method='planar')


def _step(W, V):
    return perspective_solve(planar_solve, W, V, FOCAL, PRINCIPAL, weak=planar_solve(W, V))


def test_refinement_recovers_a_bending_sheet_seen_close():
    """Known answer: the corrected re-solve leaves the perspective's depth error in the planar
    model (metric B 0.049 here); fitted to the pinhole image it recovers the sheet nearly
    exactly, with a lower reprojection error, and back-projects to the true camera-frame
    shapes up to one global scale."""
    W, V, S = bending_sheet()
    step = _step(W, V)
    ref = refine_planar_pinhole(step, W, V, FOCAL, PRINCIPAL)
    e_step = e3d_frobenius(step.S, S, scale=True)
    e_ref = e3d_frobenius(ref.S, S, scale=True)
    assert e_ref < 0.2 * e_step and e_ref < 0.01, (e_ref, e_step)
    assert ref.residual_px < 0.5 * step.residual_px, (ref.residual_px, step.residual_px)
    # the stream's convention (scale = focal / the frame centroid's depth, processing.to_metric)
    # back-projects to the true camera-frame points up to one global scale, imaging onto the
    # tracks through the pinhole camera
    depth = FOCAL / ref.scale
    X = np.stack([(ref.S[..., 0] * ref.scale[:, None] + ref.t[:, 0, None] - PRINCIPAL[0]),
                  (ref.S[..., 1] * ref.scale[:, None] + ref.t[:, 1, None] - PRINCIPAL[1]),
                  FOCAL + ref.S[..., 2] * ref.scale[:, None]], 2) * (depth / FOCAL)[:, None, None]
    k = (X * S).sum() / (X * X).sum()
    assert np.linalg.norm(k * X - S) / np.linalg.norm(S) < 0.006      # measured 0.003
    assert np.abs(FOCAL * X[..., 0] / X[..., 2] + PRINCIPAL[0] - W[0::2]).mean() < 0.1


def test_refinement_keeps_its_input_when_the_image_is_not_explained_better(monkeypatch):
    W, V, _ = bending_sheet(frames=8, side=8)
    step = _step(W, V)
    monkeypatch.setattr(planar_pinhole, 'MIN_GAIN', 1.0)    # no error can fall below 0
    assert refine_planar_pinhole(step, W, V, FOCAL, PRINCIPAL) is step
    bad = step.__class__(**{**step.__dict__, 'S': np.full_like(step.S, np.nan)})
    assert refine_planar_pinhole(bad, W, V, FOCAL, PRINCIPAL) is bad


@pytest.mark.parametrize('kw, field', [({'rounds': 0}, 'rounds'), ({'rank': 0}, 'rank'),
                                       ({'focal': -1.0}, 'focal')])
def test_bad_arguments_name_the_field(kw, field):
    W, V, _ = bending_sheet(frames=6, side=6)
    res = planar_solve(W, V)
    args = {'focal': FOCAL, **kw}
    with pytest.raises(ValueError, match=field):
        refine_planar_pinhole(res, W, V, args.pop('focal'), PRINCIPAL, **args)


def _planar_stream(batch: int, context: int = 30) -> StreamNRSfM:
    """The reconstructor's batch mode with ``planar`` and the camera's intrinsics."""
    st = StreamNRSfM(mode='batch', method='planar', batch_frames=batch, batch_context=context,
                     projection='perspective')
    st.set_intrinsics(FOCAL, PRINCIPAL)
    return st


def _push(st: StreamNRSfM, ids: np.ndarray, W: np.ndarray, frames: range) -> list:
    """The shapes ``st`` publishes while fed the tracks W of ``frames``."""
    out = []
    for f in frames:
        out += st.push(ids, W[2 * f:2 * f + 2].T)
    return out


def test_batch_stream_refines_planar_batches_with_the_camera(monkeypatch):
    """The reconstructor's batch mode with CameraInfo runs the refinement on a planar batch
    (``pinhole_refinements``) and publishes shapes closer to the truth than without it."""
    W, V, S = bending_sheet()
    F, P = V.shape
    ids = np.arange(P)

    def run() -> tuple[StreamNRSfM, float]:
        st = _planar_stream(F)
        out = _push(st, ids, W, range(F)) + st.flush()
        assert [sh.index for sh in out] == list(range(F))
        return st, e3d_frobenius(np.stack([sh.X for sh in out]), S, scale=True)

    st, e_on = run()
    assert st.pinhole_refinements == 1 and st.perspective_solves == 1
    monkeypatch.setattr('nrsfm_ros.core.nrsfm.stream.finish_planar_pinhole',
                        lambda fit, *a, **k: fit.start)
    st, e_off = run()
    assert st.pinhole_refinements == 0
    assert e_on < 0.5 * e_off, (e_on, e_off)


def test_gross_track_errors_are_weighted_down():
    """5% of the (track, frame) measurements off by 15-40 px, as the tracker's gross errors:
    the Cauchy weights (``ROBUST_PX``) keep the fit near the truth where least squares
    (``robust_px=0``) is pulled away."""
    W, V, S = bending_sheet()
    rng = np.random.default_rng(1)
    F, P = V.shape
    bad = rng.random((F, P)) < 0.05
    bad[0] = False
    angle = rng.uniform(0, 2 * np.pi, (F, P))
    size = rng.uniform(15, 40, (F, P)) * bad
    Wn = W.copy()
    Wn[0::2] += size * np.cos(angle)
    Wn[1::2] += size * np.sin(angle)
    step = _step(Wn, V)
    plain = refine_planar_pinhole(step, Wn, V, FOCAL, PRINCIPAL, robust_px=0.0)
    robust = refine_planar_pinhole(step, Wn, V, FOCAL, PRINCIPAL)
    e_plain = e3d_frobenius(plain.S, S, scale=True)
    e_robust = e3d_frobenius(robust.S, S, scale=True)
    assert e_robust < 0.3 * e_plain and e_robust < 0.03, (e_robust, e_plain)   # 0.018, 0.113
    with pytest.raises(ValueError, match='robust_px'):
        refine_planar_pinhole(step, Wn, V, FOCAL, PRINCIPAL, robust_px=-1.0)


def test_rounds_on_a_spread_subset_give_every_track_nearly_the_same_fit():
    """``max_tracks``: poses and the heights' frame coefficients from a quarter of the tracks,
    then every track's rest coordinates and heights in closed form: close to the fit on all
    tracks, and far below the perspective step."""
    W, V, S = bending_sheet(side=32)
    step = _step(W, V)
    full = refine_planar_pinhole(step, W, V, FOCAL, PRINCIPAL, max_tracks=10**6)
    sub = refine_planar_pinhole(step, W, V, FOCAL, PRINCIPAL, max_tracks=256)
    e_full, e_sub = (e3d_frobenius(r.S, S, scale=True) for r in (full, sub))
    e_step = e3d_frobenius(step.S, S, scale=True)
    assert sub.S.shape == step.S.shape
    assert e_sub < 1.5 * e_full + 1e-3 and e_sub < 0.25 * e_step, (e_sub, e_full, e_step)
    with pytest.raises(ValueError, match='max_tracks'):
        refine_planar_pinhole(step, W, V, FOCAL, PRINCIPAL, max_tracks=2)


def test_a_shared_pinhole_image_gives_the_same_refinement():
    """Several starts of one batch share one ``pinhole_image`` (rays, weights, the subset's
    copies): the same result as each building its own; one of other tracks is refused."""
    W, V, _ = bending_sheet(side=32)
    step = _step(W, V)
    image = planar_pinhole.pinhole_image(W, V, FOCAL, PRINCIPAL, max_tracks=256)
    own = refine_planar_pinhole(step, W, V, FOCAL, PRINCIPAL, max_tracks=256)
    shared = refine_planar_pinhole(step, W, V, FOCAL, PRINCIPAL, max_tracks=256, image=image)
    assert own is not step
    np.testing.assert_array_equal(shared.S, own.S)
    np.testing.assert_array_equal(shared.R, own.R)
    other = planar_pinhole.pinhole_image(W[:, :100], V[:, :100], FOCAL, PRINCIPAL)
    with pytest.raises(ValueError, match='image'):
        refine_planar_pinhole(step, W, V, FOCAL, PRINCIPAL, image=other)


@pytest.mark.parametrize('size, frames, bound', [((128, 96), 40, 0.07), ((96, 72), 20, 0.13)])
def test_stream_refines_from_both_depth_sign_starts_and_keeps_the_better_fit(size, frames,
                                                                           bound):
    """``planar`` takes each frame's depth sign from the previous frame's, and a local fit
    cannot undo a run of Necker-reversed frames; started from the perspective image's signs
    instead it can be far better or far worse (flag at 45 deg, amplitude 2, ground-truth
    tracks, as-is / sign start: 128x96, 40 frames 0.166 / 0.050 at 1.34 / 0.38 px; 96x72, 20
    frames 0.101 / 0.186 at 0.33 / 0.51 px), so the stream refines from both and keeps the
    lower reprojection error: the better of the two in both cases."""
    from nrsfm_ros.evaluation import score, stream_on_tracks
    from nrsfm_ros.io.synth import SynthConfig, generate
    seq = generate(SynthConfig(surface='flag', width=size[0], height=size[1], frames=frames,
                               camera_motion_deg=30, amplitude=2, distance=1.6))
    clouds = stream_on_tracks(seq.W, seq.V, seq.track_ids, seq.K, mode='batch',
                              method='planar', batch_frames=frames)
    e = score(clouds, seq).summary()['e3d']
    assert e < bound, e


def _depth_corr(a: np.ndarray, b: np.ndarray) -> float:
    """Correlation of two clouds' centred depths (the same points)."""
    a, b = a[:, 2] - a[:, 2].mean(), b[:, 2] - b[:, 2].mean()
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


@pytest.mark.parametrize('batch, refined, context, keeps_own',
                         [(30, True, 0, True), (30, False, 0, False), (12, True, 0, False),
                          (30, False, 30, True), (12, True, 12, True)])
def test_a_refined_batch_keeps_the_sign_its_pinhole_fit_chose(monkeypatch, batch, refined,
                                                              context, keeps_own):
    """A later batch takes its depth sign from the last published frame unless a pinhole fit
    over at least ``SIGN_FIT_FRAMES`` frames chose it: such a batch keeps the sign of its fit,
    so a wrong frame at the end of the previous batch (here its depths reversed by hand; on a
    600-frame 12 deg flag render the last frames of one batch drifted to a reversed relief
    and the next batch followed them: 60 frames published reflected) does not reflect the
    next batch; an unrefined or a short batch alone follows the last published frame, and
    with ``batch_context`` the published frames it shares (here all right but the last)."""
    from dataclasses import replace
    from nrsfm_ros.core.nrsfm.stream import SIGN_FIT_FRAMES
    assert (batch >= SIGN_FIT_FRAMES) == (batch == 30)
    W, V, S = bending_sheet(frames=2 * batch, side=16)
    F, P = V.shape
    ids = np.arange(P)
    if not refined:
        monkeypatch.setattr('nrsfm_ros.core.nrsfm.stream.finish_planar_pinhole',
                            lambda fit, *a, **k: fit.start)
    st = _planar_stream(batch, context)
    out = _push(st, ids, W, range(batch))
    assert [sh.index for sh in out] == list(range(batch))
    last = st._published[-1]
    wrong = replace(last, X=last.X * np.array([1.0, 1.0, -1.0]))
    st._published[-1] = wrong
    out += _push(st, ids, W, range(batch, F)) + st.flush()
    assert [sh.index for sh in out] == list(range(F))
    assert st.pinhole_refinements == (2 if refined else 0)
    assert (_depth_corr(out[batch].X, wrong.X) > 0) != keeps_own
    if keeps_own:   # and the later batch's sign is the truth's in every frame (refined: all)
        check = out if refined else out[batch:]
        assert all(_depth_corr(sh.X, S[sh.index]) > 0.8 for sh in check), str(
            [round(_depth_corr(sh.X, S[sh.index]), 2) for sh in check])


def test_auto_keeps_planar_more_readily_after_a_planar_batch(monkeypatch):
    """``auto``'s perspective test of the planar model allows ``PLANAR_KEPT_RATIO`` x its
    bound in a batch after a planar one (the same surface: a borderline later batch of a
    flag at 12 deg went bmm at e3D 0.088 against planar's 0.035), and the bound decides."""
    W, V, _ = bending_sheet(frames=24)
    ids = np.arange(V.shape[1])
    calls = []

    def recorded(W, V, perspective=None, planar_ratio=stream_mod.PLANAR_PERSPECTIVE_RATIO,
                 rank=2):
        res = original(W, V, perspective, planar_ratio)
        calls.append((planar_ratio, res.method))
        return res
    original = stream_mod.auto_solve
    monkeypatch.setattr(stream_mod, 'auto_solve', recorded)
    st = StreamNRSfM(mode='batch', method='auto', batch_frames=12, batch_context=0,
                     projection='perspective')
    st.set_intrinsics(FOCAL, PRINCIPAL)
    _push(st, ids, W, range(24))
    bound = stream_mod.PLANAR_PERSPECTIVE_RATIO
    assert calls == [(bound, 'planar'), (bound * stream_mod.PLANAR_KEPT_RATIO, 'planar')]
    assert stream_mod.PLANAR_KEPT_RATIO > 1.0
    persp = (FOCAL, PRINCIPAL)
    assert original(W[:24], V[:12], persp, planar_ratio=0.0).method != 'planar'
