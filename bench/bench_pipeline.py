"""End-to-end pipeline accuracy (issue 12): what a subscriber of nrsfm/points receives, against
the trivial baselines, over a sweep of rendered sequences.

    .venv/bin/python bench/bench_pipeline.py [--surfaces flag,face,sheet,sphere]
        [--motions 12,30,60] [--amplitudes 1,2] [--occluder off,on] [--size 256x192]
        [--frames 60] [--modes window,online,batch] [--gt-methods rigid,lowrank,planar,bmm]
        [--true-cameras] [--periodic N] [--background] [--noise S] [--live] [--perturb N]
        [--tracker-split] [--set name=value ...] [--json out.json]

Per case (``nrsfm-ros synth`` renders, seed 0): metric B (per-frame Procrustes + scale, mean over
frames) of
- the baselines: static oracle (ground-truth frame 0 repeated), flat plane (frame 0 flattened
  onto its plane), and the rigid factorisation of the ground-truth tracks;
- each method of ``--gt-methods`` on the ground-truth tracks (batch, whole sequence), and the
  reconstructor's stream (defaults) fed the ground-truth tracks frame by frame (``stream(GT)``);
- the pipeline: ``process`` (tracker -> reconstructor, shipped defaults) on the rendered bag, for
  each reconstructor mode (the tracker runs once, its tracks feed every mode), and with
  ``--live`` the live node graph over DDS;
- frames in / out (the fewest clouds of any pipeline row) and the ratio of the best pipeline row
  and of ``stream(GT)`` to the static oracle;
- the frames whose published depths are reflected against the truth's
  (``evaluation.depth_reflected_frames``: metric B forgives a reflection, a subscriber does
  not), for ``stream(GT)`` and each mode;
- why a case may be hard: the camera's rotation range (deg) over the sequence, which is what
  makes depth observable to an orthographic factorisation; with ``--true-cameras``, the
  observability bound: the ground-truth tracks reconstructed with the TRUE camera rotations and
  scales given (one rigid shape, and ``bmm``'s nuclear-norm shapes), so no camera error is
  left, only what the camera motion reveals of the deformation (:func:`true_camera_bound`);
- on occluder cases, per pipeline row, the error on the points behind the occluder and on the
  visible points of the same frames (:func:`occluded_split`; issue 13's target: occluded <=
  1.2x visible), printed as a second table.
A pipeline row scores only the frames and points it published that match ground truth (by stamp
and track id); its static/flat baselines are recomputed on exactly those points (`static*`).
``--periodic N``: every case's deformation repeats with a period of N frames while the camera
keeps moving (``synth --periodic``; issue 13's recurring states, for ``--modes dspr``).
With ``--frames`` above the reconstructor's ``batch_frames`` (60), a table gives each row's
e3D over the first batch's frames and over the later ones (:func:`batch_split`; the static
baseline on the same points): what a longer stream gets after its first batch solve.
``--set name=value``: reconstructor parameters (YAML values, as on the node) for the pipeline
rows and ``stream(GT)``, e.g. ``--set projection=weak batch_frames=30``.
``--perturb N``: each pipeline mode also runs on N perturbed copies of every render (+-1 grey
level on 1% of the pixels, seeded 1..N: :func:`perturbed`), scored against the same truth, and
a table gives the unperturbed value with the perturbed ones' min / median / max: how far one
render can be trusted to rank methods (session 24: occluded planar cases moved 0.03-0.41).
``--tracker-split``: where the tracker costs, per case (``evaluation.tracker_split``, on the
tracker's tracks that ground truth knows, i.e. those of its first reference): the stream on its
tracks, on the true positions with its visibility (what its missing-data pattern costs) and on
its positions with the true visibility (what its position errors cost), with the visible
observations' pixel error (median, p90, share over 3 px) and the visible shares; a table.
``--modes`` also takes ``dspr-full``: ``dspr`` with its recurrence test off (no frame is served
from a stored state, every one goes through the per-frame energy): issue 13's "the same mode
without compression", which the compression table then compares ``dspr`` with.
"""
from __future__ import annotations

import json
import shutil
import sys
import tempfile
import inspect
import time
from collections.abc import Callable
from dataclasses import fields, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchlib import parser, table  # noqa: E402
from nrsfm_ros.core.metrics import rotation_range_deg  # noqa: E402
from nrsfm_ros.core.nrsfm import reconstruct  # noqa: E402
from nrsfm_ros.core.nrsfm.perspective import corrected_tracks  # noqa: E402
from nrsfm_ros.evaluation import (depth_reflected_frames, read_clouds,  # noqa: E402
                                  read_tracks, score, shapes_as_clouds, stream_on_tracks,
                                  tracker_split)
from nrsfm_ros.io.sequence_bag import write_sequence_bag  # noqa: E402
from nrsfm_ros.io.synth import SynthConfig, generate  # noqa: E402
from nrsfm_ros.core.nrsfm.stream import StreamNRSfM  # noqa: E402
from nrsfm_ros.params import ReconstructorParams, TrackerParams  # noqa: E402
from nrsfm_ros.pipeline import process_bag  # noqa: E402

GT_KW = {'lowrank': {'rank': 3}}
STREAM_ARGS = set(inspect.signature(StreamNRSfM).parameters)


def stream_overrides(rec: ReconstructorParams) -> dict:
    """The parameters of ``rec`` that differ from the defaults, as ``make_stream`` overrides
    (``mode`` excluded: ``stream(GT)`` is the default mode's stream)."""
    base = ReconstructorParams()
    return {f.name: getattr(rec, f.name) for f in fields(rec)
            if f.name != 'mode' and getattr(rec, f.name) != getattr(base, f.name)
            and f.name in STREAM_ARGS}


def camera_range_deg(T: np.ndarray) -> float:
    """Largest rotation between any frame's camera and frame 0's (deg)."""
    return rotation_range_deg(T[:, :3, :3])


def occluded_split(clouds: dict, seq) -> tuple[float, float]:
    """RMS point error (relative to the frame's RMS radius, after per-frame Procrustes with
    scale on the matched points) of the points the occluder disc covers (their ground-truth
    projection inside it) and of the other visible points, over the frames it covers any."""
    from nrsfm_ros.core.metrics import batched_procrustes
    F, P = seq.V.shape
    order = np.argsort(seq.track_ids.astype(np.int64))
    sorted_ids = seq.track_ids.astype(np.int64)[order]
    occ_e, vis_e = [], []
    for f, (X, ids) in clouds.items():
        if seq.occluder is None or not 0 <= f < F:
            continue
        ids = np.asarray(ids).astype(np.int64)
        pos = np.clip(np.searchsorted(sorted_ids, ids), 0, sorted_ids.size - 1)
        ok = (sorted_ids[pos] == ids) & np.isfinite(X).all(axis=1)
        cols = order[pos[ok]]
        u, v, r = seq.occluder[f, :3]
        uv = seq.W.reshape(F, 2, P)[f][:, cols]
        covered = np.hypot(uv[0] - u, uv[1] - v) <= r
        visible = (seq.V[f, cols] > 0.5) & ~covered
        if covered.sum() < 4 or visible.sum() < 4:
            continue
        A, B = X[ok] - X[ok].mean(0), seq.S[f, cols] - seq.S[f, cols].mean(0)
        A = batched_procrustes(A[None], B[None], scale=True)[0]
        e = np.linalg.norm(A - B, axis=1) / np.sqrt((B ** 2).sum(1).mean())
        occ_e.append(e[covered])
        vis_e.append(e[visible])
    if not occ_e:
        return float('nan'), float('nan')
    return (float(np.sqrt(np.mean(np.concatenate(occ_e) ** 2))),
            float(np.sqrt(np.mean(np.concatenate(vis_e) ** 2))))


def true_camera_bound(seq) -> tuple[float, float]:
    """e3D of the ground-truth tracks reconstructed with the true cameras given: (one rigid
    shape, ``bmm``'s nuclear-norm shapes).  Orthographic with each frame's true scale (focal /
    mean depth): what is left is what the camera motion does not reveal."""
    from nrsfm_ros.core.nrsfm.bmm import bmm_shapes
    from nrsfm_ros.core.nrsfm.factorization import _centre, _solve_rigid_shape
    V = np.maximum(seq.V, 1e-3)
    F, P = V.shape
    Wc, _ = _centre(seq.W, V)
    scale = seq.K[0, 0] / seq.S[:, :, 2].mean(1)
    Wn = (Wc.reshape(F, 2, P) / scale[:, None, None]).reshape(2 * F, P)
    R = seq.T_camera_world[:, :3, :3]
    S0 = _solve_rigid_shape(Wn, V, R[:, :2], np.ones(F))
    S, *_ = bmm_shapes(Wn, V, R[:, :2], 0.01, 300, init=np.broadcast_to(S0, (F, 3, P)).copy())

    def e(S_cam: np.ndarray) -> float:
        return score(shapes_as_clouds(S_cam, seq.track_ids), seq).summary()['e3d']
    return e(np.einsum('fij,jp->fpi', R, S0)), e(np.einsum('fij,fjp->fpi', R, S))


def case_config(surface: str, size: tuple[int, int], frames: int, motion: float, amp: float,
                occluder: bool, periodic: int = 0, distance: float = 4.0,
                background: bool = False, noise: float = 0.0) -> SynthConfig:
    """The render of one sweep case (seed 0); ``periodic`` > 0: the deformation's period in
    frames; ``distance``: the camera's distance to the surface (m; the focal length follows so
    that the surface keeps its size in the image: 4 m is a ~19 deg field of view, nearly
    weak perspective, 1.6 m a ~45 deg one, an ordinary camera's); ``background``: a textured
    wall behind the surface (and its mask on camera/mask for the tracker's ``roi_mask``);
    ``noise``: the images' Gaussian noise (grey levels, sigma)."""
    return SynthConfig(surface=surface, width=size[0], height=size[1], frames=frames, seed=0,
                       camera_motion_deg=motion, amplitude=amp, occluder=occluder,
                       period_frames=periodic, distance=distance, background=background,
                       noise=noise)


def true_depth_bound(seq) -> float:
    """e3D of the reconstructor's stream (its defaults, weak perspective) fed the ground-truth
    tracks corrected by the *true* depth ratios Z / Zbar of every point and frame (the
    perspective step's correction made exact): what is left is the shape model's, and the gap
    to ``stream(GT)`` is what the perspective step's estimate of the depths costs."""
    V = np.maximum(seq.V, 1e-3)
    Z = seq.S[:, :, 2]
    ratio = Z / ((Z * V).sum(1) / V.sum(1))[:, None]
    W = corrected_tracks(seq.W, ratio, seq.K[:2, 2])
    return score(stream_on_tracks(W, seq.V, seq.track_ids, None), seq).summary()['e3d']


# bench-only modes: (reconstructor mode, parameter overrides)
VARIANTS = {'dspr-full': ('dspr', {'dspr_recurrence_px': 1e-12})}


def mode_params(rec: ReconstructorParams, mode: str) -> ReconstructorParams:
    """The reconstructor's parameters for one pipeline row (``VARIANTS`` resolved)."""
    base, over = VARIANTS.get(mode, (mode, {}))
    return replace(rec, mode=base, **over)


def perturbed(images: np.ndarray, seed: int, share: float = 0.01) -> np.ndarray:
    """A copy of ``images`` (F, H, W, C) uint8 with +-1 grey level (all channels alike) on
    ``share`` of the pixels of every frame, drawn from ``seed``: a change far below any
    camera's noise, to measure how a pipeline result depends on its exact input."""
    rng = np.random.default_rng(seed)
    out = images.astype(np.int16)
    hit = rng.random(out.shape[:3]) < share
    step = rng.choice(np.array([-1, 1], np.int16), size=out.shape[:3])
    out += (hit * step)[..., None] if out.ndim == 4 else hit * step
    return np.clip(out, 0, 255).astype(np.uint8)


def pipeline_runs(seq, bag: Path, out: Path, modes: list[str], rec: ReconstructorParams,
                  trk: TrackerParams | None) -> tuple[float, dict]:
    """``process`` on ``bag``: the tracker once, then the reconstructor in each mode on its
    tracks: (tracker seconds, {mode: (clouds, report, seconds)}).  The tracks stay in
    ``out / 'tracks'`` (with the inputs)."""
    t = time.perf_counter()
    process_bag(bag, out / 'tracks', stages=['tracker'], progress=False, copy_inputs=True,
                params={'tracker': trk} if trk is not None else None)
    tracker_s = time.perf_counter() - t
    runs = {}
    for mode in modes:
        t = time.perf_counter()
        rep = process_bag(out / 'tracks', out / mode, stages=['reconstructor'],
                          progress=False, params={'reconstructor': mode_params(rec, mode)})
        runs[mode] = (read_clouds(out / mode, seq.stamps_ns), rep, time.perf_counter() - t)
    return tracker_s, runs


def batch_split(e3d: np.ndarray, batch: int) -> tuple[float, float]:
    """Mean e3D (per-frame array, NaN where unscored) over a stream's first ``batch`` frames
    (its first batch solve) and over the later ones (NaN where there are none): the sweep's
    60-frame renders are one batch, a user's stream is longer."""
    e = np.asarray(e3d, np.float64)

    def mean(a: np.ndarray) -> float:
        a = a[np.isfinite(a)]
        return float(a.mean()) if a.size else float('nan')
    return mean(e[:batch]), mean(e[batch:])


def run_case(cfg: SynthConfig, modes: list[str], gt_methods: list[str], live: bool,
             work: Path, true_cameras: bool = False,
             rec: ReconstructorParams | None = None, true_depths: bool = False,
             trk: TrackerParams | None = None, perturb: int = 0, split: bool = False
             ) -> dict:
    rec = rec or ReconstructorParams()
    seq = generate(cfg)
    row: dict = {'surface': cfg.surface, 'motion_deg': cfg.camera_motion_deg,
                 'amplitude': cfg.amplitude, 'occluder': bool(getattr(cfg, 'occluder', False)),
                 'frames_in': cfg.frames, 'distance_m': cfg.distance,
                 'camera_range_deg': camera_range_deg(seq.T_camera_world)}
    gt = score(shapes_as_clouds(seq.S, seq.track_ids), seq).summary()
    row['static'], row['flat'] = gt['static'], gt['flat']
    V = np.maximum(seq.V, 1e-3)
    for m in ['rigid'] + [g for g in gt_methods if g != 'rigid']:
        t = time.perf_counter()
        try:
            res = reconstruct(seq.W, V, method=m, **GT_KW.get(m, {}))
            row[f'gt_{m}'] = score(shapes_as_clouds(res.S, seq.track_ids), seq).summary()['e3d']
        except Exception as err:             # a method that fails is a result, not a crash
            row[f'gt_{m}'] = float('nan')
            row[f'gt_{m}_error'] = str(err)
        row[f'gt_{m}_s'] = time.perf_counter() - t
    if true_cameras:
        row['truecam_rigid'], row['truecam_bmm'] = true_camera_bound(seq)
    if true_depths:
        row['truedepth_stream'] = true_depth_bound(seq)
    gt_clouds = stream_on_tracks(seq.W, seq.V, seq.track_ids, seq.K, **stream_overrides(rec))
    sc = score(gt_clouds, seq)
    st = sc.summary()
    row['stream_gt'], row['stream_gt_frames'] = st['e3d'], st['frames_scored']
    row['stream_gt_points'] = st['points_matched_mean']
    row['stream_gt_first'], row['stream_gt_later'] = batch_split(sc.e3d, rec.batch_frames)
    row['stream_gt_inverted'] = depth_reflected_frames(gt_clouds, seq)
    case = work / f'{cfg.surface}_{cfg.camera_motion_deg:g}_{cfg.amplitude:g}'
    if case.exists():
        shutil.rmtree(case)
    case.mkdir(parents=True)
    write_sequence_bag(seq, case / 'in')
    row['tracker_s'], runs = pipeline_runs(seq, case / 'in', case, modes, rec, trk)
    outs = []
    for mode in modes:
        clouds, rep, row[f'{mode}_s'] = runs[mode]
        sc = score(clouds, seq)
        s = sc.summary()
        row[mode], row[f'{mode}_static'] = s['e3d'], s['static']
        row[f'{mode}_points'] = s['points_matched_mean']     # surface points published
        row[f'{mode}_first'], row[f'{mode}_later'] = batch_split(sc.e3d, rec.batch_frames)
        row[f'{mode}_static_first'], row[f'{mode}_static_later'] = \
            batch_split(sc.static, rec.batch_frames)
        row[f'{mode}_inverted'] = depth_reflected_frames(clouds, seq)
        if row['occluder']:
            row[f'{mode}_occluded'], row[f'{mode}_visible'] = occluded_split(clouds, seq)
        row[f'{mode}_frames'] = rep.outputs.get('nrsfm/points', 0)
        st = rep.status.get('reconstructor', {})   # auto's last choice; dspr's compression
        row[f'{mode}_method'] = st.get('last_method', '')
        if 'compression_ratio' in st:
            row[f'{mode}_compression'] = float(st['compression_ratio'])
        row[f'{mode}_failures'] = len(rep.failures)
        outs.append(row[f'{mode}_frames'])
    if live:
        from nrsfm_ros.demo import run_live
        lv = run_live(case / 'in', case / 'live', cfg.frames, rate=1.0, timeout=60,
                      overrides={'tracker': {'reliable': True}})
        s = score(read_clouds(case / 'live', seq.stamps_ns), seq).summary()
        row['live'], row['live_frames'] = s['e3d'], len(read_clouds(case / 'live',
                                                                    seq.stamps_ns))
        row['live_exit'] = lv.get('graph_exit')
        outs.append(row['live_frames'])
    if split:
        W, V, ids = read_tracks(case / 'tracks', seq.stamps_ns)
        row['split'] = tracker_split(W, V, ids, seq, **stream_overrides(rec))
    for k in range(1, perturb + 1):
        pdir = case / f'perturbed_{k}'
        write_sequence_bag(replace(seq, images=perturbed(seq.images, k)), pdir / 'in')
        for mode, (clouds, _, _) in pipeline_runs(seq, pdir / 'in', pdir, modes, rec,
                                                  trk)[1].items():
            row.setdefault(f'{mode}_perturbed', []).append(score(clouds, seq).summary()['e3d'])
        shutil.rmtree(pdir, ignore_errors=True)
    row['frames_out'] = min(outs) if outs else 0
    pipe = [row[k] for k in modes + (['live'] if live else []) if np.isfinite(row[k])]
    row['best_pipeline'] = min(pipe) if pipe else float('nan')
    row['ratio_pipeline'] = row['best_pipeline'] / row['static']
    row['ratio_stream_gt'] = row['stream_gt'] / row['static']
    return row


def main() -> None:
    p = parser(__doc__)
    p.add_argument('--surfaces', default='flag,face,sheet,sphere')
    p.add_argument('--motions', default='12,30,60')
    p.add_argument('--amplitudes', default='1,2')
    p.add_argument('--occluder', default='off,on', help='off, on or off,on')
    p.add_argument('--size', default='256x192')
    p.add_argument('--frames', type=int, default=60)
    p.add_argument('--modes', default='window,online,batch')
    p.add_argument('--gt-methods', default='rigid,lowrank,planar,bmm')
    p.add_argument('--live', action='store_true', help='also run the live graph over DDS')
    p.add_argument('--true-cameras', action='store_true',
                   help='also the observability bound: the ground-truth tracks with the true '
                   'cameras given (rigid shape, bmm shapes)')
    p.add_argument('--true-depths', action='store_true',
                   help='also the stream on the ground-truth tracks corrected by the true '
                   'depths (what the perspective step could reach)')
    p.add_argument('--distance', type=float, default=4.0,
                   help='camera distance in metres (the focal length keeps the surface\'s '
                   'image size: 4 = ~19 deg field of view, 1.6 = ~45 deg)')
    p.add_argument('--background', action='store_true',
                   help='render a textured wall behind the surface (the bags also carry the '
                   "surface's mask, camera/mask: compare --tracker-set roi_mask=true)")
    p.add_argument('--noise', type=float, default=0.0, metavar='S',
                   help="Gaussian noise on the images, sigma in grey levels (a camera's: 1-5)")
    p.add_argument('--periodic', type=int, default=0,
                   help='deformation period in frames (0: the usual non-repeating motion)')
    p.add_argument('--perturb', type=int, default=0, metavar='N',
                   help='also run each pipeline mode on N perturbed copies of every render '
                   '(+-1 grey level on 1%% of the pixels) and tabulate the spread')
    p.add_argument('--tracker-split', action='store_true',
                   help='also split what the tracker costs into its position errors and its '
                   'missing-data pattern (a table)')
    p.add_argument('--work', default=None, help='keep the bags here (default: a temp folder)')
    p.add_argument('--set', nargs='*', default=[], metavar='NAME=VALUE',
                   help='reconstructor parameters (as on the node, YAML values)')
    p.add_argument('--tracker-set', nargs='*', default=[], metavar='NAME=VALUE',
                   help='tracker parameters (as on the node, YAML values)')
    a = p.parse_args()
    import yaml
    rec = ReconstructorParams().updated({k: yaml.safe_load(v) for k, v in
                                         (s.split('=', 1) for s in a.set)})
    trk = TrackerParams().updated({k: yaml.safe_load(v) for k, v in
                                   (s.split('=', 1) for s in a.tracker_set)})
    w, h = (int(v) for v in a.size.split('x'))
    modes = [m for m in a.modes.split(',') if m]
    gt_methods = [m for m in a.gt_methods.split(',') if m]
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix='bench_pipeline_'))
    rows = []
    for surface in a.surfaces.split(','):
        for motion in (float(v) for v in a.motions.split(',')):
            for amp in (float(v) for v in a.amplitudes.split(',')):
                for occ in a.occluder.split(','):
                    cfg = case_config(surface, (w, h), a.frames, motion, amp, occ == 'on',
                                      a.periodic, a.distance, a.background, a.noise)
                    row = run_case(cfg, modes, gt_methods, a.live, work, a.true_cameras, rec,
                                   a.true_depths, trk, a.perturb, a.tracker_split)
                    rows.append(row)
                    print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v)
                                      for k, v in row.items()}), file=sys.stderr)
    if not a.work:
        shutil.rmtree(work, ignore_errors=True)
    pipe_cols = modes + (['live'] if a.live else [])
    header = (['surface', 'cam deg', 'amp', 'occl', 'cam range', 'static', 'flat']
              + [f'{m}(GT)' for m in gt_methods]
              + (['rigid(true cams)', 'bmm(true cams)'] if a.true_cameras else [])
              + ['stream(GT)']
              + (['stream(GT, true depths)'] if a.true_depths else [])
              + [f'{m}' for m in pipe_cols]
              + ['frames in/out', 'pipe/static', 'stream(GT)/static'])

    def f4(v: float) -> str:
        return f'{v:.4f}' if np.isfinite(v) else 'nan'
    table(header, [[r['surface'], f"{r['motion_deg']:g}", f"{r['amplitude']:g}",
                    'yes' if r['occluder'] else 'no', f"{r['camera_range_deg']:.0f}",
                    f4(r['static']), f4(r['flat'])]
                   + [f4(r[f'gt_{m}']) for m in gt_methods]
                   + ([f4(r['truecam_rigid']), f4(r['truecam_bmm'])] if a.true_cameras else [])
                   + [f4(r['stream_gt'])]
                   + ([f4(r['truedepth_stream'])] if a.true_depths else [])
                   + [f4(r[m]) for m in pipe_cols]
                   + [f"{r['frames_in']}/{r['frames_out']}", f"{r['ratio_pipeline']:.2f}",
                      f"{r['ratio_stream_gt']:.2f}"] for r in rows])

    def per_case(title: str, cell: Callable[[dict, str], str]) -> None:
        """One column per stream (``stream_gt`` and each mode) of a per-case quantity."""
        print()
        table(['surface', 'cam deg', 'amp', 'occl', f'{title}: stream(GT)'] + list(modes),
              [[r['surface'], f"{r['motion_deg']:g}", f"{r['amplitude']:g}",
                'yes' if r['occluder'] else 'no', cell(r, 'stream_gt')]
               + [cell(r, m) for m in modes] for r in rows])
    per_case('frames depth-reflected', lambda r, m: f"{r[f'{m}_inverted']}/{r['frames_in']}")
    per_case('surface points a frame', lambda r, m: f"{r[f'{m}_points']:.0f}")
    occ_rows = [[r['surface'], f"{r['motion_deg']:g}", f"{r['amplitude']:g}", m, f4(r[m]),
                 f4(r[f'{m}_occluded']), f4(r[f'{m}_visible']),
                 f"{r[f'{m}_occluded'] / r[f'{m}_visible']:.2f}"]
                for r in rows if r['occluder'] for m in modes]
    if occ_rows:
        print()
        table(['surface', 'cam deg', 'amp', 'mode', 'e3D', 'occluded', 'visible',
               'occluded/visible'], occ_rows)
    spread = [[r['surface'], f"{r['motion_deg']:g}", f"{r['amplitude']:g}",
               'yes' if r['occluder'] else 'no', m, f4(r[m]),
               f4(min(r[f'{m}_perturbed'])), f4(float(np.median(r[f'{m}_perturbed']))),
               f4(max(r[f'{m}_perturbed'])), f4(r['static'])]
              for r in rows for m in modes if f'{m}_perturbed' in r]
    if spread:
        print()
        table(['surface', 'cam deg', 'amp', 'occl', 'mode', 'e3D', f'perturbed x{a.perturb}: min',
               'median', 'max', 'static'], spread)
    later = [[r['surface'], f"{r['motion_deg']:g}", f"{r['amplitude']:g}",
              'yes' if r['occluder'] else 'no',
              f"{f4(r['stream_gt_first'])} / {f4(r['stream_gt_later'])}"]
             + [f"{f4(r[f'{m}_first'])} / {f4(r[f'{m}_later'])} (static "
                f"{f4(r[f'{m}_static_first'])} / {f4(r[f'{m}_static_later'])})" for m in modes]
             for r in rows if r['frames_in'] > rec.batch_frames]
    if later:
        print()
        table(['surface', 'cam deg', 'amp', 'occl',
               f'stream(GT): first {rec.batch_frames} frames / later']
              + [f'{m}: first / later (static on its points)' for m in modes], later)
    split = [[r['surface'], f"{r['motion_deg']:g}", f"{r['amplitude']:g}",
              'yes' if r['occluder'] else 'no', f4(r['static']), f4(r['stream_gt']),
              f4(r['split']['trk']), f4(r['split']['gt_positions']),
              f4(r['split']['gt_visibility']), f"{r['split']['median_px']:.2f}",
              f"{r['split']['p90_px']:.2f}", f"{r['split']['over_3px']:.3f}",
              f"{r['split']['visible_tracker']:.2f} / {r['split']['visible_truth']:.2f}"]
             for r in rows if 'split' in r]
    if split:
        print()
        table(['surface', 'cam deg', 'amp', 'occl', 'static', 'stream(GT)',
               'stream(tracker, first-reference tracks)', 'true positions, tracker visibility',
               'tracker positions, true visibility', 'visible error median px', 'p90 px',
               'share > 3 px', 'visible: tracker / truth'], split)
    full = 'dspr-full' in modes
    comp = [[r['surface'], f"{r['motion_deg']:g}", f"{r['amplitude']:g}", m,
             f"{r[f'{m}_compression']:.1f}", f4(r[m])]
            + ([f"{r[m] / r['dspr-full']:.2f}"] if full else [])
            for r in rows for m in modes if f'{m}_compression' in r]
    if comp:
        print()
        table(['surface', 'cam deg', 'amp', 'mode', 'compression (frames / stored states)',
               'e3D'] + (['/ dspr-full (no compression)'] if full else []), comp)
    ratios = np.array([r['ratio_pipeline'] for r in rows])
    if rows:
        print(f'\npipeline / static: median {np.nanmedian(ratios):.2f}, worst '
              f'{np.nanmax(ratios):.2f}; cases with frames out < in: '
              f"{sum(r['frames_out'] < r['frames_in'] for r in rows)} of {len(rows)}")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1, default=str))


if __name__ == '__main__':
    main()
