"""nrsfm-ros: the command line (argparse).  Every verb has --help with an example; bad input
prints one ``error:`` line and exits non-zero."""
from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

EXAMPLES = {
    'demo': 'nrsfm-ros demo --out out/demo',
    'synth': 'nrsfm-ros synth --surface face --size 320x240 --frames 80 --out bags/face',
    'record': 'nrsfm-ros record nrsfm/points scene_flow/points --out bags/rec --duration 10',
    'replay': 'nrsfm-ros replay bags/face --rate 0.5 --loop --clock',
    'process': 'nrsfm-ros process bags/face --out bags/face_out --report report.json; '
               'nrsfm-ros process bags/a bags/b bags/c --out out/batch --jobs 2',
    'topic': 'nrsfm-ros topic list; nrsfm-ros topic echo nrsfm/points -n 1; '
             'nrsfm-ros topic hz camera/image_raw',
    'export': 'nrsfm-ros export bags/face_out --out out/face --every 10',
    'evaluate': 'nrsfm-ros evaluate bags/face_out --ground-truth bags/face.npz --plot error.png '
                '--json eval.json --render out/face   (bags/face.npz: what synth wrote beside '
                'bags/face)',
    'track': 'nrsfm-ros track frames/ --out tracks.npz   (a folder of images or a video file)',
    'reconstruct': 'nrsfm-ros reconstruct tracks.npz --method bmm --out shapes.npz',
    'register': 'nrsfm-ros register source.ply target.ply --method cpd-rigid --w 0.3 --out r.npz',
    'scene-flow': 'nrsfm-ros scene-flow rgbd/ --out flow.npz   (rgbd/color/*.png, '
                  'rgbd/depth/*.png 16-bit mm, rgbd/intrinsics.txt)',
    'train-hdmnet': 'nrsfm-ros train-hdmnet --out out/hdmnet --seed 0 --states 4000 --epochs 20 '
                    '  (needs pip install .[learning])',
    'reconstruct-image': 'nrsfm-ros reconstruct-image frame.png --out shape.npz --fx 768',
    'view': 'nrsfm-ros view bags/face_out --rate 0.5 --loop   (then open ws://127.0.0.1:8765 in '
            'Foxglove with config/foxglove_layout.json); nrsfm-ros view   (the live topics)',
}


class CliError(Exception):
    pass


def _defaults(fn: Callable[..., Any]) -> dict[str, Any]:
    """The keyword defaults of a core function (what a flag left unset gets)."""
    import inspect
    return {k: p.default for k, p in inspect.signature(fn).parameters.items()
            if p.default is not inspect.Parameter.empty}


def _parser(verb: str | None = None) -> argparse.ArgumentParser:
    """The whole command line; with ``verb``, only that verb's flags are built (the others are
    listed with their help but take no flags: their defaults import the core, about 1.4 s of a
    cold start that ``topic list`` or ``replay`` never needed)."""
    p = argparse.ArgumentParser(prog='nrsfm-ros', description=__doc__)
    sub = p.add_subparsers(dest='verb', required=True)

    def wanted(name: str) -> bool:
        return verb is None or verb == name

    def add(name: str, help_: str) -> argparse.ArgumentParser:
        return sub.add_parser(name, help=help_, description=help_,
                              epilog=f'example: {EXAMPLES[name]}',
                              formatter_class=argparse.RawDescriptionHelpFormatter)

    d = add('demo', 'the main job: live graph on the sample bag, summary, PLY files, 3-D renders '
            'beside the ground truth with an error heat map, a GIF of the stream')
    d.add_argument('--out', default='out/demo', help='output folder (default out/demo)')
    d.add_argument('--bags', default='bags', help='where the sample bag lives (default bags)')
    d.add_argument('--rate', type=float, default=1.0, help='replay rate (default 1.0)')
    d.add_argument('--timeout', type=float, default=60.0,
                   help='seconds to wait for the last outputs after replay (default 60)')

    from .io.synth import SURFACES, SynthConfig
    sc = SynthConfig()              # the flags' defaults are the synthetic sequence's own
    s = add('synth', 'write a synthetic deforming sequence (MCAP bag + .npz ground truth)')
    s.add_argument('--surface', choices=SURFACES, default=sc.surface,
                   help='flag, face, sheet (isometric bending) or sphere (breathing cap); '
                   f'default {sc.surface}')
    s.add_argument('--size', default=f'{sc.width}x{sc.height}',
                   help=f'WIDTHxHEIGHT (default {sc.width}x{sc.height})')
    s.add_argument('--frames', type=int, default=sc.frames, help=f'(default {sc.frames})')
    s.add_argument('--fps', type=float, default=sc.fps, help=f'(default {sc.fps:g})')
    s.add_argument('--seed', type=int, default=sc.seed, help=f'(default {sc.seed})')
    s.add_argument('--noise', type=float, default=sc.noise,
                   help=f'image noise sigma (default {sc.noise:g})')
    s.add_argument('--camera-motion', type=float, default=sc.camera_motion_deg, metavar='DEG',
                   help='camera swing amplitude, degrees 0..90 '
                   f'(default {sc.camera_motion_deg:g})')
    s.add_argument('--amplitude', type=float, default=sc.amplitude, metavar='A',
                   help=f'deformation amplitude multiplier, 0 = rigid (default {sc.amplitude:g})')
    s.add_argument('--occluder', action='store_true',
                   help='a textured disc sweeps across in front of the surface')
    s.add_argument('--background', action='store_true',
                   help='a textured wall behind the surface, still in the world (instead of '
                   'a plain dark background)')
    s.add_argument('--distance', type=float, default=sc.distance, metavar='M',
                   help=f'camera distance to the surface, metres (default {sc.distance:g})')
    s.add_argument('--periodic', type=int, default=sc.period_frames, metavar='N',
                   help='the deformation repeats every N frames (forwards and back; a '
                   'heartbeat- or breathing-like motion) while the camera moves; 0: off')
    s.add_argument('--stride', type=int, default=sc.stride,
                   help=f'ground-truth track sampling (default {sc.stride})')
    s.add_argument('--out', required=True, help='output bag folder (the .npz goes beside it)')

    r = add('record', 'record live topics into an MCAP bag (raw bytes; counts printed)')
    r.add_argument('topics', nargs='+')
    r.add_argument('--out', required=True)
    r.add_argument('--duration', type=float, default=0.0, help='seconds (0: until Ctrl-C)')
    r.add_argument('--storage', choices=['mcap', 'sqlite3'], default='mcap')

    rp = add('replay', 'publish a bag with its recorded timing')
    rp.add_argument('bag')
    rp.add_argument('--rate', type=float, default=1.0)
    rp.add_argument('--loop', action='store_true')
    rp.add_argument('--clock', action='store_true', help='publish /clock (use_sim_time)')
    rp.add_argument('--topics', nargs='*', default=None)
    rp.add_argument('--wait-for-subscribers', type=int, default=1, metavar='N',
                    help='before publishing, wait until every topic has N subscribers matched '
                    '(topics nobody subscribes to are not waited for; 0: do not wait; '
                    'default 1)')
    rp.add_argument('--wait-timeout', type=float, default=10.0, metavar='S',
                    help='longest wait for subscribers, seconds (default 10)')

    pr = add('process', 'run the node pipeline offline over a bag (no DDS); several bags: each '
             'in its own worker process (or Ray task: --ray), one output bag per input under '
             '--out')
    pr.add_argument('bag', nargs='+', help='input bag(s)')
    pr.add_argument('--out', required=True,
                    help='output bag folder; with several bags the folder that gets one output '
                    'bag per input (named like the input) and report.json')
    pr.add_argument('--pipeline', default='tracker,reconstructor,registrar,scene_flow',
                    help='comma-separated stages (default: all four)')
    pr.add_argument('--params', default=None,
                    help='folder with <node>.yaml parameter files (default: config/)')
    pr.add_argument('--report', default=None,
                    help='report JSON: per-frame errors and per-stage timing (several bags: '
                    'the combined report, default OUT/report.json)')
    pr.add_argument('--jobs', type=int, default=None, metavar='N',
                    help='several bags: worker processes (default 1); with --ray: the local Ray '
                    "instance's CPUs (default: all cores) or, on a cluster, the most bags at a "
                    'time')
    pr.add_argument('--ray', nargs='?', const='', default=None, metavar='ADDRESS',
                    help='run the bags as Ray tasks (pip install nrsfm_ros[ray]): without '
                    'ADDRESS on a private local Ray instance bound to 127.0.0.1, with one '
                    '(HOST:PORT of the head) on that cluster; --out is then a folder '
                    'of output bags even for one bag.  Put it after the bags or write '
                    '--ray=ADDRESS')
    pr.add_argument('--copy-inputs', action='store_true', help='also copy the input topics')
    pr.add_argument('--stage-workers', choices=('threads', 'processes', 'none'), default=None,
                    help='one bag: the stages run at once, each in its own thread (the '
                    'default: nothing pickled, the stages overlap where they release the GIL; '
                    'on 2 cores 0.8-1.0x the wall time of one stage at a time) or process '
                    '(no GIL; each starts and pickles its messages), fed in the one-process '
                    'order (the same output messages); none: one stage at a time.  Several '
                    'bags run one stage at a time in each worker (--jobs)')
    pr.add_argument('--no-progress', action='store_true')

    t = add('topic', 'inspect live topics: list, echo, hz, info')
    t.add_argument('action', choices=['list', 'echo', 'hz', 'info'])
    t.add_argument('topic', nargs='?')
    t.add_argument('-n', '--count', type=int, default=1, help='echo: messages to show')
    t.add_argument('--seconds', type=float, default=None,
                   help='how long to listen (list, hz, info: 3 s; echo: 5 s for the first '
                   'messages)')

    e = add('export', 'write PLY files and PNG renders of the clouds in a bag (perspective, '
            'oblique view; the cloud\'s rgb colours, else shaded by depth)')
    e.add_argument('bag')
    e.add_argument('--out', required=True)
    e.add_argument('--topic', default='nrsfm/points')
    e.add_argument('--every', type=int, default=1, help='export every N-th cloud')

    ev = add('evaluate', 'score an output bag against the ground truth synth wrote: e3D of '
             'nrsfm/points per frame with the static-oracle and flat-plane baselines on the same '
             'frames and points, registration and scene-flow errors; unmatched frames listed, '
             'never scored')
    ev.add_argument('bag', help='output bag (of process, record or demo)')
    ev.add_argument('--ground-truth', required=True, metavar='GT',
                    help='the .npz that synth writes beside its bag (synth --out BAG: BAG.npz)')
    ev.add_argument('--plot', default=None, metavar='PNG',
                    help='write a PNG of e3D per frame against the baselines over time')
    ev.add_argument('--json', default=None, metavar='FILE',
                    help='write the numbers (and the per-frame e3D) as JSON')
    ev.add_argument('--render', default=None, metavar='DIR',
                    help='write perspective 3-D renders to DIR: compare_FFF.png (first, middle, '
                    'last frame) with the aligned cloud, the ground truth and a per-point error '
                    'heat map side by side, and a video of every frame')
    if wanted('evaluate'):
        from .render import SHADINGS, VIDEO_FORMATS
        ev.add_argument('--shading', default=None, choices=SHADINGS,
                        help='--render: shade the clouds by surface normals (default) or by '
                        'depth')
        ev.add_argument('--video', default=None, choices=VIDEO_FORMATS,
                        help='--render: stream.gif (default), stream.mp4 or no video')

    tr = add('track', 'dense tracks from a folder of images or a video -> tracks.npz (W, V)')
    if wanted('track'):
        _track_args(tr)

    rc = add('reconstruct', 'NRSfM on a tracks .npz (W 2FxP, optional V FxP) -> shapes.npz')
    _reconstruct_args(rc)

    train = add('train-hdmnet', 'HDM-Net: render the training data, train (PyTorch), export '
                'hdmnet.onnx + hdmnet.json (seed, data, command, commit, metrics)')
    image = add('reconstruct-image', 'HDM-Net: one image -> a 73 x 73 grid of 3-D points '
                '(camera frame, m) and its depth image (.npz: points, valid, depth, K)')
    if wanted('train-hdmnet') or wanted('reconstruct-image'):
        from .hdmnet_tools import add_image_args, add_train_args
        add_train_args(train)
        add_image_args(image)

    rg = add('register', 'register SOURCE to TARGET (PLY, PCD ascii, .npy or xyz text)')
    if wanted('register'):
        _register_args(rg)

    sf = add('scene-flow', 'RGB-D scene flow (MSF, piecewise rigid) of a folder -> flow.npz: '
             'flow (F-1, H, W, 3) m from the first frame to each later one, first camera '
             'frame, NaN where unknown; valid (F-1, H, W)')
    if wanted('scene-flow'):
        _scene_flow_args(sf)

    vw = add('view', 'Foxglove WebSocket server: plays a bag, or bridges the live topics '
             '(without BAG): clouds, images, depth, scene-flow arrows, camera pose')
    vw.add_argument('bag', nargs='?', default=None,
                    help='bag to play (default: bridge the live ROS topics)')
    vw.add_argument('--port', type=int, default=8765, help='WebSocket port (default 8765; 0: '
                    'any free port)')
    vw.add_argument('--host', default='127.0.0.1', help='address to serve on (default '
                    '127.0.0.1)')
    vw.add_argument('--rate', type=float, default=1.0, help='bag: playback rate (default 1.0)')
    vw.add_argument('--loop', action='store_true', help='bag: play it again and again')
    return p


def _track_args(tr: argparse.ArgumentParser) -> None:
    tr.add_argument('frames')
    tr.add_argument('--out', required=True)
    # the tracker node's parameters (params.TrackerParams): the same names, defaults and checks
    from .core.tracking import MASKS, PRESETS
    from .params import TRACKER_METHODS, TrackerParams
    tp = TrackerParams()
    tr.add_argument('--method', default=None, choices=TRACKER_METHODS,
                    help=f'mfof: multi-frame subspace flow + occlusion tensor; reference: DIS '
                    f'reference->frame seeded by the previous frame (default {tp.method})')
    tr.add_argument('--preset', default=None, choices=sorted(PRESETS),
                    help=f'DIS preset of the data step (default {tp.preset})')
    tr.add_argument('--stride', type=int, default=None,
                    help=f'track every stride-th pixel (default {tp.stride})')
    tr.add_argument('--mask', default=None, choices=MASKS,
                    help=f'which reference pixels to track (default {tp.mask})')
    tr.add_argument('--rank', type=int, default=None,
                    help=f'mfof: learned basis images (default {tp.rank})')
    tr.add_argument('--window', type=int, default=None,
                    help=f'mfof: refinement window, frames (default {tp.window})')
    tr.add_argument('--streaming', action='store_true',
                    help='mfof: skip the two-sided batch pass (what the node publishes)')
    tr.add_argument('--masks', default=None, metavar='MASKS',
                    help='the surface\'s segmentation, one image per frame (a folder in name '
                    'order, or a video; bright (> 127): the surface): what lies outside is '
                    'blacked out and a new reference tracks only inside (the node\'s roi_mask)')
    tr.add_argument('--roi-margin', type=int, default=None, metavar='PX',
                    help=f'with --masks: px taken off the mask\'s edge for a new reference '
                    f'(default {tp.roi_margin})')


def _reconstruct_args(rc: argparse.ArgumentParser) -> None:
    rc.add_argument('tracks')
    rc.add_argument('--method', default='bmm',
                    help='rigid, lowrank, bmm (default: Dai-Li-He cameras + nuclear-norm '
                    'shapes), smsr (DCT-smoothed tracks), amp (metric projections) or cdf '
                    '(coherent depth fields: occluded tracks filled from visible neighbours) or '
                    'hdsm (lifted high-dimensional model; --rank is its dimension D, default 9) '
                    'or va (Garg variational: cdf + spatial Huber-TV on the image grid) or '
                    'planar (planar rest shape deforming out of its plane: cloth, paper, flag) '
                    'or dspr (dynamic shape prior: the first --batch-frames frames solved by '
                    'auto, then frame by frame; recurring states stored as camera + index) '
                    'or spva (shape prior from the least-occluded frames of a cdf solve, '
                    'then every frame by the variational energy with the prior weighted by '
                    'the occlusion 1 - V; --rank is its subspace rank, default 4)')
    rc.add_argument('--batch-frames', type=int, default=None, metavar='N',
                    help='dspr: frames of the initial batch that builds the prior (default '
                    'min(60, F/2))')
    rc.add_argument('--prior-frames', type=int, default=None, metavar='N',
                    help='spva: least-occluded frames (total occlusion sum_p 1 - V) the shape '
                    'prior is built from (default 10, at most the frames)')
    rc.add_argument('--rank', type=int, default=None,
                    help='K: lowrank shape rank (default 3); bmm/smsr motion rank (default: '
                    'automatic, cameras averaged over K=2..6); hdsm: lifted dimension D '
                    '(default 9)')
    rc.add_argument('--camera-model', choices=('auto', 'free', 'orbit'), default=None,
                    help='bmm/cdf: per-frame cameras (free), their constant-rate orbit fit '
                    '(orbit: turntable, orbiting rig, steady pan) or orbit when the per-frame '
                    'rotations agree with it (auto, default)')
    rc.add_argument('--smooth', type=float, default=None,
                    help='bmm/cdf: weight of the trajectory prior on the shapes (second '
                    'differences over frames; default 100 with orbit cameras, else 0)')
    rc.add_argument('--robust', type=float, default=None, metavar='K',
                    help='rigid: reweighted fit (--robust-loss), entries further than K x '
                    'the robust spread of the reprojection distances count less (tracker '
                    'outliers; default 0: the plain factorisation)')
    rc.add_argument('--robust-loss', choices=('huber', 'cauchy'), default=None,
                    help='rigid with --robust: the weights, huber (default) or cauchy '
                    '(redescending: entries far off count next to nothing)')
    rc.add_argument('--out', required=True)


def _register_args(rg: argparse.ArgumentParser) -> None:
    rg.add_argument('source')
    rg.add_argument('target')
    rg.add_argument('--method', default='icp',
                    help='icp, icp-point-to-point, icp-point-to-plane, cpd-rigid, cpd-affine, '
                    'cpd-nonrigid, ga, bhrga, nrga (default icp; ecpd-* need prior matches, '
                    'which the registrar node takes from track ids)')
    # unset flags take the core functions' defaults, which the help quotes
    from .core.registration import cpd, icp
    icp_d, cpd_d = _defaults(icp), _defaults(cpd)
    rg.add_argument('--init', choices=('centroid', 'global', 'identity'), default=None,
                    help=f'icp*: centroid, global (search over all rotations, robust to outliers '
                    f"and missing parts) or identity (default {icp_d['init']})")
    rg.add_argument('--voxel', type=float, default=None,
                    help=f"icp*: coarse-to-fine voxel edge in input units (default "
                    f"{icp_d['voxel']:g}: off)")
    rg.add_argument('--trim', type=float, default=None,
                    help=f"icp*: fraction of closest pairs kept (default {icp_d['trim']:g}; "
                    'about the overlap)')
    rg.add_argument('--w', type=float, default=None,
                    help=f"cpd: outlier weight (default {cpd_d['w']:g})")
    rg.add_argument('--beta', type=float, default=None,
                    help=f"cpd-nonrigid: kernel width in RMS radii (default {cpd_d['beta']:g})")
    rg.add_argument('--lam', type=float, default=None,
                    help=f"cpd-nonrigid: field smoothness (default {cpd_d['lam']:g})")
    rg.add_argument('--out', required=True)


def _scene_flow_args(sf: argparse.ArgumentParser) -> None:
    from .params import SceneFlowParams
    sf.add_argument('rgbd', help='folder with color/ (jpg/png), depth/ (16-bit PNG, mm) and '
                    'intrinsics.txt (3x3); frames in name order')
    sf.add_argument('--out', required=True)
    sf.add_argument('--method', choices=('msf', 'dis', 'icp'), default='msf',
                    help='msf (default), dis (DIS optical flow + depth) or icp (per-segment '
                    'projective ICP)')
    sf.add_argument('--segments', type=int, default=SceneFlowParams().segments,
                    help='msf/icp: SLIC segments (default: the scene_flow node\'s, '
                    f'{SceneFlowParams().segments})')
    sf.add_argument('--depth-scale', type=float, default=1000.0,
                    help='depth PNG units per metre (default 1000: millimetres; 5000: the TUM '
                    'RGB-D benchmark); 0 in a depth PNG is no depth')


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = _parser(argv[0] if argv and argv[0] in VERBS else None).parse_args(argv)
    args.argv = list(argv) if argv is not None else sys.argv[1:]
    try:
        return int(VERBS[args.verb](args) or 0)
    except KeyboardInterrupt:
        return 130
    except (CliError, ValueError, FileNotFoundError, FileExistsError, LookupError,
            RuntimeError, OSError) as err:
        print(f'error: {_one_line(err)}', file=sys.stderr)
        return 2
    except Exception as err:  # noqa: BLE001 -- bad input never ends in a traceback
        print(f'error: {type(err).__name__}: {_one_line(err)}', file=sys.stderr)
        return 3


def _one_line(err: BaseException) -> str:
    return ' '.join(str(err).split()) or type(err).__name__


# ------------------------------------------------------------------ verbs

def cmd_demo(args: argparse.Namespace) -> int:
    from .demo import SAMPLE, ensure_sample, format_summary, run_live, summarise, write_summary
    from .evaluation import load_ground_truth
    out = Path(args.out)
    bag, npz = ensure_sample(Path(args.bags))
    print(f'sample bag: {bag}')
    seq = load_ground_truth(npz)
    out.mkdir(parents=True, exist_ok=True)
    out_bag = out / 'outputs'
    if out_bag.exists():
        import shutil
        shutil.rmtree(out_bag)
    overrides = {'tracker': {'reliable': True},
                 'reconstructor': {'mean_depth': SAMPLE.distance}}
    live = run_live(bag, out_bag, seq.S.shape[0], args.rate, args.timeout, overrides)
    summary = summarise(out_bag, seq, out)
    summary['live'] = {k: v for k, v in live.items() if k != 'graph_exit'}
    table = format_summary(summary, live)
    write_summary(out, summary, table)
    print(table)
    print(f'outputs: {out_bag} (bag), {out}/summary.md, {out}/summary.json, PLY files, '
          f'compare_FFF.png renders and stream.gif in {out}')
    missing = [t for t in ('nrsfm/tracks', 'nrsfm/points', 'nrsfm/depth', 'registration/aligned',
                           'scene_flow/points') if summary['outputs'].get(t, 0) < seq.S.shape[0]]
    if live.get('graph_exit'):
        raise CliError(f"node(s) exited during the run: {live['graph_exit']}")
    if missing:
        raise CliError(f'outputs lost on {missing}: expected one per input frame')
    return 0


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split('x'))
    except ValueError as err:
        raise CliError(f'--size {text!r}: expected WIDTHxHEIGHT, e.g. 320x240') from err
    return w, h


def cmd_synth(args: argparse.Namespace) -> int:
    from .io.sequence_bag import write_sequence_bag
    from .io.synth import SynthConfig, generate
    w, h = _size(args.size)
    cfg = SynthConfig(surface=args.surface, width=w, height=h, frames=args.frames, fps=args.fps,
                      seed=args.seed, noise=args.noise, stride=args.stride,
                      camera_motion_deg=args.camera_motion, amplitude=args.amplitude,
                      occluder=args.occluder, background=args.background,
                      distance=args.distance,
                      period_frames=args.periodic)
    flags = {'camera_motion_deg': '--camera-motion', 'amplitude': '--amplitude',
             'period_frames': '--periodic',
             'distance': '--distance', 'noise': '--noise', 'frames': '--frames', 'fps': '--fps',
             'stride': '--stride', 'width x height ': '--size'}
    try:
        cfg.validate()
    except ValueError as err:  # name the flag, not the config field
        field, _, rest = str(err).partition('=')
        flag = flags.get(field)
        raise CliError(f'{flag} {rest.lstrip()}' if flag else str(err)) from err
    out = Path(args.out)
    if out.exists():
        raise CliError(f'{out} exists; choose another --out or delete it')
    seq = generate(cfg)
    counts = write_sequence_bag(seq, out)
    npz = out.with_suffix('.npz')
    np.savez_compressed(npz, **seq.npz_dict())
    print(f'wrote {out} ({sum(counts.values())} messages) and {npz}')
    for topic, n in counts.items():
        print(f'  {topic}: {n}')
    return 0


def _rclpy_node(name: str) -> Any:
    import rclpy
    from rclpy.node import Node

    from .live import ensure_loopback_env
    ensure_loopback_env()
    rclpy.init()
    return Node(name)


def _shutdown(node: Any) -> None:
    import rclpy
    node.destroy_node()
    rclpy.try_shutdown()


def cmd_record(args: argparse.Namespace) -> int:
    import time

    import rclpy

    from .live import Recorder
    if not args.duration >= 0:
        raise CliError(f'--duration {args.duration}: must be >= 0 seconds (0: until Ctrl-C)')
    node = _rclpy_node('nrsfm_record')
    rec = Recorder(node, args.topics, args.out, storage=args.storage)
    end = time.monotonic() + args.duration if args.duration > 0 else float('inf')
    try:
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.1)
    except KeyboardInterrupt:
        pass
    finally:
        counts = rec.close()
        _shutdown(node)
    print(f'recorded {args.out}:')
    for topic, n in counts.items():
        print(f'  {topic}: {n} messages')
    return 0


def _bag_topics(bag: str, topics: Sequence[str] | None, kind: str = '') -> dict[str, str]:
    """{topic: type} of the bag, checked against the ``topics`` asked for (names without '/')."""
    from .io.bag import bag_info
    have = {t: v['type'] for t, v in bag_info(bag)['topics'].items()}
    for t in topics or ():
        name = t.lstrip('/')
        if name not in have:
            raise CliError(f'topic {t!r} is not in {bag} (it has: {", ".join(sorted(have))})')
        if kind and not have[name].endswith(kind):
            raise CliError(f'topic {t!r} is a {have[name]}, not a {kind}')
    return have


def cmd_replay(args: argparse.Namespace) -> int:
    from .live import replay
    if not args.rate > 0:
        raise CliError(f'--rate {args.rate}: must be > 0')
    if args.wait_for_subscribers < 0 or not args.wait_timeout >= 0:
        raise CliError('--wait-for-subscribers and --wait-timeout must be >= 0')
    if args.topics is not None:
        if not args.topics:
            raise CliError('--topics: name at least one topic')
        _bag_topics(args.bag, args.topics)
    damage: list[str] = []
    unheard: list[str] = []
    node = _rclpy_node('nrsfm_replay')
    try:
        counts = replay(node, args.bag, rate=args.rate, loop=args.loop, clock=args.clock,
                        topics=args.topics, wait_for=args.wait_for_subscribers,
                        wait_timeout=args.wait_timeout, damage=damage, unheard=unheard)
    finally:
        _shutdown(node)
    if unheard:
        print(f'note: no subscriber matched on {", ".join(sorted(unheard))} (published anyway)')
    for topic, n in counts.items():
        print(f'  {topic}: {n} messages')
    if damage:
        raise CliError(damage[0])
    return 0


def load_params(folder: str | None) -> dict[str, Any]:
    """Parameter sets from <folder>/<node>.yaml (ROS params-file layout)."""
    import yaml

    from .live import package_root
    from .params import NODE_PARAMS, from_mapping
    base = Path(folder) if folder else package_root() / 'config'
    if not base.is_dir():
        raise CliError(f'--params {base}: not a folder (expected one with <node>.yaml files)')
    out = {}
    for name, cls in NODE_PARAMS.items():
        path = base / f'{name}.yaml'
        if not path.exists():
            continue
        try:
            doc = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as err:
            raise CliError(f'{path}: not valid YAML ({_one_line(err)})') from err
        values = doc.get(name, {}).get('ros__parameters', {}) \
            if isinstance(doc, dict) and isinstance(doc.get(name, {}), dict) else None
        if not isinstance(values, dict):
            raise CliError(f'{path}: expected "{name}: ros__parameters: {{name: value}}"')
        try:
            out[name] = from_mapping(cls, values)
        except (ValueError, TypeError) as err:
            raise CliError(f'{path}: {err}') from err
    if folder and not out:
        raise CliError(f'--params {base}: no <node>.yaml file in it '
                       f'(expected {", ".join(f"{n}.yaml" for n in NODE_PARAMS)})')
    return out


def cmd_process(args: argparse.Namespace) -> int:
    from .io.bag import bag_info
    from .pipeline import STAGES, process_bag, write_report
    stages = [s.strip() for s in args.pipeline.split(',') if s.strip()]
    if not stages:
        raise CliError(f'--pipeline {args.pipeline!r}: name at least one of {", ".join(STAGES)}')
    bad = [s for s in stages if s not in STAGES]
    if bad:
        raise CliError(f'--pipeline: unknown stage(s) {bad}; expected from {", ".join(STAGES)}')
    if args.jobs is not None and args.jobs < 1:
        raise CliError(f'--jobs {args.jobs}: expected >= 1')
    if args.ray and Path(args.ray).exists():
        raise CliError(f'--ray {args.ray}: that is a path, not a Ray address; put --ray after '
                       'the bags or write --ray=HOST:PORT')
    params = load_params(args.params)
    if len(args.bag) > 1 or args.ray is not None:
        if args.stage_workers not in (None, 'none'):
            raise CliError(f'--stage-workers {args.stage_workers}: one bag only; several bags '
                           '(or --ray) already run one worker per bag (--jobs)')
        return _process_many(args, stages, params)
    bag = args.bag[0]
    bag_info(bag)               # not a bag: one error line before anything is written
    if Path(args.out).exists():
        raise CliError(f'{args.out} exists; choose another --out or delete it')
    report = process_bag(bag, args.out, stages, params,
                         progress=not args.no_progress, copy_inputs=args.copy_inputs,
                         pipelined=False if args.stage_workers == 'none'
                         else args.stage_workers or 'threads')
    d = report.as_dict()
    if args.report:
        write_report(report, args.report)
    print(f"processed {sum(d['inputs'].values())} messages in {d['seconds']} s "
          f"(CPU {d.get('cpu_s')} s; {d['realtime_factor']}x real time); outputs:")
    for topic, n in d['outputs'].items():
        print(f'  {topic}: {n}')
    for line in format_timing(d):
        print(line)
    if d['failures']:
        print(f"{len(d['failures'])} frame(s) could not be processed:")
        for f in d['failures'][:20]:
            print(f"  stamp {f['stamp_ns']} {f['stage']} ({f['topic']}): {f['error']}")
        if len(d['failures']) > 20:
            print(f"  ... and {len(d['failures']) - 20} more"
                  + (f' (all in {args.report})' if args.report else ' (see --report)'))
    if report.damage:
        raise CliError(report.damage[0])
    return 1 if d['failures'] else 0


def format_timing(d: dict[str, Any]) -> list[str]:
    """The per-stage timing table of a process report (ms per callback of each stage)."""
    rows = [(stage, kind, t) for stage, kinds in d.get('timing', {}).items()
            for kind, t in kinds.items()]
    if not rows:
        return []
    io = d.get('io_s', {})
    lines = ['per-stage processing time (ms per message; each stage alone; cpu s: the '
             "process' CPU time, which other work on the machine does not inflate):",
             f"  {'stage':<14}{'input':<18}{'calls':>6}{'mean':>9}{'p50':>9}{'p90':>9}"
             f"{'max':>9}{'total s':>9}{'cpu s':>9}"]
    for stage, kind, t in rows:
        lines.append(f"  {stage:<14}{kind:<18}{t['calls']:>6}{t['mean_ms']:>9.2f}"
                     f"{t['p50_ms']:>9.2f}{t['p90_ms']:>9.2f}{t['max_ms']:>9.2f}"
                     f"{t['total_s']:>9.3f}{t.get('cpu_s', float('nan')):>9.3f}")
    if io:
        lines.append('  outside the stages: ' + ', '.join(f'{k} {v:.3f} s'
                                                       for k, v in io.items()))
    return lines


def _process_many(args: argparse.Namespace, stages: list[str], params: Any) -> int:
    """``process BAG BAG ... --out DIR --jobs N``: one worker process per bag (or Ray task)."""
    from .fleet import RayUnavailableError, output_paths, process_bags, write_fleet_report
    try:
        output_paths(args.bag, args.out)
    except ValueError as err:
        raise CliError(str(err)) from err
    report_path = Path(args.report) if args.report else Path(args.out) / 'report.json'
    if report_path.exists():
        raise CliError(f'--report {report_path} exists; choose another or delete it')
    total = len(args.bag)
    done = [0]

    def on_done(entry: dict[str, Any]) -> None:
        done[0] += 1
        if args.no_progress:
            return
        what = entry['error'] if entry['status'] == 'failed' else \
            f"{entry['frames_in']} frames in, {entry['frames_out']} out, " \
            f"{entry['failures']} failure(s), {entry['seconds']:.2f} s"
        print(f"[{done[0]}/{total}] {entry['bag']}: {entry['status']}: {what}", flush=True)

    try:
        fleet = process_bags(args.bag, args.out, stages, params, jobs=args.jobs,
                             copy_inputs=args.copy_inputs, on_done=on_done, ray=args.ray)
    except RayUnavailableError as err:
        raise CliError(f'--ray: {err}') from err
    write_fleet_report(fleet, report_path)
    d = fleet.as_dict()
    tot, thr = d['total'], d['throughput']
    where = ''
    if 'ray' in d:
        r = d['ray']
        where = f" (Ray {r['address']}: {len(r['nodes'])} node(s), {r['cpus']:g} CPU(s))"
    print(f"{tot['bags']} bag(s) on {d['jobs']} worker(s){where} in {d['wall_s']} s: "
          f"{tot['ok']} ok, "
          f"{tot['frame_failures']} with frame failures, {tot['failed']} failed; "
          f"{tot['frames_in']} frames in, {tot['frames_out']} out; "
          f"{thr['frames_per_s']} frames/s, {thr['bags_per_s']} bags/s "
          f"(worker time {tot['worker_s']} s)")
    print(f"  {'bag':<32}{'status':<16}{'in':>6}{'out':>6}{'fail':>6}{'s':>8}  error")
    for b in d['bags']:
        print(f"  {Path(b['bag']).name:<32}{b['status']:<16}{b['frames_in']:>6}"
              f"{b['frames_out']:>6}{b['failures']:>6}{b['seconds']:>8.2f}  {b['error']}")
    print(f'outputs under {args.out}; report {report_path}')
    return fleet.exit_code()


def cmd_topic(args: argparse.Namespace) -> int:
    import time

    import rclpy

    from .live import echo, hz, topic_types
    if args.action != 'list' and not args.topic:
        raise CliError(f'topic {args.action} needs a TOPIC')
    if args.seconds is None:
        args.seconds = 5.0 if args.action == 'echo' else 3.0
    if not args.seconds > 0:
        raise CliError(f'--seconds must be > 0 (got {args.seconds})')
    node = _rclpy_node('nrsfm_topic')
    try:
        if args.action == 'list':
            end = time.monotonic() + args.seconds
            while time.monotonic() < end:
                rclpy.spin_once(node, timeout_sec=0.1)
            for name, t in sorted(topic_types(node).items()):
                print(f'{name} [{t}]')
        elif args.action == 'echo':
            if echo(node, args.topic, args.count, args.seconds) == 0:
                raise CliError(f'no message on {args.topic} within {args.seconds} s')
        elif args.action == 'hz':
            r = hz(node, args.topic, args.seconds)
            print(f"{args.topic}: {r['rate_hz']:.2f} Hz over {r['messages']} messages, "
                  f"mean {r['mean_bytes'] / 1e3:.1f} kB")
        else:
            name = args.topic if args.topic.startswith('/') else '/' + args.topic
            end = time.monotonic() + args.seconds
            while time.monotonic() < end and name not in topic_types(node):
                rclpy.spin_once(node, timeout_sec=0.1)
            rclpy.spin_once(node, timeout_sec=0.3)  # let the endpoint counts settle
            types = topic_types(node)
            if name not in types:
                raise CliError(f'topic {name} not found')
            print(f'{name}\n  type: {types[name]}\n'
                  f'  publishers: {node.count_publishers(name)}\n'
                  f'  subscribers: {node.count_subscribers(name)}')
    finally:
        _shutdown(node)
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from .io import pointcloud2 as pc2
    from .io.bag import deserialize, read_messages
    from .io.export import write_ply
    from .render import render_cloud
    from .io.errors import MessageError
    if args.every < 1:
        raise CliError('--every must be >= 1')
    _bag_topics(args.bag, [args.topic], 'PointCloud2')
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    n, bad, damage = 0, [], []
    for i, m in enumerate(read_messages(args.bag, [args.topic.lstrip('/')], damage=damage)):
        if i % args.every:
            continue
        try:
            msg = deserialize(m.raw, m.msgtype)
            X = pc2.read_xyz(msg, skip_nans=False)
            rgb = pc2.read_points(msg).reshape(-1)['rgb'] \
                if 'rgb' in pc2.field_names(msg) else None
            rgb = pc2.unpack_rgb(rgb) if rgb is not None and rgb.ndim == 1 else None
        except MessageError as err:
            bad.append(f'cloud {i}: {err}')
            continue
        write_ply(out / f'cloud_{i:04d}.ply', X, rgb)
        render_cloud(out / f'cloud_{i:04d}.png', X, rgb)
        n += 1
    if n == 0 and not damage:
        raise CliError(f'no readable cloud on {args.topic} in {args.bag}'
                       + (f' ({bad[0]})' if bad else ''))
    print(f'wrote {n} PLY + PNG pairs to {out}')
    if damage:
        raise CliError(damage[0])
    if bad:
        raise CliError(f'{len(bad)} cloud(s) not exported: {bad[0]}'
                       + (f' (and {len(bad) - 1} more)' if len(bad) > 1 else ''))
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from .evaluation import (MIN_POINTS, evaluate_outputs, load_ground_truth, plot_errors,
                             read_outputs)
    from .io.bag import bag_info
    from .processing import TOPICS
    bag, gt = Path(args.bag), Path(args.ground_truth)
    info = bag_info(bag)                # a missing or foreign bag: one error line naming it
    seq = load_ground_truth(gt)
    if (args.shading or args.video) and not args.render:
        raise CliError('--shading and --video shape the renders of --render DIR: give --render')
    if args.plot:
        try:
            import matplotlib  # noqa: F401
        except ImportError as err:
            raise CliError('--plot needs matplotlib (.venv/bin/pip install -r '
                           'requirements.txt)') from err
    points = TOPICS['points']
    if points not in info['topics']:
        raise CliError(f'{bag}: no {points} topic to score (it has: '
                       f'{", ".join(sorted(info["topics"])) or "nothing"})')
    out = read_outputs(bag, seq)
    if not out.clouds:
        seen = out.unmatched.get(points, [])
        raise CliError(f'{bag}: none of its {len(seen)} {points} cloud(s) has the stamp of a '
                       f'frame of {gt} (clouds {min(seen, default=0)}..{max(seen, default=0)} '
                       f'ns, ground truth {int(seq.stamps_ns[0])}..{int(seq.stamps_ns[-1])} ns): '
                       'not the ground truth of this bag?')
    r = evaluate_outputs(out, seq)
    if r['frames_scored'] == 0:
        raise CliError(f'{bag}: no {points} frame could be scored against {gt} (no cloud has '
                       f'{MIN_POINTS} points with a ground-truth track id): not the ground truth '
                       'of this bag?')
    for line in format_evaluation(r, seq, bag, gt):
        print(line)
    if args.json:
        Path(args.json).write_text(json.dumps(evaluation_json(r, seq, bag, gt), indent=2,
                                              allow_nan=False))
        print(f'wrote {args.json}')
    if args.plot:
        plot_errors(r, seq, args.plot, title=f'{bag.name} against {gt.name}')
        print(f'wrote {args.plot}')
    if args.render:
        from .render import render_stream
        rr = render_stream(out.clouds, seq.S, seq.track_ids, args.render,
                           shading=args.shading or 'normals', video=args.video or 'gif',
                           fps=seq.config.fps, min_points=MIN_POINTS)
        print(f'wrote {len(rr.stills)} render(s) to {args.render}'
              + (f' and {rr.video} ({rr.frames} frames)' if rr.video else '')
              + f'; heat map 0..{rr.vmax:.3g} x RMS radius, {rr.seconds_per_frame:.2f} s/frame')
    if out.damage:
        raise CliError(out.damage[0])
    return 0


def format_evaluation(r: dict[str, Any], seq: Any, bag: Path, gt: Path) -> list[str]:
    """The printed report of ``evaluate`` (numbers as in the demo summary)."""
    from .demo import OUTPUT_TOPICS
    from .processing import TOPICS
    F = r['frames_in']
    outs = r['outputs']
    lines = [f'{bag} against {gt}: {F} ground-truth frames, {seq.S.shape[1]} tracks',
             f'frames in: {F}; frames out: ' + ', '.join(
                 f'{t} {outs.get(t, 0)}' for t in OUTPUT_TOPICS),
             f"nrsfm/points: {r['frames_scored']} of {F} frames scored; "
             f"{r['points_matched_per_frame']:.0f} of {r['points_per_frame']} points per frame "
             'matched to ground truth',
             f"  e3D metric B (per-frame Procrustes + scale), mean over frames  "
             f"{r['e3d_B_frame_scaled']:.4f}",
             f"  static oracle (frame 0 repeated), same frames and points      "
             f"{r['e3d_static_oracle']:.4f}   e3D/static {r['ratio_static']:.2f}x",
             f"  flat plane (frame 0 flattened), same frames and points        "
             f"{r['e3d_flat_plane']:.4f}   e3D/flat   {r['ratio_flat']:.2f}x",
             f"  frames with depths reflected against the truth (metric B forgives them) "
             f"{r['frames_depth_reflected']}"]
    per = r.get('per_frame_e3d', {})
    if per:
        e = {f: v[0] for f, v in per.items()}
        worst = max(e, key=e.get)
        lines.append(f'  per frame: median {np.median(list(e.values())):.4f}, worst '
                     f'{e[worst]:.4f} (frame {worst})')
    if 'registration_rmse_m' in r:
        lines.append(f"registration/aligned: RMSE to the frame-0 ground truth "
                     f"{r['registration_rmse_m']:.4f} m ({r['registration_rmse_frames']} frames)")
    if 'registration_rotation_error_deg_median' in r:
        lines.append(f"registration/transform: rotation error, median "
                     f"{r['registration_rotation_error_deg_median']:.2f} deg "
                     f"({r['registration_rotation_frames']} frames)")
    if 'scene_flow_relative_epe' in r:
        lines.append(f"scene_flow/points: relative EPE {r['scene_flow_relative_epe']:.3f} "
                     f"({r['scene_flow_frames_scored']} frames; frame 0 has no flow)")
    elif outs.get(TOPICS['scene_flow']):
        why = 'no frame with enough points matched' if 'scene_flow_unscored' in r else \
            'the ground truth has no S_world / fps'
        lines.append(f'scene_flow/points: not scored ({why})')
    if r['frames_unscored']:
        lines.append(f"unscored nrsfm/points frames ({len(r['frames_unscored'])}):")
        lines += [f"  frame {f} (stamp {int(seq.stamps_ns[f])}): {r['unscored_reasons'][f]}"
                  for f in r['frames_unscored']]
    if r.get('scene_flow_unscored'):
        lines.append(f"unscored scene_flow/points frames: {r['scene_flow_unscored']}")
    for topic, stamps in r.get('unmatched_stamps', {}).items():
        lines.append(f'{topic}: {len(stamps)} message(s) whose stamp is no ground-truth frame '
                     f'(not scored): {", ".join(str(s) for s in stamps)}')
    return lines


def evaluation_json(r: dict[str, Any], seq: Any, bag: Path, gt: Path) -> dict[str, Any]:
    """``evaluate --json``: the numbers under the demo summary's keys, per-frame e3D and
    unscored frames as lists."""
    t0 = int(seq.stamps_ns[0])
    d = {'bag': str(bag), 'ground_truth': str(gt)}
    d.update({k: v for k, v in r.items() if not k.startswith('per_frame')
              and k != 'unscored_reasons'})
    d['unscored'] = [{'frame': f, 'stamp_ns': int(seq.stamps_ns[f]), 'reason': why}
                     for f, why in r.get('unscored_reasons', {}).items()]
    d['per_frame'] = [{'frame': f, 'stamp_ns': int(seq.stamps_ns[f]),
                       'time_s': (int(seq.stamps_ns[f]) - t0) / 1e9, 'e3d': e, 'static': st,
                       'flat': fl, 'points_matched': n}
                      for f, (e, st, fl, n) in sorted(r.get('per_frame_e3d', {}).items())]
    sf = r.get('per_frame_scene_flow_relative_epe', {})
    if sf:
        d['per_frame_scene_flow'] = [{'frame': f, 'relative_epe': v}
                                     for f, v in sorted(sf.items())]

    def finite(v: Any) -> Any:      # strict JSON: a NaN or inf number is written as null
        if isinstance(v, dict):
            return {k: finite(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [finite(x) for x in v]
        return None if isinstance(v, float) and not np.isfinite(v) else v
    return finite(d)


def _read_frames(path: Path) -> list[np.ndarray]:
    import cv2
    if path.is_dir():
        files = sorted(p for p in path.iterdir()
                       if p.suffix.lower() in ('.png', '.jpg', '.jpeg', '.bmp', '.ppm', '.pgm'))
        frames = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
        bad = [str(f) for f, im in zip(files, frames) if im is None]
        if bad:
            raise CliError(f'could not read image(s): {bad[:3]}')
        return frames
    if not path.exists():
        raise FileNotFoundError(f'{path} does not exist')
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
    return frames


TRACK_FLAGS = ('method', 'preset', 'stride', 'mask', 'rank', 'window',
               'roi_margin')                                        # TrackerParams names


def cmd_track(args: argparse.Namespace) -> int:
    from .core.tracking import ReferenceFlowTracker, track_sequence
    from .params import TrackerParams
    frames = _read_frames(Path(args.frames))
    if len(frames) < 2:
        raise CliError(f'{args.frames}: need at least 2 frames, found {len(frames)}')
    for i, f in enumerate(frames):
        if f.shape != frames[0].shape:
            raise CliError(f'frame {i}: size {f.shape} differs from frame 0 {frames[0].shape}')
    given = {k: getattr(args, k) for k in TRACK_FLAGS if getattr(args, k) is not None}
    p = TrackerParams().updated(given)          # the node's checks: an error names the flag
    rois = None
    if args.masks is not None:
        from .core.tracking.reference_flow import black_out, roi_region
        masks = _read_frames(Path(args.masks))
        if len(masks) != len(frames):
            raise CliError(f'--masks {args.masks}: {len(masks)} masks for {len(frames)} frames')
        for i, m in enumerate(masks):
            if m.shape != frames[0].shape:
                raise CliError(f'--masks: mask {i} size {m.shape} differs from the frames '
                               f'{frames[0].shape}')
        masks = [m > 127 for m in masks]         # a compressed file's black is not 0
        frames = [black_out(f, m) for f, m in zip(frames, masks)]
        rois = [roi_region(m, p.roi_margin) for m in masks]
    elif args.roi_margin is not None:
        raise CliError('--roi-margin: only with --masks')
    if p.method == 'mfof':
        res = track_sequence(frames, p.mfof_config(), smooth=not args.streaming, rois=rois)
        W, V = res.W.astype(np.float64), res.V
        np.savez_compressed(args.out, W=W, V=V, O=res.O, track_ids=res.ids,
                            reselections=np.array(res.reselections, np.int64))
        extra = f'; occlusion tensor O {res.O.shape}; {res.seconds:.2f} s'
        if res.reselections:
            extra += (f'; new reference at frame {res.reselections[0]}: later frames keep the '
                      'first reference\'s tracks marked invisible')
    else:
        tracker = ReferenceFlowTracker(preset=p.preset, stride=p.stride, mask=p.mask,
                                       min_std=p.min_std,
                                       occlusion_threshold=p.occlusion_threshold)
        tracker.roi = None if rois is None else rois[0]
        out = [tracker.step(f) for f in frames]
        W = np.concatenate([t.uv.T for t in out]).astype(np.float64)
        V = np.stack([t.visibility for t in out])
        np.savez_compressed(args.out, W=W, V=V, track_ids=tracker.ids)
        extra = ''
    print(f'wrote {args.out}: W {W.shape}, {len(frames)} frames x {W.shape[1]} tracks{extra}')
    return 0


def _load_npz(path: Path) -> Any:
    """An .npz with every array readable (a truncated file fails here, naming the path)."""
    import zipfile
    try:
        d = np.load(path, allow_pickle=False)
        if not hasattr(d, 'files'):
            raise CliError(f'{path}: not an .npz archive (a single array)')
        for k in d.files:
            d[k]
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as err:
        raise CliError(f'{path}: not a readable .npz ({_one_line(err)})') from err
    return d


def cmd_reconstruct(args: argparse.Namespace) -> int:
    from .core.nrsfm import METHODS, reconstruct
    path = Path(args.tracks)
    if not path.exists():
        raise FileNotFoundError(f'{path} does not exist')
    d = _load_npz(path)
    if 'W' not in d.files:
        raise CliError(f'{path}: no array named W (keys: {d.files})')
    if args.method == 'dspr':
        return _reconstruct_dspr(d, args)
    if args.batch_frames is not None:
        raise CliError(f'--batch-frames applies to --method dspr, not {args.method}')
    if args.method not in METHODS:
        raise CliError(f'--method {args.method!r}: expected one of '
                       f'{sorted([*METHODS, "dspr"])}')
    if args.prior_frames is not None and args.method != 'spva':
        raise CliError(f'--prior-frames applies to --method spva, not {args.method}')
    if args.method in ('rigid', 'cdf', 'va', 'planar'):
        if args.rank is not None:
            raise CliError(f'--rank does not apply to --method {args.method}')
        kw = {}
    elif args.method == 'spva':
        kw = {k: v for k, v in (('rank', args.rank), ('prior_frames', args.prior_frames))
              if v is not None}
    elif args.method == 'hdsm':
        kw = {'dim': args.rank if args.rank is not None else 9}
    else:
        kw = {'rank': args.rank if args.rank is not None else
              (3 if args.method in ('lowrank', 'amp') else 0)}
    for flag, key in (('--camera-model', 'camera_model'), ('--smooth', 'smooth')):
        value = getattr(args, key)
        if value is None:
            continue
        if args.method not in ('bmm', 'cdf'):
            raise CliError(f'{flag} applies to --method bmm and cdf, not {args.method}')
        kw[key] = value
    if args.robust is not None:
        if args.method != 'rigid':
            raise CliError(f'--robust applies to --method rigid, not {args.method}')
        kw['robust'] = args.robust
    if args.robust_loss is not None:
        if 'robust' not in kw:
            raise CliError('--robust-loss needs --robust K (the scale of its weights)')
        kw['loss'] = args.robust_loss
    res = reconstruct(d['W'], d['V'] if 'V' in d.files else None, method=args.method, **kw)
    np.savez_compressed(args.out, S=res.S, R=res.R, scale=res.scale, t=res.t)
    extra = f', compression {res.compression:.1f}x' if res.compression != 1.0 else ''
    print(f'wrote {args.out}: S {res.S.shape} ({res.method}, rank {res.rank}, '
          f'{res.camera_model} cameras, residual {res.residual_px:.3g} px{extra}, '
          f'{res.seconds:.2f} s)')
    return 0


def _reconstruct_dspr(d: Any, args: argparse.Namespace) -> int:
    """The reconstructor's dspr stream over the tracks, frame by frame (S NaN where a frame
    has no shape for a track)."""
    import time

    from .core.nrsfm.result import check_tracks
    from .core.nrsfm.stream import StreamNRSfM
    for flag, key in (('--rank', 'rank'), ('--camera-model', 'camera_model'),
                      ('--smooth', 'smooth'), ('--robust', 'robust'),
                      ('--robust-loss', 'robust_loss')):
        if getattr(args, key) is not None:
            raise CliError(f'{flag} does not apply to --method dspr')
    W, V = check_tracks(d['W'], d['V'] if 'V' in d.files else None)
    F, P = V.shape
    batch = args.batch_frames if args.batch_frames is not None else min(60, max(3, F // 2))
    if not 3 <= batch <= F:
        raise CliError(f'--batch-frames {batch}: expected 3..{F} (the sequence has {F} frames)')
    t0 = time.perf_counter()
    stream = StreamNRSfM(mode='dspr', batch_frames=batch)
    ids = np.arange(P)
    S = np.full((F, P, 3), np.nan)
    t = np.zeros((F, 2))
    shapes = [sh for f in range(F) for sh in stream.push(ids, W[2 * f:2 * f + 2].T, V[f])]
    for sh in shapes + stream.flush():
        S[sh.index, sh.ids] = sh.X
        t[sh.index] = sh.t
    np.savez_compressed(args.out, S=S, t=t, compression=stream.compression_ratio)
    print(f'wrote {args.out}: S {S.shape} (dspr, prior from {batch} frames, compression '
          f'{stream.compression_ratio:.1f}x, {time.perf_counter() - t0:.2f} s)')
    return 0


def read_points_file(path: str) -> np.ndarray:
    """PLY, ascii PCD, .npy or whitespace/comma-separated xyz text -> (N, 3)."""
    from .io.export import read_ply
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f'{p} does not exist')
    suffix = p.suffix.lower()
    if suffix == '.ply':
        X = read_ply(p)
    elif suffix == '.npy':
        X = np.load(p)
    elif suffix == '.pcd':
        lines = p.read_text().splitlines()
        start = next((i for i, ln in enumerate(lines) if ln.startswith('DATA')), None)
        if start is None or 'ascii' not in lines[start]:
            raise CliError(f'{p}: only ascii PCD is supported')
        X = np.loadtxt(lines[start + 1:], ndmin=2)[:, :3]
    else:
        text = p.read_text().replace(',', ' ')
        X = np.loadtxt(text.splitlines(), ndmin=2)
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] < 3:
        raise CliError(f'{p}: expected N x 3 points, got shape {X.shape}')
    return X[:, :3]


def cmd_train_hdmnet(args: argparse.Namespace) -> int:
    from .hdmnet_tools import train_command
    return train_command(args, args.argv)


def cmd_reconstruct_image(args: argparse.Namespace) -> int:
    from .hdmnet_tools import reconstruct_image_command
    return reconstruct_image_command(args)


def cmd_register(args: argparse.Namespace) -> int:
    from .core.registration import METHODS, register
    if args.method not in METHODS:
        raise CliError(f'--method {args.method!r}: expected one of {sorted(METHODS)}')
    kw = {k: v for k in ('w', 'beta', 'lam') if (v := getattr(args, k)) is not None}
    if kw and not args.method.startswith('cpd'):
        raise CliError(f'--{sorted(kw)[0]} applies to the cpd methods, not {args.method}')
    icp_kw = {k: v for k in ('init', 'voxel', 'trim') if (v := getattr(args, k)) is not None}
    if icp_kw and not args.method.startswith('icp'):
        raise CliError(f'--{sorted(icp_kw)[0]} applies to the icp methods, not {args.method}')
    kw.update(icp_kw)
    res = register(read_points_file(args.source), read_points_file(args.target),
                   method=args.method, **kw)
    np.savez_compressed(args.out, T_target_source=res.T_target_source, aligned=res.aligned,
                        displacement=res.displacement, correspondences=res.correspondences)
    print(json.dumps({'method': res.method, 'iterations': res.iterations,
                      'converged': res.converged, 'residual': res.residual,
                      'fitness': res.fitness, 'seconds': round(res.seconds, 3)}))
    return 0


def read_rgbd_folder(folder: Path) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """color/ and depth/ images (name order, same count and size) and intrinsics.txt."""
    import cv2
    if not folder.is_dir():
        raise FileNotFoundError(f'{folder}: not a folder')
    kf = folder / 'intrinsics.txt'
    if not kf.exists():
        raise CliError(f'{kf}: missing (the 3x3 camera matrix)')
    try:
        K = np.loadtxt(kf, ndmin=2)
    except ValueError as err:
        raise CliError(f'{kf}: not a 3x3 matrix of numbers ({_one_line(err)})') from err
    if K.shape != (3, 3):
        raise CliError(f'{kf}: expected a 3x3 matrix, got shape {K.shape}')
    names = {}
    for sub, exts in (('color', ('.png', '.jpg', '.jpeg')), ('depth', ('.png',))):
        d = folder / sub
        if not d.is_dir():
            raise CliError(f'{d}: missing folder')
        names[sub] = sorted(p for p in d.iterdir() if p.suffix.lower() in exts)
    if len(names['color']) != len(names['depth']) or len(names['color']) < 2:
        raise CliError(f'{folder}: {len(names["color"])} color and {len(names["depth"])} depth '
                       'images; expected the same number, at least 2')
    colors, depths = [], []
    for c, d in zip(names['color'], names['depth']):
        img = cv2.imread(str(c), cv2.IMREAD_COLOR)
        dep = cv2.imread(str(d), cv2.IMREAD_UNCHANGED)
        if img is None or dep is None:
            raise CliError(f'{c if img is None else d}: not a readable image')
        if dep.dtype != np.uint16 or dep.ndim != 2:
            raise CliError(f'{d}: expected a 16-bit single-channel PNG (millimetres), got '
                           f'{dep.dtype} with shape {dep.shape}')
        if img.shape[:2] != dep.shape or img.shape[:2] != cv2.imread(
                str(names['color'][0]), cv2.IMREAD_COLOR).shape[:2]:
            raise CliError(f'{c}: size {img.shape[:2]} differs from its depth {dep.shape} or '
                           'from the first frame')
        colors.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
        depths.append(dep)
    return colors, depths, K


def cmd_scene_flow(args: argparse.Namespace) -> int:
    from .core.sceneflow.msf import MSFConfig, dis_depth_flow, msf_sequence
    if args.segments < 1:
        raise CliError(f'--segments {args.segments}: expected >= 1')
    if not (np.isfinite(args.depth_scale) and args.depth_scale > 0):
        raise CliError(f'--depth-scale {args.depth_scale}: expected > 0 (units per metre)')
    colors, depths, K = read_rgbd_folder(Path(args.rgbd))
    depths = [np.where(d > 0, d.astype(np.float32) / np.float32(args.depth_scale), np.nan)
              .astype(np.float32) for d in depths]
    if args.method == 'dis':
        flow, valid, st = dis_depth_flow(colors, depths, K)
    else:
        cfg = MSFConfig(segments=args.segments)
        if args.method == 'icp':
            cfg = MSFConfig(segments=args.segments, photometric_weight=0.0, smoothness=0.0)
        flow, valid, st = msf_sequence(colors, depths, K, cfg)
    np.savez_compressed(args.out, flow=flow, valid=valid, K=K)
    print(f'wrote {args.out}: flow {flow.shape} m ({args.method}), '
          f'{100 * valid.mean():.1f}% valid, {st["seconds_per_frame"]:.3f} s/frame')
    for i, err in st.get('skipped', []):
        print(f'frame {i} not processed (flow NaN, not valid): {err}')
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    if not args.rate > 0:
        raise CliError(f'--rate {args.rate}: must be > 0')
    if not 0 <= args.port <= 65535:
        raise CliError(f'--port {args.port}: expected 0..65535 (0: any free port)')
    if args.bag is None and (args.loop or args.rate != 1.0):
        raise CliError('--rate and --loop play a bag: name the BAG')
    try:
        from .view import serve
    except ImportError as err:
        raise CliError(f'view needs the foxglove-sdk package (pip install foxglove-sdk; '
                       f'{_one_line(err)})') from err
    serve(args.bag, args.host, args.port, args.rate, args.loop,
          out=lambda line: print(line, flush=True))
    return 0


# verb -> the function that runs it (every verb of _parser; test_params_vocabulary checks)
VERBS: dict[str, Callable[[argparse.Namespace], int]] = {
    'demo': cmd_demo,
    'synth': cmd_synth,
    'record': cmd_record,
    'replay': cmd_replay,
    'process': cmd_process,
    'topic': cmd_topic,
    'export': cmd_export,
    'evaluate': cmd_evaluate,
    'track': cmd_track,
    'reconstruct': cmd_reconstruct,
    'train-hdmnet': cmd_train_hdmnet,
    'reconstruct-image': cmd_reconstruct_image,
    'register': cmd_register,
    'scene-flow': cmd_scene_flow,
    'view': cmd_view,
}


if __name__ == '__main__':
    sys.exit(main())
