"""RGB-D scene-flow benchmark (issue 14): zero flow, DIS optical flow + depth back-projection,
per-segment projective ICP and MSF, in one run, on deforming surfaces seen by a moving camera,
with and without the occluder, at 320x240 and 640x480.

    .venv/bin/python bench/bench_sceneflow.py [--frames 8] [--surfaces flag,face] [--json out]
    .venv/bin/python bench/bench_sceneflow.py --mono [--surfaces flag,face] [--mono-size 256x192]

``--mono`` (monocular NRSfM-Flow, issue 14) instead renders a 30 deg camera sweep
(``nrsfm-ros synth --camera-motion 30``, 60 frames), runs ``process`` (tracker ->
reconstructor -> scene_flow, nrsfm_ros.pipeline.process_bag) and scores with
``evaluation.scene_flow_errors`` (what ``nrsfm-ros evaluate`` and the demo print: relative EPE in
the object frame, mean over frames 1..59): the published scene_flow/points (shrinkage: jitter);
zero flow; the reconstructor's clouds without the shrinkage (raw), through the old two-frame
Kabsch fit and with the *true* ego-motion
removed (what the reconstruction allows at best); the ground-truth shapes through the node's
estimator (its own floor), without the shrinkage and through the two-frame fit.

Flow is scored from the first frame to every later one (what ``nrsfm-ros scene-flow`` writes),
per surface pixel visible in the first frame, against ``io.synth_flow.dense_scene_flow``
(definition: core.sceneflow.definition).  EPE in mm (the same in the camera and the object
frame); relative EPE = mean error / mean true displacement in the object frame (camera
ego-motion removed with the true poses); 'zero' is zero object-frame flow (a static world).
Sensor noise ``--sensor``: none (perfect rendered depth, as the bags carry), rgbd (image
sigma 2, depth sigma 0.5e-3 z^2 m, ~8 mm at 4 m, seeded) and/or kinect (a structured-light
sensor: image sigma 3, depth sigma 1.425e-3 z^2 m, disparity quantised to 1/8 px with f b =
43.5 px m, ~6 mm steps at 1.5 m, no depth at grazing angles over 75 deg, in 2% of the pixels in
blobs and in half of a 2 px band around depth edges).  ``--background``: off (the surface alone
has depth) and/or on (a textured wall behind it, as every real RGB-D frame has); ``--distance``:
the camera's distance to the surface (m).  frames/s: estimation per frame after
the reference, from CPU time (process_time: all of the process's threads) and from wall time
(one process; the machine may be shared: the load average is printed).
"""
from __future__ import annotations

import itertools
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchlib import parser, table  # noqa: E402

from nrsfm_ros.core.sceneflow import (ICP_CONFIG, MSFConfig, camera_to_object,  # noqa: E402
                                      dis_depth_flow, epe, msf_sequence, relative_motion)
from nrsfm_ros.core.sceneflow.msf import back_project  # noqa: E402
from nrsfm_ros.io.synth import SynthConfig, generate  # noqa: E402
from nrsfm_ros.io.synth_flow import dense_scene_flow  # noqa: E402


def score(flow: np.ndarray, seq, gt_obj: np.ndarray, valid: np.ndarray, X0: np.ndarray
          ) -> tuple[float, float]:
    e, r = [], []
    for f in range(flow.shape[0]):
        T = relative_motion(seq.T_camera_world, 0, f + 1)
        a, b = epe(camera_to_object(flow[f], X0, T), gt_obj[f], valid)
        e.append(a)
        r.append(b)
    return float(np.mean(e)), float(np.mean(r))


def kinect_depth(depth: np.ndarray, K: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Rendered depth (F, H, W) m -> what a structured-light sensor gives (module docstring)."""
    import cv2
    fb = 580.0 * 0.075
    out = []
    for z in np.asarray(depth, np.float64):
        ok = np.isfinite(z)
        zf = np.where(ok, z, 0)
        slope = np.hypot(cv2.Sobel(zf, cv2.CV_64F, 1, 0, ksize=3) / 8 * K[0, 0],
                         cv2.Sobel(zf, cv2.CV_64F, 0, 1, ksize=3) / 8 * K[1, 1]) / np.where(
                             ok, z, 1)
        bad = slope > np.tan(np.radians(75))
        bad |= (cv2.dilate((~ok).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0) & (
            rng.random(z.shape) < 0.5)
        blobs = cv2.GaussianBlur(rng.random(z.shape), (0, 0), 3)
        bad |= blobs > np.quantile(blobs, 0.98)
        zn = z + 1.425e-3 * z ** 2 * rng.standard_normal(z.shape)
        zq = fb / (np.round(fb / np.where(ok, zn, 1.0) * 8) / 8)
        out.append(np.where(ok & ~bad, zq, np.nan).astype(np.float32))
    return np.stack(out)


def run_case(surface: str, size: tuple[int, int], occluder: bool, sensor: str, frames: int,
             background: bool = False, distance: float = 4.0) -> list[dict]:
    seq = generate(SynthConfig(surface=surface, width=size[0], height=size[1], frames=frames,
                               stride=1, occluder=occluder, background=background,
                               distance=distance,
                               noise={'rgbd': 2.0, 'kinect': 3.0}.get(sensor, 0.0)))
    depth = seq.depth
    rng = np.random.default_rng(1)
    if sensor == 'rgbd':
        depth = depth + (5e-4 * depth ** 2 * rng.standard_normal(depth.shape)).astype(np.float32)
    elif sensor == 'kinect':
        depth = kinect_depth(depth, seq.K, rng)
    gt_obj, valid = dense_scene_flow(seq, 'object')
    X0 = back_project(seq.depth[0], seq.K)
    case = {'surface': surface, 'size': f'{size[0]}x{size[1]}', 'occluder': occluder,
            'sensor': sensor, 'background': background, 'distance': distance}
    rows = [dict(case, method='zero', **dict(zip(('epe_m', 'rel_epe'), score(
        np.full(gt_obj.shape, np.nan, np.float32), seq, gt_obj, valid, X0))), fps=None,
        fps_cpu=None)]
    # zero object flow: NaN scores as zero displacement in the scored (object) frame
    for name, fn in (('DIS+depth', lambda: dis_depth_flow(seq.images, depth, seq.K)),
                     ('segment ICP', lambda: msf_sequence(seq.images, depth, seq.K,
                                                          ICP_CONFIG)),
                     ('MSF', lambda: msf_sequence(seq.images, depth, seq.K, MSFConfig()))):
        t0 = time.perf_counter()
        flow, ok, st = fn()
        del t0
        e, r = score(flow, seq, gt_obj, valid, X0)
        rows.append(dict(case, method=name, epe_m=e, rel_epe=r,
                         fps=1.0 / max(st['seconds_per_frame'], 1e-9),
                         fps_cpu=1.0 / max(st['cpu_seconds_per_frame'], 1e-9)))
    dis = rows[1]['epe_m']
    for row in rows:
        row['vs_dis'] = row['epe_m'] / dis
    return rows


def _node_flows(clouds: dict, stamps: np.ndarray, params=None) -> dict:
    """Replay {frame: (X, ids)} through SceneFlowProcessor: {frame: (velocity, ids)}."""
    from nrsfm_ros.io import pointcloud2 as pc2
    from nrsfm_ros.io.msgtypes import RosbagsFactory
    from nrsfm_ros.params import SceneFlowParams
    from nrsfm_ros.processing import SceneFlowProcessor
    from nrsfm_ros.io.msgtypes import stamp_ns
    fac = RosbagsFactory()
    proc = SceneFlowProcessor(fac, params or SceneFlowParams())
    frame_of = {int(s): f for f, s in enumerate(stamps)}
    outs = []
    for f in sorted(clouds):
        X, ids = clouds[f]
        X = np.asarray(X, np.float32)
        msg = pc2.to_msg({'x': X[:, 0], 'y': X[:, 1], 'z': X[:, 2],
                          'track_id': np.asarray(ids, np.uint32)}, fac, int(stamps[f]), 'cam')
        outs += proc.on_points(msg)
    out = {}
    for topic, _, m in outs + proc.flush():       # look-ahead: published later, and at the end
        if topic.endswith('scene_flow/points'):
            out[frame_of[stamp_ns(m.header)]] = (
                pc2.read_fields(m, ('vx', 'vy', 'vz'), np.float64),
                pc2.read_fields(m, ('track_id',), np.uint32)[:, 0])
    return out


def _true_ego(clouds: dict, seq) -> dict:
    """Flow of consecutive clouds with the true camera motion removed."""
    fs = sorted(clouds)
    out = {}
    for a, b in zip(fs[:-1], fs[1:]):
        (Xa, ia), (Xb, ib) = clouds[a], clouds[b]
        common, pa, pb = np.intersect1d(ia, ib, assume_unique=True, return_indices=True)
        T = relative_motion(seq.T_camera_world, a, b)
        v = camera_to_object(Xb[pb] - Xa[pa], Xa[pa], T) * seq.config.fps / (b - a)
        out[b] = (v, common)
    return out


def run_mono(surface: str, size: tuple[int, int], frames: int = 60) -> list[dict]:
    import tempfile
    from nrsfm_ros.evaluation import BagOutputs, read_outputs, scene_flow_errors
    from nrsfm_ros.io.sequence_bag import write_sequence_bag
    from nrsfm_ros.params import SceneFlowParams
    from nrsfm_ros.pipeline import process_bag
    seq = generate(SynthConfig(surface=surface, width=size[0], height=size[1], frames=frames,
                               camera_motion_deg=30.0))
    with tempfile.TemporaryDirectory() as tmp:
        write_sequence_bag(seq, Path(tmp) / 'in')
        t0 = time.perf_counter()
        process_bag(Path(tmp) / 'in', Path(tmp) / 'out', progress=False,
                    stages=('tracker', 'reconstructor', 'scene_flow'))
        seconds = time.perf_counter() - t0
        out = read_outputs(Path(tmp) / 'out', seq)
    two = SceneFlowParams(window=2, iterations=0, warm_iterations=0, shrinkage='none')
    raw = SceneFlowParams(shrinkage='none')
    gt = {f: (seq.S[f], seq.track_ids) for f in range(seq.S.shape[0])}
    st = seq.stamps_ns
    cases = [('pipeline scene_flow/points', out.flows),
             ('zero flow', {f: (0 * v, i) for f, (v, i) in out.flows.items()}),
             ('recon clouds, no shrinkage (raw)', _node_flows(out.clouds, st, raw)),
             ('recon clouds, two-frame Kabsch (old)', _node_flows(out.clouds, st, two)),
             ('recon clouds, true ego-motion', _true_ego(out.clouds, seq)),
             ('GT shapes, node estimator (floor)', _node_flows(gt, st)),
             ('GT shapes, no shrinkage (raw)', _node_flows(gt, st, raw)),
             ('GT shapes, two-frame Kabsch (old)', _node_flows(gt, st, two))]
    rows = []
    for name, flows in cases:
        r = scene_flow_errors(BagOutputs(flows=flows), seq)
        rows.append({'surface': surface, 'size': f'{size[0]}x{size[1]}', 'method': name,
                     'rel_epe': r.get('scene_flow_relative_epe', float('nan')),
                     'frames': r.get('scene_flow_frames_scored', 0),
                     'process_s': seconds if name.startswith('pipeline') else None})
    return rows


def main() -> int:
    p = parser(__doc__)
    p.add_argument('--mono', action='store_true', help='the monocular NRSfM-Flow section only')
    p.add_argument('--mono-size', default='256x192')
    p.add_argument('--frames', type=int, default=8)
    p.add_argument('--surfaces', default='flag,face')
    p.add_argument('--sizes', default='320x240,640x480')
    p.add_argument('--sensor', default='none,rgbd', help='none, rgbd, kinect (comma list)')
    p.add_argument('--background', default='off', help='off, on or off,on: a wall behind')
    p.add_argument('--distance', type=float, default=4.0, help='camera to surface, m')
    args = p.parse_args()
    rows = []
    if args.mono:
        wh = tuple(int(v) for v in args.mono_size.split('x'))
        for surface in args.surfaces.split(','):
            rows += run_mono(surface, wh)
            print(f'# done {surface}', file=sys.stderr, flush=True)
        table(['surface', 'size', 'method', 'rel EPE (object frame)', 'frames scored'],
              [(r['surface'], r['size'], r['method'], f"{r['rel_epe']:.3f}", r['frames'])
               for r in rows])
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=1))
        return 0
    for size in args.sizes.split(','):
        wh = tuple(int(v) for v in size.split('x'))
        for surface in args.surfaces.split(','):
            for occ, sensor, bg in itertools.product(
                    (False, True), args.sensor.split(','), args.background.split(',')):
                if bg not in ('off', 'on'):
                    p.error(f'--background: {bg!r} is neither off nor on')
                rows += run_case(surface, wh, occ, sensor, args.frames, bg == 'on',
                                 args.distance)
                print(f'# done {surface} {size} occluder={occ} sensor={sensor} wall={bg}',
                      file=sys.stderr, flush=True)
    table(['surface', 'size', 'occluder', 'wall', 'sensor', 'method', 'EPE mm', 'rel EPE',
           'EPE / DIS', 'frames/s (CPU)', 'frames/s (wall)'],
          [(r['surface'], r['size'], 'yes' if r['occluder'] else 'no',
            'yes' if r['background'] else 'no', r['sensor'], r['method'],
            f"{1000 * r['epe_m']:.2f}", f"{r['rel_epe']:.3f}", f"{r['vs_dis']:.2f}",
            '-' if r['fps'] is None else f"{r['fps_cpu']:.1f}",
            '-' if r['fps'] is None else f"{r['fps']:.1f}") for r in rows])
    print(f'load average (1, 5, 15 min) at the end: {os.getloadavg()}')
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
