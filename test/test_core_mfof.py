"""MFOF tracking: subspace fits with known answers, accuracy targets of issue 5 on a generated
deforming sequence with an occluder, occlusion tensor, visibility against the ground truth of a
rendered turning flag, tracks recaptured on a face under large viewpoint change and kept on a
strongly deforming flag (issue 12),
reference re-selection with carried tracks, validation."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from nrsfm_ros.core.tracking import (MFOFConfig, MFOFTracker, ReferenceFlowTracker,
                                     track_sequence)
from nrsfm_ros.core.tracking.mfof import contrast_normalise as mfof_contrast
from nrsfm_ros.core.tracking.mfof import visible_support
from nrsfm_ros.core.tracking.subspace import fit_basis, fit_coefficients, polynomial_basis
from nrsfm_ros.io.synth import SynthConfig, generate
from nrsfm_ros.io.synth_tracks import DeformConfig, generate_deforming


def _errors(W: np.ndarray, seq) -> tuple[float, float, float]:
    """Mean track error over in-view points of frames 1.., over visible and occluded ones."""
    h, w = seq.config.height, seq.config.width
    e = np.hypot(W[0::2] - seq.W[0::2], W[1::2] - seq.W[1::2])
    x, y = seq.W[0::2], seq.W[1::2]
    inview = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    occ = seq.occluded & inview
    return (float(e[1:][inview[1:]].mean()), float(e[1:][seq.V[1:]].mean()),
            float(e[occ].mean()))


@pytest.fixture(scope='module')
def occluder_seq():
    return generate_deforming(DeformConfig(width=320, height=256, frames=50, seed=3,
                                           occluder_frames=15))


def test_generator_ground_truth_is_exact():
    seq = generate_deforming(DeformConfig(width=160, height=128, frames=8, noise=0.0,
                                          illumination=0.0, seed=1))
    h, w = 128, 160
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    for f in (3, 7):
        flow = seq.flow(f).astype(np.float32)
        warped = cv2.remap(seq.images[f].astype(np.float32), gx + flow[..., 0],
                           gy + flow[..., 1], cv2.INTER_LINEAR)
        resid = np.abs(warped - seq.images[0].astype(np.float32))[seq.V[f].reshape(h, w)]
        moved = np.abs(seq.images[f].astype(np.float32) - seq.images[0])[seq.V[f].reshape(h, w)]
        assert resid.mean() < 1.0 < 4 * resid.mean() < moved.mean()
    again = generate_deforming(DeformConfig(width=160, height=128, frames=8, noise=0.0,
                                            illumination=0.0, seed=1))
    np.testing.assert_array_equal(again.images, seq.images)
    with pytest.raises(ValueError, match='strain'):
        DeformConfig(strain=0.9).validate()


def test_fit_basis_fills_missing_entries_of_a_low_rank_field():
    rng = np.random.default_rng(0)
    h, w, N, rank = 24, 32, 12, 3
    fixed = polynomial_basis(h, w, 2)
    yy, xx = np.mgrid[0:h, 0:w]
    imgs = np.stack([np.sin(xx / 5.0 + k) * np.cos(yy / 7.0 - k) for k in range(rank)])
    L = imgs.reshape(rank, -1).astype(np.float32)
    D = (rng.normal(size=(2 * N, rank)) @ L + rng.normal(size=(2 * N, 6)) @ fixed
         ).astype(np.float32)
    weight = np.ones((N, h * w), np.float32)
    hole = ((xx > 10) & (xx < 20) & (yy > 5) & (yy < 15)).ravel()
    weight[4:9, hole] = 0.0                      # a block hidden in 5 of 12 frames
    Dmiss = D.copy()
    Dmiss[8:18, hole] = 50.0                     # garbage where the weight is 0
    learned = fit_basis(Dmiss, weight, fixed, rank, (h, w), iterations=8,
                        smooth_weight=1e-4)
    B = np.concatenate([fixed, learned])
    for f in range(4, 9):
        q = fit_coefficients(B, Dmiss[2 * f:2 * f + 2], weight[f], iterations=0)
        err = np.abs(q @ B - D[2 * f:2 * f + 2])[:, hole]
        assert err.max() < 1e-2 * np.abs(D).max()


def test_fit_coefficients_ignores_outliers():
    rng = np.random.default_rng(1)
    B = np.linalg.qr(rng.normal(size=(2000, 5)))[0].T.astype(np.float32)
    q_true = rng.normal(size=(2, 5)).astype(np.float32) * 40
    d = q_true @ B
    bad = rng.random(2000) < 0.2
    d[:, bad] += rng.normal(0, 30, size=(2, bad.sum()))
    w = np.ones(2000, np.float32)
    plain = fit_coefficients(B, d, w, iterations=0)
    robust = fit_coefficients(B, d, w, huber_px=0.5, iterations=6)
    assert np.abs(robust - q_true).max() < 0.3 * np.abs(plain - q_true).max()


def test_mfof_meets_issue_targets_and_beats_the_anchor(occluder_seq):
    seq = occluder_seq
    anchor = ReferenceFlowTracker(stride=1, mask='full')
    Wa = np.concatenate([anchor.step(im).uv.T for im in seq.images])
    a_all, _, a_occ = _errors(Wa, seq)
    dense = MFOFConfig(stride=1, mask='full')          # every pixel, as the anchor
    stream = track_sequence(seq.images, dense, smooth=False)
    s_all, s_vis, s_occ = _errors(stream.W, seq)
    batch = track_sequence(seq.images, dense, smooth=True)
    b_all, _, b_occ = _errors(batch.W, seq)
    # issue 5: mean error <= 1.0 px over all frames, <= 2.0 px on occluded points.  Seed 3 is
    # the hardest of bench/bench_tracking.py's seeds: the two-sided batch pass meets 2.0 px on
    # it; streaming (1.5 px mean over the seeds) gets 2.6 px here, so it is held to 3.0
    assert s_all <= 1.0 and b_all <= 1.0
    assert b_occ <= 2.0 and s_occ <= 3.0
    assert s_occ < a_occ / 3 and s_all < a_all
    assert b_all <= s_all + 0.05
    assert stream.W.shape == (100, 320 * 256) and stream.O.shape == (50, 320 * 256)


def test_occlusion_tensor_flags_the_occluder(occluder_seq):
    seq = occluder_seq
    tr = MFOFTracker(MFOFConfig(stride=1, mask='full'))
    vis_occ, vis_free = [], []
    for f, im in enumerate(seq.images):
        fr = tr.step(im)
        if seq.occluded[f].sum() > 500:
            vis_occ.append(fr.visibility[seq.occluded[f]].mean())
            vis_free.append(fr.visibility[seq.V[f]].mean())
            assert fr.occlusion[seq.occluded[f]].mean() > 0.6
    assert np.mean(vis_occ) < 0.3 and np.mean(vis_free) > 0.7


def test_reference_is_reselected_when_the_view_leaves_it():
    rng = np.random.default_rng(2)
    big = cv2.GaussianBlur(rng.integers(0, 255, (120, 400)).astype(np.uint8), (0, 0), 1.5)
    frames = [np.ascontiguousarray(big[10:90, 6 * k:6 * k + 96]) for k in range(30)]
    tr = MFOFTracker(MFOFConfig(rank=4, window=8, stride=2, mask='full'))
    out = [tr.step(f) for f in frames]
    re = [fr.index for fr in out if fr.reselected]
    assert re and 8 <= re[0] <= 20
    assert tr.epoch == len(re)
    new, before = out[re[0]], out[re[0] - 1]
    for fr in out:
        assert fr.ids.size == fr.uv.shape[0] == fr.visibility.size == fr.occlusion.size
        assert np.unique(fr.ids).size == fr.ids.size
    # the still-visible tracks are carried across with their ids (first, in their old order),
    # at their positions in the new reference; the uncovered rest of it gets new ids
    carried = np.isin(new.ids, out[0].ids)
    n = int(carried.sum())
    assert n > 200 and carried[:n].all()
    k = np.searchsorted(before.ids, new.ids[:n])
    np.testing.assert_array_equal(before.ids[k], new.ids[:n])
    assert np.abs(new.uv[:n] - before.uv[k]).max() < 8          # one frame of motion
    assert np.all(new.ids[n:] >= 96 * 80)                          # epoch 1 ids
    assert new.ids.size < 1.3 * out[0].ids.size                    # no doubled coverage
    # every track of the new reference (carried or new) follows the pan (6 px per frame left)
    nxt = out[re[0] + 3]
    np.testing.assert_array_equal(nxt.ids, new.ids)
    assert np.median(nxt.uv[:, 0] - new.uv[:, 0]) == pytest.approx(-18, abs=0.5)
    assert np.median(nxt.uv[:n, 0] - new.uv[:n, 0]) == pytest.approx(-18, abs=0.5)


@pytest.fixture(scope='module')
def turning_flag():
    """A waving flag under a 60 degree camera turn: strong foreshortening and shading change,
    ground-truth visibility ~0.997 (nothing is really occluded)."""
    return generate(SynthConfig(surface='flag', camera_motion_deg=60, amplitude=1.0,
                                width=128, height=96, frames=24, seed=0))


def _versus_truth(frames, seq):
    """Per frame 1..: |vis - V_gt| (ids not reported count as vis 0), the fraction of GT-visible
    tracks reported visible, and the mean position error of GT-visible reported tracks."""
    mae, recall, err = [], [], []
    for f, fr in enumerate(frames[1:], 1):
        _, ia, ib = np.intersect1d(fr.ids, seq.track_ids, return_indices=True)
        vis = np.zeros(seq.track_ids.size)
        vis[ib] = fr.visibility[ia]
        V = seq.V[f].astype(bool)
        mae.append(np.abs(vis - V).mean())
        recall.append((vis[V] > 0.5).mean())
        e = np.hypot(fr.uv[ia, 0] - seq.W[2 * f, ib], fr.uv[ia, 1] - seq.W[2 * f + 1, ib])
        err.append(e[V[ib]].mean())
    return float(np.mean(mae)), float(np.mean(recall)), float(np.mean(err))


def test_visibility_follows_ground_truth_under_foreshortening_and_shading(turning_flag):
    seq = turning_flag
    tr = MFOFTracker(MFOFConfig(stride=2, mask='full'))
    out = [tr.step(cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)) for im in seq.images]
    assert seq.V[1:].mean() > 0.99
    assert not any(fr.reselected for fr in out) and tr.epoch == 0
    mae, recall, err = _versus_truth(out, seq)
    # measured 0.165 / 0.894 / 0.75 px; the tracker before (high-pass residual, FB check on the
    # unwarped pair, re-selection on visibility) gave 0.59 / 0.40 / 1.27 px and re-selected
    assert mae < 0.25 and recall > 0.8 and err < 1.1


def test_forced_reselection_carries_tracks_with_their_ids(turning_flag):
    seq = turning_flag
    grey = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in seq.images]
    tr = MFOFTracker(MFOFConfig(stride=2, mask='full'))
    switch = 10
    out = [tr.step(g) for g in grey[:switch + 1]]
    fr = out[-1]
    keep = fr.visibility > 0.5
    with pytest.raises(ValueError, match='unique current track ids'):
        tr.reselect(grey[switch], np.array([fr.ids[0], fr.ids[0]]), fr.uv[:2])
    tr.reselect(grey[switch], fr.ids[keep], fr.uv[keep])
    n = int(keep.sum())
    assert tr.epoch == 1
    np.testing.assert_array_equal(tr.ids[:n], fr.ids[keep])
    np.testing.assert_allclose(tr.reference_xy[:n], fr.uv[keep])
    assert not np.isin(tr.ids[n:], out[0].ids).any()
    after = [tr.step(g) for g in grey[switch + 1:]]
    for a in after:
        np.testing.assert_array_equal(a.ids, tr.ids)
        assert a.uv.shape == (tr.ids.size, 2)
    # the carried tracks continue smoothly: their error against the ground truth after the
    # switch stays close to the error before it
    common, ia, ib = np.intersect1d(fr.ids[keep], seq.track_ids, return_indices=True)
    assert common.size > 0.8 * seq.V[switch].sum()        # most surface tracks visible there

    def err(f, frame):
        order = np.argsort(frame.ids)
        k = order[np.searchsorted(frame.ids, common, sorter=order)]
        np.testing.assert_array_equal(frame.ids[k], common)
        V = seq.V[f, ib].astype(bool)
        e = np.hypot(frame.uv[k, 0] - seq.W[2 * f, ib], frame.uv[k, 1] - seq.W[2 * f + 1, ib])
        return float(e[V].mean())

    before = np.mean([err(f, out[f]) for f in range(switch - 3, switch + 1)])
    post = [err(f, a) for f, a in enumerate(after, switch + 1)]
    assert max(post[:3]) < before + 0.5 and np.mean(post) < before + 1.0 and max(post) < 2.5
    # track_sequence keeps the first reference's P and continues the carried tracks
    res = track_sequence(grey[:switch + 4], MFOFConfig(stride=2, mask='full',
                                                       reselect_fraction=0.99,
                                                       reselect_patience=1), smooth=False)
    assert res.reselections and res.W.shape == (2 * (switch + 4), out[0].ids.size)
    f = res.reselections[0] + 1
    assert res.V[f].mean() > 0.5


def _chained(grey: list[np.ndarray], xy: np.ndarray) -> np.ndarray:
    """Naive baseline: DIS-medium frame to frame, chained at the positions xy (P, 2): (F, P, 2)."""
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    pos = [np.asarray(xy, np.float32)]
    for a, b in zip(grey[:-1], grey[1:]):
        flow = dis.calc(a, b, None)
        p = pos[-1].reshape(1, -1, 2)
        pos.append(pos[-1] + cv2.remap(flow, p[..., 0], p[..., 1], cv2.INTER_LINEAR,
                                       borderMode=cv2.BORDER_REPLICATE).reshape(-1, 2))
    return np.stack(pos)


def test_recapture_keeps_tracks_on_a_face_under_60_deg_camera_motion():
    """A rendered face (256x192, 30 frames) seen from a camera swinging over ~74 deg: the far
    cheek foreshortens and darkens until its tracks are lost, then comes back into view.  The
    coarse-to-fine recapture pass finds them again; without it (``recapture_margin=0``, the
    tracker before) they stay carried by a drifting subspace."""
    seq = generate(SynthConfig(surface='face', frames=30, camera_motion_deg=60.0))
    grey = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in seq.images]
    tr = MFOFTracker(MFOFConfig(stride=2, mask='texture'))     # the tracker node's defaults
    out = [tr.step(g) for g in grey]
    assert not any(fr.reselected for fr in out)
    _, ia, ib = np.intersect1d(out[0].ids, seq.track_ids, return_indices=True)
    assert ib.size > 0.95 * seq.track_ids.size
    uv = np.stack([fr.uv[ia] for fr in out])
    vis = np.stack([fr.visibility[ia] for fr in out])
    gt = np.stack([seq.W[0::2, ib], seq.W[1::2, ib]], axis=-1)
    V = seq.V[:, ib] > 0.5
    late = np.zeros_like(V)
    late[20:] = V[20:]                      # the last third: the cheek is back in view
    err = np.linalg.norm(uv - gt, axis=-1)
    chain = np.linalg.norm(_chained(grey, seq.W[:2, ib].T) - gt, axis=-1)
    kept = float((vis[1:][V[1:]] > 0.5).mean())
    # measured: last third 1.43 px (chained 3.14 px; recapture_margin=0 3.05 px), all frames
    # 0.92 px (1.46 px), kept 0.81 (0.79); 1.81 px on another machine (the tracker is chaotic
    # on such views: a last-bit difference grows to pixels within ~8 frames), so the bounds sit
    # between that and the tracker without recapture
    assert err[late].mean() < 2.4 and err[late].mean() < 0.75 * chain[late].mean()
    assert err[1:][V[1:]].mean() < 1.2 and kept > 0.78


def test_the_recapture_pass_in_its_thread_gives_the_tracks_of_the_serial_tracker(monkeypatch):
    """The recapture pass runs in a second thread beside the data step (OpenCV's DIS
    releases the GIL): the same calls as in sequence, so the same tracks to the last bit as a
    tracker held to one thread (``core.threads.set_workers(1)``: a fleet worker)."""
    import threading

    from nrsfm_ros.core import threads
    from nrsfm_ros.core.tracking import mfof
    seq = generate(SynthConfig(surface='face', frames=12, camera_motion_deg=60.0))
    grey = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in seq.images]
    names = set()
    flow = mfof.MFOFTracker._recapture_flow

    def recorded(self, *a):
        names.add(threading.current_thread().name)
        return flow(self, *a)
    monkeypatch.setattr(mfof.MFOFTracker, '_recapture_flow', recorded)
    monkeypatch.setattr(threads, 'WORKERS', threads.WORKERS)     # restored after the test
    runs = []
    for n in (2, 1):
        threads.set_workers(n)
        tr = MFOFTracker(MFOFConfig(stride=2, mask='texture'))
        runs.append(np.stack([tr.step(g).uv for g in grey]))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert any(n.startswith('mfof-recapture') for n in names)          # the threaded run
    assert threading.current_thread().name in names                      # the serial one


def test_offset_prediction_keeps_a_strongly_deforming_flag_under_60_deg_camera_motion():
    """A rendered flag at twice the deformation amplitude (30 frames) under a ~74 deg camera
    swing: folds deform faster than the first subspace (polynomial images only, then a rank-8
    window) follows.  The prediction that keeps every pixel's offset from the subspace
    (``predict_offset``) keeps those tracks; the subspace-only prediction (the tracker before)
    loses a strip of the flag within 5 frames and carries it on a drifting subspace."""
    seq = generate(SynthConfig(surface='flag', width=256, height=192, frames=30,
                               camera_motion_deg=60.0, amplitude=2.0))
    grey = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in seq.images]
    res = {}
    for on in (True, False):
        tr = MFOFTracker(MFOFConfig(stride=2, mask='texture', predict_offset=on))
        out = [tr.step(g) for g in grey]
        _, ia, ib = np.intersect1d(out[0].ids, seq.track_ids, return_indices=True)
        uv = np.stack([fr.uv[ia] for fr in out])
        vis = np.stack([fr.visibility[ia] for fr in out])
        gt = np.stack([seq.W[0::2, ib], seq.W[1::2, ib]], axis=-1)
        V = seq.V[:, ib] > 0.5
        err = np.linalg.norm(uv - gt, axis=-1)[1:][V[1:]]
        res[on] = (float(err.mean()), float((vis[1:][V[1:]] > 0.5).mean()))
    chain = np.linalg.norm(_chained(grey, seq.W[:2, ib].T) - gt, axis=-1)[1:][V[1:]].mean()
    (err, kept), (err_old, kept_old) = res[True], res[False]
    # measured: 1.51 px, kept 0.82; chained 4.13 px; predict_offset=False 3.11 px, kept 0.71
    # (DIS's output depends on the CPU's SIMD path: 2.47 px without the offset on another
    # machine; on a third 1.75 px against 2.46 without, chained 4.13: hence 0.8x; on a fourth,
    # session 28: 1.66-1.90 px, kept 0.81, against 4.44 px, kept 0.68; session 33, another
    # machine: 1.75 px, kept 0.80 against 0.73 without the fusion gap, 0.77 against 0.68 with
    # it, the default, which hides some good observations by design)
    print(f'offset {err:.2f} px kept {kept:.2f}; without {err_old:.2f} kept {kept_old:.2f}; '
          f'chained {chain:.2f}')
    assert err < 2.0 and err < 0.5 * chain and err < 0.8 * err_old
    assert kept > 0.75 and kept > kept_old + 0.06


def test_mfof_rejects_bad_input():
    with pytest.raises(ValueError, match='preset'):
        MFOFConfig(preset='slow').validate()
    with pytest.raises(ValueError, match='rank'):
        MFOFTracker(MFOFConfig(rank=-1))
    with pytest.raises(ValueError, match='reselect_fraction'):
        MFOFConfig(reselect_fraction=1.5).validate()
    with pytest.raises(ValueError, match='collapse_fraction'):
        MFOFConfig(collapse_fraction=-0.1).validate()
    with pytest.raises(ValueError, match='ncc_threshold'):
        MFOFConfig(ncc_threshold=0).validate()
    with pytest.raises(ValueError, match='recapture_margin'):
        MFOFConfig(recapture_margin=-0.1).validate()
    with pytest.raises(ValueError, match='chain_check_px'):
        MFOFConfig(chain_check_px=-1.0).validate()
    with pytest.raises(ValueError, match='lk_radius'):
        MFOFConfig(lk_radius=-1).validate()
    with pytest.raises(ValueError, match='lk_iterations'):
        MFOFConfig(lk_iterations=0).validate()
    tr = MFOFTracker(MFOFConfig(stride=1, mask='full'))
    tr.step(np.full((40, 50), 100, np.uint8))
    with pytest.raises(ValueError, match='differs from the reference'):
        tr.step(np.zeros((10, 10), np.uint8))
    with pytest.raises(ValueError, match='uint8'):
        tr.step(np.zeros((40, 50), np.float32))
    with pytest.raises(ValueError, match=r'\(8, 60\) smaller than 16 px'):  # was OpenCV's
        MFOFTracker(MFOFConfig(stride=1, mask='full')).step(np.full((8, 60), 9, np.uint8))


def _shifted_texture(frames: int, step: float) -> list[np.ndarray]:
    """A random texture translated by ``step`` px a frame along x (grey uint8, 96 x 128)."""
    rng = np.random.default_rng(4)
    base = cv2.GaussianBlur(rng.uniform(0, 255, (96, 160)).astype(np.float32), (0, 0), 1.5)
    out = []
    for f in range(frames):
        M = np.float32([[1, 0, -f * step], [0, 1, 0]])
        out.append(np.clip(cv2.warpAffine(base, M, (160, 96))[:, 16:144], 0, 255)
                   .astype(np.uint8))
    return out


def test_chained_check_flags_tracks_that_leave_the_frame_to_frame_chain():
    """``chain_check_px``: tracks consistent with the frame-to-frame flow stay as they were;
    tracks moved 8 px off it are reported not visible (occlusion 1) and the chain carries their
    chained position on, so they become visible again once back on it.  Off: untouched."""
    grey = _shifted_texture(4, 1.0)
    off = MFOFTracker(MFOFConfig(stride=4, mask='full'))
    on = MFOFTracker(MFOFConfig(stride=4, mask='full', chain_check_px=2.0))
    for g in grey[:3]:
        a, b = off.step(g), on.step(g)
    inner = (a.uv[:, 0] > 8) & (a.uv[:, 0] < 120) & (a.uv[:, 1] > 8) & (a.uv[:, 1] < 88)
    assert on.chain_rejected <= 0.02 * a.ids.size
    assert np.array_equal(a.visibility[inner], b.visibility[inner])
    # frame 3, as the tracker would give it but with every other track 8 px off
    good = on._step(grey[3])
    gn = mfof_contrast(grey[3])
    moved = np.zeros(good.ids.size, bool)
    moved[::2] = True
    bad = good.__class__(**{**good.__dict__, 'uv': good.uv + 8.0 * moved[:, None]})
    saved = on._chain
    out = on._chain_check(gn, bad)
    assert (out.visibility[moved & inner] == 0).all() and (out.occlusion[moved & inner] == 1).all()
    assert np.array_equal(out.visibility[~moved & inner], good.visibility[~moved & inner])
    # the same frame's true positions against the chain carried on: consistent again
    on._chain = saved
    on._chain_check(gn, bad)
    grey4 = _shifted_texture(5, 1.0)[4]
    nxt = on._step(grey4)
    back = on._chain_check(mfof_contrast(grey4), nxt)
    assert on.chain_rejected <= 0.05 * nxt.ids.size
    assert (back.visibility[moved & inner] > 0.5).mean() > 0.9


def test_visible_support_is_the_visible_share_of_the_mask_around_each_pixel():
    mask = np.ones((12, 12), bool)
    mask[:, 8:] = False                      # pixels off the mask never count
    vis = np.zeros((12, 12), bool)
    vis[5, 5] = True
    vis[:, 10] = True                        # visible but off the mask
    share = visible_support(vis, mask, 1)
    assert share[5, 5] == pytest.approx(1 / 9) and share[4, 4] == pytest.approx(1 / 9)
    assert share[0, 0] == 0.0 and share[5, 10] == 0.0      # no mask pixel near: 0
    assert share[5, 8] == pytest.approx(0.0)
    vis[:] = True
    share = visible_support(vis, mask, 2)
    assert share[:, :8].min() == 1.0          # clipped windows at the border count their own
    assert share[:, 11].max() == 0.0


def test_visibility_support_drops_tracks_dragged_by_an_occluder():
    """``support_radius``: on a rendered flag turning 60 deg with a disc sweeping across, most
    observations reported visible but more than 3 px off the truth sit among occluded
    neighbours (dragged by the disc or slid off the surface): the support check reports at
    least half of them not visible, at a cost of under 10% of the true visible observations
    kept within 3 px."""
    seq = generate(SynthConfig(surface='flag', width=256, height=192, frames=40,
                               camera_motion_deg=60, amplitude=2, occluder=True))
    col = {int(i): k for k, i in enumerate(seq.track_ids)}
    grey = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in seq.images]

    def shares(radius: int) -> tuple[float, float]:
        tracker = MFOFTracker(MFOFConfig(support_radius=radius))
        bad = good = kept = truth = 0
        for f, g in enumerate(grey):
            fr = tracker.step(g)
            k = np.array([col.get(int(i), -1) for i in fr.ids])
            ok = k >= 0
            e = np.hypot(fr.uv[ok, 0] - seq.W[2 * f, k[ok]],
                         fr.uv[ok, 1] - seq.W[2 * f + 1, k[ok]])
            v, t = fr.visibility[ok] >= 0.5, seq.V[f, k[ok]] >= 0.5
            bad += int((v & (e > 3)).sum())
            good += int((v & (e <= 3)).sum())
            kept += int((v & t & (e <= 3)).sum())
            truth += int(t.sum())
        return bad / (bad + good), kept / truth
    bad_off, kept_off = shares(0)
    bad_on, kept_on = shares(6)
    assert bad_on < 0.5 * bad_off, (bad_on, bad_off)
    assert kept_on > 0.9 * kept_off, (kept_on, kept_off)


def test_fusion_gap_hides_published_positions_the_frame_does_not_support():
    """``fusion_gap_px``: on a rendered cap turning 60 deg with a disc sweeping across, the
    tracks lost behind the disc are carried on by the motion subspace to where the frame's own
    flow does not put them, yet pass the FB and ZNCC checks; the gate reports at least 40% of
    the visible observations over 3 px off not visible, at a cost of under 3% of those within
    3 px, and leaves the positions and the re-selections as they were."""
    seq = generate(SynthConfig(surface='sphere', width=256, height=192, frames=40,
                               camera_motion_deg=60, amplitude=1, occluder=True))
    col = {int(i): k for k, i in enumerate(seq.track_ids)}
    grey = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in seq.images]

    def run(gap: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        tracker = MFOFTracker(MFOFConfig(fusion_gap_px=gap))
        err, vis, uv = [], [], []
        for f, g in enumerate(grey):
            fr = tracker.step(g)
            k = np.array([col.get(int(i), -1) for i in fr.ids])
            ok = k >= 0
            err.append(np.hypot(fr.uv[ok, 0] - seq.W[2 * f, k[ok]],
                                fr.uv[ok, 1] - seq.W[2 * f + 1, k[ok]]))
            vis.append(fr.visibility[ok] >= 0.5)
            uv.append(fr.uv)
        return np.concatenate(err), np.concatenate(vis), np.concatenate(uv), tracker.epoch
    e, v_off, uv_off, epochs_off = run(0.0)
    e_on, v_on, uv_on, epochs_on = run(1.0)
    np.testing.assert_array_equal(uv_on, uv_off)
    assert epochs_on == epochs_off
    bad, good = v_off & (e > 3), v_off & (e <= 3)
    assert bad.sum() > 0.05 * v_off.sum()           # the failure is there to remove
    assert not (v_on & ~v_off).any()
    assert (bad & ~v_on).sum() >= 0.4 * bad.sum(), ((bad & ~v_on).sum(), bad.sum())
    assert (good & ~v_on).sum() < 0.03 * good.sum(), ((good & ~v_on).sum(), good.sum())


def _textured(h: int, w: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.random((h, w)).astype(np.float32) * 255, (0, 0), 1.5)


def test_lk_reference_recovers_a_known_affine_warp_and_keeps_what_it_cannot_improve():
    """``LKReference.refine``: a frame that is the reference under a known affine map (a
    stretch, a shear and a sub-pixel shift), tracks started 0.4-0.8 px off with the flow's
    Jacobian: refined to within 0.12 px (median 0.05); one started on the truth stays there;
    tracks that are not selected, on a flat patch, or that would move more than
    ``LK_MAX_MOVE`` px keep their positions."""
    from nrsfm_ros.core.tracking import mfof as mfof_module
    from nrsfm_ros.core.tracking.mfof import LK_MAX_MOVE, LKReference
    h, w = 120, 160
    ref = _textured(h, w)
    ref[:, :20] = 128.0                           # a flat strip: nothing to align on
    A = np.array([[1.08, 0.05], [-0.04, 0.95]])
    t = np.array([3.3, -1.7])
    frame = cv2.warpAffine(ref, np.hstack([A, t[:, None]]), (w, h), flags=cv2.INTER_CUBIC)
    ys, xs = np.mgrid[30:90:6, 30:130:6]
    p0 = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
    truth = p0 @ A.T + t
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    grid = np.stack([gx, gy], -1)
    flow = (grid @ A.T + t - grid).astype(np.float32)
    rng = np.random.default_rng(1)
    off = rng.normal(size=p0.shape)
    off *= rng.uniform(0.4, 0.8, (p0.shape[0], 1)) / np.linalg.norm(off, axis=1, keepdims=True)
    lk = LKReference(ref)
    start = truth + off
    start[0] = truth[0]
    out = lk.refine(frame, flow, p0, start, np.ones(p0.shape[0], bool), 4, 5)
    err = np.linalg.norm(out - truth, axis=1)      # bilinear sampling limits it to ~0.1 px
    assert err.max() < 0.12 and np.median(err) < 0.05, err
    assert np.linalg.norm(start - truth, axis=1)[1:].min() > 0.39
    # not selected: unchanged
    some = np.zeros(p0.shape[0], bool)
    some[::2] = True
    out2 = lk.refine(frame, flow, p0, start, some, 4, 5)
    np.testing.assert_array_equal(out2[~some], start[~some])
    np.testing.assert_allclose(out2[some], out[some])
    # a flat template, or a start beyond the kernel's reach of LK_MAX_MOVE: kept
    flat = np.array([[8.0, 60.0]])
    np.testing.assert_array_equal(
        lk.refine(frame, flow, flat, flat + 0.5, np.ones(1, bool), 4, 5), flat + 0.5)
    far = truth + [LK_MAX_MOVE + 0.5, 0.0]
    every = np.ones(p0.shape[0], bool)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(mfof_module, 'LK_MAX_MOVE', 100.0)
        free = lk.refine(frame, flow, p0, far, every, 4, 40)
    found = np.linalg.norm(free - truth, axis=1) < 0.12     # the truth, but too far a move
    assert found.mean() > 0.5
    np.testing.assert_array_equal(lk.refine(frame, flow, p0, far, every, 4, 40)[found],
                                  far[found])


def test_lk_refinement_lowers_the_track_error_under_60_deg_camera_motion():
    """``lk_radius``: on a rendered flag turning 60 deg the published positions of the
    visible tracks are closer to the truth with the affine refinement than without (median
    and 90th percentile), and the visibility is the same (only positions change)."""
    seq = generate(SynthConfig(surface='flag', width=192, height=144, frames=30,
                               camera_motion_deg=60))
    col = {int(i): k for k, i in enumerate(seq.track_ids)}
    grey = [cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in seq.images]

    def errors(radius: int) -> tuple[np.ndarray, np.ndarray]:
        tracker = MFOFTracker(MFOFConfig(lk_radius=radius))
        errs, vis = [], []
        for f, g in enumerate(grey):
            fr = tracker.step(g)
            k = np.array([col.get(int(i), -1) for i in fr.ids])
            ok = (k >= 0) & (fr.visibility >= 0.5)
            ok[ok] &= seq.V[f, k[ok]] >= 0.5
            errs.append(np.hypot(fr.uv[ok, 0] - seq.W[2 * f, k[ok]],
                                 fr.uv[ok, 1] - seq.W[2 * f + 1, k[ok]]))
            vis.append(fr.visibility)
        return np.concatenate(errs[1:]), np.concatenate(vis)
    e0, v0 = errors(0)
    e4, v4 = errors(4)
    np.testing.assert_array_equal(v0, v4)
    assert np.median(e4) < 0.7 * np.median(e0), (np.median(e4), np.median(e0))
    assert np.percentile(e4, 90) < 0.85 * np.percentile(e0, 90)


def test_dis_finest_scale_is_the_presets_below_640_px_and_coarser_per_doubling():
    from nrsfm_ros.core.tracking.mfof import dis_finest_scale
    assert [dis_finest_scale(-1, 1, s) for s in ((240, 320), (479, 639), (480, 640),
                                                 (640, 480), (960, 1280), (1080, 1920))] == \
        [1, 1, 2, 2, 3, 3]
    assert dis_finest_scale(0, 1, (480, 640)) == 0          # an explicit level wins
    assert dis_finest_scale(-1, 2, (480, 640)) == 3         # the fast presets' own is 2
    with pytest.raises(ValueError, match='recapture_finest_scale'):
        MFOFConfig(recapture_finest_scale=-2).validate()


def test_auto_recapture_scale_at_640x480_keeps_the_track_error():
    """At 640x480 the recapture pass runs DIS one level coarser (auto, ~1.25x the frame rate);
    the data step keeps the preset's level: the tracks' error against the ground truth stays
    that of the recapture pass at the preset's own level 1, and at 320x240 nothing changes."""
    from nrsfm_ros.core.metrics import track_error_px
    seq = generate(SynthConfig(surface='face', width=640, height=480, frames=8,
                               camera_motion_deg=30.0))
    errs = {}
    for level in (-1, 1):
        tr = MFOFTracker(MFOFConfig(recapture_finest_scale=level))
        uv = [tr.step(cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)).uv.T for im in seq.images]
        assert tr._rec.getFinestScale() == (2 if level < 0 else 1)
        assert tr._fwd.getFinestScale() == 1
        common, ia, ib = np.intersect1d(tr.ids, seq.track_ids, return_indices=True)
        assert common.size > 0.8 * seq.track_ids.size
        errs[level] = track_error_px(np.concatenate(uv)[:, ia], seq.W[:, ib], seq.V[:, ib])
    assert errs[-1] < 0.3 and errs[-1] < 1.15 * errs[1], errs
    small = MFOFTracker()
    small.step(cv2.resize(cv2.cvtColor(seq.images[0], cv2.COLOR_RGB2GRAY), (320, 240)))
    assert small._rec.getFinestScale() == 1
