"""End-to-end evaluation against a synthetic sequence's ground truth: what a subscriber receives.

Clouds are matched to ground truth by header stamp (frame) and ``track_id`` (point); a frame
without a cloud, or with too few matched points, is listed as unscored, never scored.  Tracks
of the tracker's later references (ids ``epoch * H * W + y * W + x``, epoch >= 1) are matched
too where the sequence was rendered in this process: their truth is the surface point their
pixel saw in the frame where their epoch's ids first appear (``truth_for_clouds``).  Each
score comes with the trivial baselines on the same frames and points (``core.metrics``), and the
rigid factorisation on the ground-truth tracks.
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .core.metrics import StreamScore, relative_epe, rotation_error_deg, score_stream
from .core.nrsfm import reconstruct
from .io import pointcloud2 as pc2
from .io.bag import deserialize, read_messages
from .io.msgtypes import stamp_ns
from .io.synth import SynthConfig, SynthSequence, pixel_truth, scene_flow_ground_truth
from .params import ReconstructorParams
from .processing import TOPICS, make_stream, transform_matrix


def read_clouds(bag: str | Path, stamps_ns: np.ndarray, topic: str = TOPICS['points']
                ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """``{frame: (X (n, 3), track_id (n,))}`` of the clouds on ``topic`` whose stamps are
    frames of the sequence (``stamps_ns``)."""
    return {f: _cloud(msg) for f, msg in _frame_messages(bag, stamps_ns, topic)}


def _frame_messages(bag: str | Path, stamps_ns: np.ndarray, topic: str
                    ) -> Iterator[tuple[int, Any]]:
    """(frame, message) of the messages on ``topic`` whose stamps are frames of the sequence
    (``stamps_ns``)."""
    index = {int(s): i for i, s in enumerate(stamps_ns)}
    for m in read_messages(bag):
        if m.topic.lstrip('/') != topic:
            continue
        msg = deserialize(m.raw, m.msgtype)
        f = index.get(stamp_ns(msg.header))
        if f is not None:
            yield f, msg


def read_tracks(bag: str | Path, stamps_ns: np.ndarray, topic: str = TOPICS['tracks']
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tracks published on ``topic`` for the frames ``stamps_ns`` as one matrix over the
    union of their ids: W (2F, P) image positions (NaN where a track is absent from a frame: a
    later reference's track before that reference, one ended by a re-selection), V (F, P)
    visibility (0 where a track is absent or its position is not finite), ids (P,) sorted.  A
    frame without a tracks message has every track absent."""
    frames = {f: (pc2.read_fields(msg, ('track_id',), np.uint32)[:, 0].astype(np.int64),
                  pc2.read_fields(msg, ('u', 'v', 'visibility'), np.float64))
              for f, msg in _frame_messages(bag, stamps_ns, topic)}
    F = len(stamps_ns)
    ids = np.unique(np.concatenate([i for i, _ in frames.values()] or
                                   [np.empty(0, np.int64)]))
    W, V = np.full((2 * F, ids.size), np.nan), np.zeros((F, ids.size))
    for f, (i, cols) in frames.items():
        c = np.searchsorted(ids, i)
        ok = np.isfinite(cols[:, :2]).all(1)
        W[2 * f, c], W[2 * f + 1, c] = np.nan_to_num(cols[:, 0]), np.nan_to_num(cols[:, 1])
        V[f, c] = np.where(ok, np.clip(np.nan_to_num(cols[:, 2]), 0.0, 1.0), 0.0)
    return W, V, ids


def tracker_split(W: np.ndarray, V: np.ndarray, ids: np.ndarray, seq: SynthSequence,
                  **params: Any) -> dict[str, float]:
    """Where the tracker costs, on its tracks that ground truth knows (the same ids): the
    stream (reconstructor defaults, ``params`` overriding, the sequence's intrinsics) on
    the tracker's positions and visibility (``trk``), on the true positions with the tracker's
    visibility (``gt_positions``: the loss left is its missing-data pattern's) and on the
    tracker's positions with the true visibility (``gt_visibility``: the loss left is its
    position errors'); the visible observations' error in px (``median_px``, ``p90_px``,
    ``over_3px``: share over 3 px) and the visible shares of the tracker and the truth."""
    col = {int(i): k for k, i in enumerate(seq.track_ids)}
    keep = np.array([int(i) in col for i in ids], bool)
    if keep.sum() < MIN_POINTS:
        raise ValueError(f'tracker_split: only {int(keep.sum())} tracks match ground truth')
    gcols = np.array([col[int(i)] for i in ids[keep]])
    Wt, Vt = W[:, keep], V[:, keep]
    Wg, Vg = seq.W[:, gcols], seq.V[:, gcols]
    kid = ids[keep].astype(np.uint32)
    err = np.hypot(Wt[0::2] - Wg[0::2], Wt[1::2] - Wg[1::2])[Vt >= 0.5]

    def e3d(W_: np.ndarray, V_: np.ndarray) -> float:
        return score(stream_on_tracks(W_, V_, kid, seq.K, **params), seq).summary()['e3d']
    return {'trk': e3d(Wt, Vt), 'gt_positions': e3d(Wg, Vt), 'gt_visibility': e3d(Wt, Vg),
            'median_px': float(np.median(err)) if err.size else float('nan'),
            'p90_px': float(np.percentile(err, 90)) if err.size else float('nan'),
            'over_3px': float((err > 3).mean()) if err.size else float('nan'),
            'visible_tracker': float((Vt >= 0.5).mean()),
            'visible_truth': float((Vg >= 0.5).mean())}


def _cloud(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    """(X (n, 3) with NaNs kept, track_id (n,)) of a published cloud."""
    return (pc2.read_xyz(msg, skip_nans=False),
            pc2.read_fields(msg, ('track_id',), np.uint32)[:, 0])


def shapes_as_clouds(S: np.ndarray, ids: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """A full reconstruction S (F, P, 3) of the tracks ``ids`` as per-frame clouds."""
    return {f: (S[f], ids) for f in range(S.shape[0])}


def stream_on_tracks(W: np.ndarray, V: np.ndarray, ids: np.ndarray,
                     K: np.ndarray | None = None, **params: Any
                     ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """The streaming reconstructor (``StreamNRSfM``, reconstructor defaults unless given) fed
    the tracks W (2F, P), V (F, P) frame by frame, with the camera intrinsics ``K`` as from
    CameraInfo (None: none arrived): what it would publish, in image units.  A track whose
    position in a frame is NaN (absent there, as ``read_tracks`` gives it) is left out of
    that frame's message, as the tracker leaves it out: pushed as present-but-hidden, a later
    reference's track would be published (filled) in the frames before its reference, and
    ``truth_for_clouds`` would then take its truth from the wrong frame's pixel."""
    stream = make_stream(ReconstructorParams(), **params)
    if K is not None:
        stream.set_intrinsics(float(K[0, 0]), np.asarray(K)[:2, 2])
    out = {}
    F = V.shape[0]
    for f in range(F):
        uv = W[2 * f:2 * f + 2].T
        here = np.isfinite(uv).all(axis=1)
        for sh in stream.push(ids[here], uv[here], V[f, here]):
            out[sh.index] = (sh.X, sh.ids)
    for sh in stream.flush():
        out[sh.index] = (sh.X, sh.ids)
    return out


MIN_POINTS = 10     # a frame with fewer points matched to ground truth is unscored


def truth_for_clouds(clouds: dict[int, tuple[np.ndarray, np.ndarray]], seq: SynthSequence
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The ground truth's ids (P',) and shapes (F, P', 3): the sequence's own tracks (its
    first frame's pixels) and, where the sequence has its per-pixel surface coordinates, the
    tracks of the tracker's later references found in ``clouds``: an id ``epoch * H * W + y *
    W + x`` (epoch >= 1) is the pixel (x, y) of the frame where its epoch's ids first appear
    (a re-selected reference), and its truth the surface point that pixel saw then
    (``synth.pixel_truth``; none where it saw the occluder or nothing)."""
    ids, S = seq.track_ids.astype(np.int64), seq.S
    if seq.surface_st is None or not clouds:
        return ids, S
    F, H, Wd = seq.surface_st.shape[:3]
    first: dict[int, int] = {}          # epoch -> the first frame whose cloud holds its ids
    seen = []
    for f in sorted(k for k in clouds if 0 <= k < F):
        c = np.unique(np.asarray(clouds[f][1]).astype(np.int64))
        seen.append(c)
        for e in np.unique(c // (H * Wd)):
            first.setdefault(int(e), f)
    new = np.unique(np.concatenate(seen)) if seen else np.zeros(0, np.int64)
    new = new[new >= H * Wd]
    if not new.size:
        return ids, S
    extra_ids, extra_S = [ids], [S]
    for e in np.unique(new // (H * Wd)):
        group = new[new // (H * Wd) == e]
        pix = group % (H * Wd)
        X = pixel_truth(seq, first[int(e)], np.stack([pix % Wd, pix // Wd], axis=1))
        ok = np.isfinite(X[0]).all(axis=1)
        extra_ids.append(group[ok])
        extra_S.append(X[:, ok])
    return np.concatenate(extra_ids), np.concatenate(extra_S, axis=1)


def score(clouds: dict[int, tuple[np.ndarray, np.ndarray]], seq: SynthSequence) -> StreamScore:
    ids, S = truth_for_clouds(clouds, seq)
    return score_stream(clouds, ids, S, min_points=MIN_POINTS)


def depth_reflected_frames(clouds: dict[int, tuple[np.ndarray, np.ndarray]],
                           seq: SynthSequence) -> int:
    """Frames whose published depths run against the truth's (negative correlation of the
    centred depths on the points matched by ``track_id``, at least ``MIN_POINTS``): a depth
    reflection, which metric B (Procrustes with reflections, the NRSfM convention) forgives but
    a subscriber of the cloud or of ``nrsfm/depth`` does not -- a concave cap for a convex one,
    a flag turned away from the camera instead of towards it."""
    gt_ids, S = truth_for_clouds(clouds, seq)
    col = {int(i): k for k, i in enumerate(gt_ids)}
    bad = 0
    for f, (X, ids) in clouds.items():
        keep = [k for k, i in enumerate(ids) if int(i) in col] if 0 <= f < S.shape[0] \
            else []
        if len(keep) < MIN_POINTS:
            continue
        z = X[keep, 2] - X[keep, 2].mean()
        g = S[f][[col[int(ids[k])] for k in keep], 2]
        bad += float(z @ (g - g.mean())) < 0
    return bad


def rigid_on_ground_truth(seq: SynthSequence) -> float:
    """e3D of the rigid factorisation of the ground-truth tracks (a baseline)."""
    res = reconstruct(seq.W, np.maximum(seq.V, 1e-3), method='rigid')
    return score(shapes_as_clouds(res.S, seq.track_ids), seq).summary()['e3d']


# ------------------------------------------------------------------ ground truth

GT_REQUIRED = ('S', 'track_ids', 'stamps_ns')


class GroundTruthError(ValueError):
    """A ground-truth file that is not what ``nrsfm-ros synth`` writes (one ``error:`` line)."""


def load_ground_truth(path: str | Path) -> SynthSequence:
    """The ground truth ``nrsfm-ros synth --out BAG`` writes beside its bag (``BAG.npz``,
    ``SynthSequence.npz_dict``): needs ``S`` (F, P, 3), ``track_ids`` (P,) and ``stamps_ns``
    (F,); ``T_camera_world`` (registration rotation) and ``S_world`` with ``fps`` (scene flow)
    are used where present, every other array is optional.  Missing parts are empty arrays."""
    import zipfile
    import zlib
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f'ground truth {path} does not exist')
    if path.is_dir():
        hint = path.with_suffix('.npz')
        raise GroundTruthError(f'ground truth {path}: a folder, not the .npz that synth writes '
                               f'beside its bag' + (f' (try {hint})' if hint.exists() else ''))
    if not zipfile.is_zipfile(path):
        raise GroundTruthError(f'ground truth {path}: not an .npz archive (expected the .npz '
                               'that synth writes beside its bag)')
    try:
        d = np.load(path, allow_pickle=False)
        missing = [k for k in GT_REQUIRED if k not in d.files]
        if missing:
            raise GroundTruthError(f'ground truth {path}: not a synth ground truth (no '
                                   f'{", ".join(missing)}; it has: {", ".join(d.files)})')
        a = {k: d[k] for k in d.files if k not in ('images', 'depth')}
        shape = d['images'].shape if 'images' in d.files else None
        a['images'] = d['images'] if shape is not None else np.zeros((0, 0, 0, 3), np.uint8)
        a['depth'] = d['depth'] if 'depth' in d.files else np.zeros((0, 0, 0), np.float32)
    except GroundTruthError:
        raise
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, KeyError) as err:
        raise GroundTruthError(f'ground truth {path}: not a readable .npz '
                               f'({" ".join(str(err).split()) or type(err).__name__})') from err
    S, ids, stamps = a['S'], a['track_ids'], a['stamps_ns']
    if S.ndim != 3 or S.shape[2] != 3 or ids.shape != (S.shape[1],) \
            or stamps.shape != (S.shape[0],):
        raise GroundTruthError(f'ground truth {path}: S {S.shape}, track_ids {ids.shape}, '
                               f'stamps_ns {stamps.shape}: expected (F, P, 3), (P,), (F,)')
    F, P = S.shape[:2]
    T = a.get('T_camera_world', np.zeros((0, 4, 4)))
    if T.shape != (F, 4, 4):
        T = np.zeros((0, 4, 4))
    S_world = a.get('S_world', np.zeros((0, P, 3)))
    if S_world.shape != S.shape or 'fps' not in a:
        S_world = np.zeros((0, P, 3))
    cfg = SynthConfig(surface=str(a.get('surface', 'flag')),
                      width=shape[2] if shape else 0, height=shape[1] if shape else 0,
                      frames=F, fps=float(a.get('fps', 10.0)))
    return SynthSequence(config=cfg, images=a['images'], depth=a['depth'],
                         K=a.get('K', np.eye(3)), T_camera_world=T,
                         stamps_ns=stamps.astype(np.int64), track_ids=ids,
                         W=a.get('W', np.zeros((0, P))), V=a.get('V', np.zeros((0, P))),
                         S=S, S_world=S_world)


# ------------------------------------------------------------------ an output bag

@dataclass
class BagOutputs:
    """What an output bag holds, matched to the ground-truth frames by header stamp.

    ``clouds`` {frame: (X, track_id)} of nrsfm/points (``colours`` {frame: rgb} if asked for),
    ``flows`` {frame: (v, track_id)} of scene_flow/points, ``transforms`` {frame: 4x4} of
    registration/transform, ``residuals`` {frame: RMS distance (m) of registration/aligned to
    the frame-0 ground truth}; ``unmatched`` {topic: stamps that are no ground-truth frame}
    (never scored); ``counts`` messages per topic; ``latency`` ms per node from
    /diagnostics; ``damage`` what a damaged bag lost."""

    counts: dict[str, int] = field(default_factory=dict)
    clouds: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    colours: dict[int, np.ndarray] = field(default_factory=dict)
    flows: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    transforms: dict[int, np.ndarray] = field(default_factory=dict)
    residuals: dict[int, float] = field(default_factory=dict)
    latency: dict[str, float] = field(default_factory=dict)
    unmatched: dict[str, list[int]] = field(default_factory=dict)
    damage: list[str] = field(default_factory=list)


def read_outputs(bag: str | Path, seq: SynthSequence, colours: bool = False) -> BagOutputs:
    """Read every scored output of ``bag`` once (see ``BagOutputs``)."""
    from scipy.spatial import cKDTree
    stamps = {int(s): i for i, s in enumerate(seq.stamps_ns)}
    out = BagOutputs()
    ref_tree = cKDTree(seq.S[0])
    scored = (TOPICS['points'], TOPICS['scene_flow'], TOPICS['transform'], TOPICS['aligned'])
    for m in read_messages(bag, damage=out.damage):
        out.counts[m.topic] = out.counts.get(m.topic, 0) + 1
        if m.topic in scored:
            msg = deserialize(m.raw, m.msgtype)
            st = stamp_ns(msg.header)
            f = stamps.get(st)
            if f is None:
                out.unmatched.setdefault(m.topic, []).append(st)
                continue
            if m.topic == TOPICS['points']:
                out.clouds[f] = _cloud(msg)
                if colours:
                    out.colours[f] = pc2.unpack_rgb(pc2.read_points(msg).reshape(-1)['rgb'])
            elif m.topic == TOPICS['scene_flow']:
                out.flows[f] = (pc2.read_fields(msg, ('vx', 'vy', 'vz'), np.float64),
                                pc2.read_fields(msg, ('track_id',), np.uint32)[:, 0])
            elif m.topic == TOPICS['aligned']:
                out.residuals[f] = float(np.sqrt(np.mean(
                    ref_tree.query(pc2.read_xyz(msg))[0] ** 2)))
            else:
                out.transforms[f] = transform_matrix(msg)
        elif m.topic == TOPICS['diagnostics'].lstrip('/'):
            msg = deserialize(m.raw, m.msgtype)
            for status in msg.status:
                vals = {kv.key: kv.value for kv in status.values}
                if 'latency_ms' in vals and float(vals.get('processed', 0)) > 0:
                    out.latency[status.hardware_id] = float(vals['latency_ms'])
    return out


def registration_errors(out: BagOutputs, seq: SynthSequence) -> dict[str, Any]:
    """Median rotation error (deg) of registration/transform against the true camera rotation
    from frame 0, and the mean RMSE (m) of registration/aligned to the frame-0 ground truth
    (keys as in the demo summary; absent where the bag or the ground truth has no data)."""
    r: dict[str, Any] = {}
    if out.transforms and seq.T_camera_world.shape[0] == seq.S.shape[0]:
        R0 = seq.T_camera_world[0, :3, :3]
        errs = [rotation_error_deg(T[:3, :3], R0 @ seq.T_camera_world[f, :3, :3].T)
                for f, T in out.transforms.items()]
        r['registration_rotation_error_deg_median'] = float(np.median(errs))
        r['registration_rotation_frames'] = len(errs)
    if out.residuals:
        r['registration_rmse_m'] = float(np.mean(list(out.residuals.values())))
        r['registration_rmse_frames'] = len(out.residuals)
    return r


def scene_flow_errors(out: BagOutputs, seq: SynthSequence, min_points: int = MIN_POINTS
                      ) -> dict[str, Any]:
    """Relative EPE (``core.metrics.relative_epe``) of scene_flow/points against
    ``io.synth.scene_flow_ground_truth`` (object frame of ``core.sceneflow.definition``, axes of
    the earlier camera, m/s), points matched by track id, mean over frames 1..F-1
    (frame 0 has no flow); a frame with fewer than ``min_points`` matches is unscored.  Empty
    where the bag has no scene flow or the ground truth no world-frame shapes."""
    if not out.flows or seq.S_world.shape != seq.S.shape:
        return {}
    id_index = {int(t): i for i, t in enumerate(seq.track_ids)}
    per_frame: dict[int, float] = {}
    unscored = []
    for f, (v, ids) in sorted(out.flows.items()):
        if f == 0:
            continue
        cols = np.array([id_index.get(int(i), -1) for i in ids], np.int64)
        keep = (cols >= 0) & np.isfinite(v).all(axis=1)
        if keep.sum() < min_points:
            unscored.append(f)
            continue
        gt = scene_flow_ground_truth(seq, f)[cols[keep]]
        per_frame[f] = relative_epe(v[keep], gt)
    if not per_frame:
        return {'scene_flow_unscored': unscored}
    return {'scene_flow_relative_epe': float(np.mean(list(per_frame.values()))),
            'scene_flow_frames_scored': len(per_frame), 'scene_flow_unscored': unscored,
            'per_frame_scene_flow_relative_epe': per_frame}


def evaluate_outputs(out: BagOutputs, seq: SynthSequence) -> dict[str, Any]:
    """The numbers of an output bag against ground truth (what ``nrsfm-ros evaluate`` prints
    and the demo summary holds): e3D of nrsfm/points (``score``, metric B) with its static and
    flat baselines on the same frames and points, the frames published depth-reflected
    (``depth_reflected_frames``), ``registration_errors`` and
    ``scene_flow_errors``.  Keys starting with ``per_frame`` hold per-frame values."""
    F = int(seq.S.shape[0])
    r: dict[str, Any] = {'frames_in': F, 'outputs': dict(out.counts)}
    if out.clouds:
        sc = score(out.clouds, seq)
        sm = sc.summary()
        r['e3d_B_frame_scaled'] = sm['e3d']
        r['e3d_static_oracle'] = sm['static']
        r['e3d_flat_plane'] = sm['flat']
        r['ratio_static'] = sm['e3d'] / max(sm['static'], 1e-300)
        r['ratio_flat'] = sm['e3d'] / max(sm['flat'], 1e-300)
        r['frames_scored'] = sm['frames_scored']
        r['frames_unscored'] = sm['unscored']
        r['unscored_reasons'] = {
            f: ('no cloud' if f not in out.clouds else
                f'{int(sc.matched[f])} point(s) matched to ground truth (< {MIN_POINTS})')
            for f in sm['unscored']}
        r['frames_depth_reflected'] = depth_reflected_frames(out.clouds, seq)
        r['points_per_frame'] = int(round(np.mean([c[1].size for c in out.clouds.values()])))
        r['points_matched_per_frame'] = sm['points_matched_mean']
        r['per_frame_e3d'] = {f: (float(sc.e3d[f]), float(sc.static[f]), float(sc.flat[f]),
                                  int(sc.matched[f])) for f in range(F) if np.isfinite(sc.e3d[f])}
    r.update(registration_errors(out, seq))
    r.update(scene_flow_errors(out, seq))
    if out.unmatched:
        r['unmatched_stamps'] = {t: list(s) for t, s in out.unmatched.items()}
    return r


def plot_errors(r: dict[str, Any], seq: SynthSequence, path: str | Path, title: str = '') -> None:
    """PNG of e3D per frame against the static and flat baselines over time (seconds from the
    first ground-truth frame); unscored frames are gaps, marked on the time axis."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    t = (np.asarray(seq.stamps_ns, np.int64) - int(seq.stamps_ns[0])) / 1e9
    curves = np.full((t.size, 3), np.nan)
    for f, vals in r.get('per_frame_e3d', {}).items():
        curves[f] = vals[:3]
    fig, ax = plt.subplots(figsize=(8, 4), dpi=100)
    for k, (label, style) in enumerate((('e3D nrsfm/points', 'C0-o'),
                                        ('static oracle', 'C1--'), ('flat plane', 'C2:'))):
        ax.plot(t, curves[:, k], style, label=label, markersize=3)
    bad = r.get('frames_unscored', [])
    if bad:
        ax.plot(t[bad], np.zeros(len(bad)), 'rx', label=f'unscored ({len(bad)})', clip_on=False)
    ax.set_xlabel('time (s)')
    ax.set_ylabel('e3D (metric B, per frame)')
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(loc='best', fontsize=8)
    ax.set_title(title or 'nrsfm/points against ground truth', fontsize=9)
    fig.tight_layout()
    fig.savefig(path, format='png')
    plt.close(fig)
