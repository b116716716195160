"""One parameter vocabulary (issue 19): every node parameter that reaches the core has the core's
default (or an entry in params.NODE_DEFAULTS saying why not), and the node's checks accept
exactly what the core accepts, probed at and around every boundary through the same calls the
processors make; dispatch goes through explicit tables
(no names built at run time) and the node code names its constants."""
from __future__ import annotations

import dataclasses
import inspect
import math
import re
from pathlib import Path

import numpy as np
import pytest

from nrsfm_ros import cli, params
from nrsfm_ros.core.registration import register
from nrsfm_ros.core.sceneflow.msf import MSF, MSFConfig
from nrsfm_ros.core.sceneflow.nrsfm_flow import object_poses
from nrsfm_ros.core.tracking import MASKS, PRESETS, MFOFConfig, ReferenceFlowTracker
from nrsfm_ros.io.msgtypes import RosbagsFactory
from nrsfm_ros.core.registration.rays import ray_pose
from nrsfm_ros.params import (NODE_DEFAULTS, ReconstructorParams, RegistrarParams,
                              SceneFlowParams, TrackerParams)
from nrsfm_ros.processing import (ReconstructorProcessor, RegistrarProcessor,
                                  SceneFlowProcessor, TrackerProcessor, make_stream,
                                  registration_kwargs)

ROOT = Path(__file__).resolve().parent.parent
FACTORY = RosbagsFactory()


def signature_defaults(fn) -> dict:
    return {k: p.default for k, p in inspect.signature(fn).parameters.items()
            if p.default is not inspect.Parameter.empty}


def config_defaults(cls) -> dict:
    inst = cls()
    return {f.name: getattr(inst, f.name) for f in dataclasses.fields(cls)}


# node -> [(core defaults, {node parameter: core name})]: the core function or config each
# parameter is handed to (the node's default method: mfof, icp)
_ICP = signature_defaults(register.__globals__['icp'])
_CPD = signature_defaults(register.__globals__['cpd'])
_TRACKER = {f.name for f in dataclasses.fields(TrackerParams)}
CORE = {
    'tracker': [(config_defaults(MFOFConfig), {n: n for n in config_defaults(MFOFConfig)
                                               if n in _TRACKER}),
                (signature_defaults(ReferenceFlowTracker),
                 {n: n for n in signature_defaults(ReferenceFlowTracker) if n in _TRACKER})],
    'registrar': [
        (_ICP, {n: n for n in ('max_iterations', 'max_points', 'tolerance', 'trim', 'voxel',
                               'init', 'inlier_threshold')}),
        (_CPD, {n: n for n in ('w', 'beta', 'lam')}),
        (signature_defaults(ray_pose), {'depth_weight': 'depth_weight'})],
    'reconstructor': [
        (signature_defaults(make_stream.__globals__['StreamNRSfM']),
         {n: n for n in ('mode', 'window', 'rank', 'iterations', 'method', 'batch_frames',
                         'projection', 'dspr_recurrence_px', 'dspr_distinct',
                         'dspr_prior_weight')})],
    'scene_flow': [
        (signature_defaults(object_poses), {'iterations': 'iterations', 'softness': 'softness',
                                            'pose_points': 'max_points'}),
        (config_defaults(MSFConfig), {'segments': 'segments'})],
}


def disagreements(node: str) -> dict[str, tuple]:
    cls = params.NODE_PARAMS[node]
    ours = cls()
    out = {}
    for core, names in CORE[node]:
        for name, core_name in names.items():
            assert name in {f.name for f in dataclasses.fields(cls)}, f'{node}: no {name}'
            if getattr(ours, name) != core[core_name]:
                out[name] = (getattr(ours, name), core[core_name])
    return out


@pytest.mark.parametrize('node', sorted(CORE))
def test_defaults_are_the_cores(node):
    found = disagreements(node)
    declared = {name for (n, name) in NODE_DEFAULTS if n == node}
    undeclared = {k: v for k, v in found.items() if k not in declared}
    assert not undeclared, f'{node}: defaults (node, core) that disagree: {undeclared}'
    stale = declared - set(found)
    assert not stale, f'{node}: params.NODE_DEFAULTS entries that agree with the core: {stale}'


def test_tracker_defaults_are_one_set():
    """Both trackers share preset, stride, mask and min_std defaults with the node."""
    ref = signature_defaults(ReferenceFlowTracker)
    mfof = config_defaults(MFOFConfig)
    for name in ('preset', 'stride', 'mask', 'min_std'):
        assert ref[name] == mfof[name] == getattr(TrackerParams(), name), name


# ------------------------------------------------------------------ ranges, probed

def probes(value, choices=()) -> list:
    """Values at and around every boundary the rules use, of the parameter's type."""
    if isinstance(value, bool):
        return []
    if isinstance(value, int):
        return sorted({-1, 0, 1, 2, 3, 4, value, value + 1})
    if isinstance(value, float):
        return [-1.0, -1e-9, 0.0, 1e-9, 0.0999, 0.1, 0.5, 0.999, 1.0, 1.001, 2.0, 3.0, value,
                math.nan, math.inf, -math.inf]
    return sorted({value, *choices, 'bogus', ''})


def params_accept(cls, base, name, v) -> bool:
    try:
        base.updated({name: v})
        return True
    except ValueError:
        return False


def core_accepts(make) -> bool:
    try:
        make()
        return True
    except ValueError:
        return False


def compare(cls, base, name, choices, make) -> list[str]:
    bad = []
    for v in probes(getattr(base, name), choices):
        ours = params_accept(cls, base, name, v)
        theirs = core_accepts(lambda: make(dataclasses.replace(base, **{name: v})))
        if ours != theirs:
            bad.append(f'{name}={v!r}: node {"accepts" if ours else "rejects"}, core '
                       f'{"accepts" if theirs else "rejects"}')
    return bad


TRACKER_FIELDS = {
    'mfof': ['preset', 'recapture_finest_scale', 'stride', 'mask', 'min_std', 'rank',
             'window', 'refine_every', 'subspace_weight', 'spatial_sigma', 'backward_preset',
             'fb_threshold', 'ncc_threshold', 'recapture_margin', 'outlier_px',
             'reselect_fraction', 'collapse_fraction', 'reselect_patience'],
    'reference': ['preset', 'stride', 'mask', 'min_std', 'occlusion_threshold'],
}


@pytest.mark.parametrize('method', sorted(TRACKER_FIELDS))
def test_tracker_ranges_are_the_cores(method):
    base = TrackerParams(method=method)
    choices = {'preset': PRESETS, 'backward_preset': PRESETS, 'mask': MASKS}
    bad = []
    for name in TRACKER_FIELDS[method]:
        bad += compare(TrackerParams, base, name, choices.get(name, ()),
                       lambda p: TrackerProcessor(FACTORY, p))
    assert not bad, bad


def _clouds(n: int = 40, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, 3))
    c, s = np.cos(0.2), np.sin(0.2)
    return X @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + 0.1, X


REGISTRAR_FIELDS = {
    'icp': ['max_iterations', 'max_points', 'tolerance', 'trim', 'voxel', 'init',
            'inlier_threshold'],
    'cpd-nonrigid': ['max_iterations', 'max_points', 'tolerance', 'w', 'beta', 'lam',
                     'inlier_threshold'],
}


@pytest.mark.parametrize('method', sorted(REGISTRAR_FIELDS))
def test_registrar_ranges_are_the_cores(method):
    src, dst = _clouds()
    base = RegistrarParams(method=method, max_iterations=5)
    choices = {'init': ('centroid', 'global', 'identity')}

    def make(p):
        return register(src, dst, method=p.method, **registration_kwargs(p))
    bad = []
    for name in REGISTRAR_FIELDS[method]:
        bad += compare(RegistrarParams, base, name, choices.get(name, ()), make)
    assert not bad, bad


def test_registrar_match_track_id_ranges_are_the_cores():
    """depth_weight, max_iterations, max_points, tolerance as the ray pose takes them."""
    src, dst = _clouds()
    base = RegistrarParams()

    def make(p):
        return ray_pose(src + [0, 0, 10], dst, 0.1, depth_weight=p.depth_weight,
                        max_iterations=p.max_iterations, tolerance=p.tolerance,
                        max_points=p.max_points)
    bad = []
    for name in ('depth_weight', 'max_iterations', 'max_points', 'tolerance'):
        bad += compare(RegistrarParams, base, name, (), make)
    assert not bad, bad


def test_reconstructor_ranges_are_the_cores():
    base = ReconstructorParams()
    bad = []
    for name in ('window', 'rank', 'iterations', 'batch_frames', 'projection',
                 'dspr_recurrence_px', 'dspr_distinct', 'dspr_prior_weight'):
        bad += compare(ReconstructorParams, base, name, ('weak', 'perspective'), make_stream)
    assert not bad, bad


# ------------------------------------------------------------------ the reconstructor's choices

def _face_tracks(frames: int = 8):
    from nrsfm_ros.io.synth import dense_tracks
    d = dense_tracks('face', frames=frames, points=80, projection='orthographic',
                     camera_motion_deg=30)
    return d, np.arange(d['W'].shape[1])


def _run(stream, d, ids) -> list:
    out = []
    for f in range(d['V'].shape[0]):
        out += stream.push(ids, d['W'][2 * f:2 * f + 2].T, d['V'][f])
    return out + stream.flush()


def test_reconstructor_choices_are_the_cores():
    """mode and method allow exactly the core's names (hdmnet: the node's own mode, per image):
    the same tuples, and each value of the node's runs in the core (a shape per frame; a method
    solves its batch itself, no fallback)."""
    from nrsfm_ros.core.nrsfm import METHODS
    from nrsfm_ros.core.nrsfm.stream import BATCH_METHODS, MODES, StreamNRSfM
    modes = params.choices(ReconstructorParams, 'mode')
    methods = params.choices(ReconstructorParams, 'method')
    assert set(modes) == {*MODES, 'hdmnet'} and set(methods) == set(BATCH_METHODS)
    assert set(methods) - {'auto'} <= set(METHODS)
    d, ids = _face_tracks()
    for m in methods:
        p = ReconstructorParams().updated({'mode': 'batch', 'method': m, 'batch_frames': 8,
                                           'projection': 'weak'})
        s = make_stream(p)
        assert len(_run(s, d, ids)) == 8, m
        assert not s.fallbacks, (m, s.fallbacks)
        assert s.last_method == m if m != 'auto' else s.last_method in ('planar', 'bmm', 'rigid', 'lowrank')
    for m in modes:
        p = ReconstructorParams().updated({'mode': m, 'window': 4, 'batch_frames': 8,
                                           'spva_prior_frames': 4})
        proc = ReconstructorProcessor(FACTORY, p)
        if m == 'hdmnet':              # no stream of tracks: the model, per image
            assert proc.hdmnet is not None and proc.stream.mode == 'batch'
            with pytest.raises(ValueError, match="mode='hdmnet'"):
                StreamNRSfM(mode='hdmnet')
            continue
        assert proc.stream.mode == m
        assert len(_run(proc.stream, d, ids)) == 8, m


@pytest.mark.parametrize('name', ['mode', 'method'])
def test_reconstructor_unknown_choice_names_field_and_value(name, rclpy_context):
    """An unknown mode or method is refused by the parameters, the core and the node, each
    naming the field and the value."""
    from nrsfm_ros.core.nrsfm.stream import StreamNRSfM
    from nrsfm_ros.nodes.common import ProcessorNode
    text = f"{name}='bogus'"
    with pytest.raises(ValueError, match=text):
        ReconstructorParams().updated({name: 'bogus'})
    with pytest.raises(ValueError, match=text):
        StreamNRSfM(**{name: 'bogus'})
    with pytest.raises(ValueError, match=text):
        ReconstructorProcessor(FACTORY, dataclasses.replace(ReconstructorParams(),
                                                            **{name: 'bogus'}))
    node = ProcessorNode('reconstructor', ReconstructorProcessor,
                         [('points', 'sensor_msgs/msg/PointCloud2')], context=rclpy_context)
    try:
        from rclpy.parameter import Parameter
        bad = node.set_parameters([Parameter(name, value='bogus')])[0]
        assert not bad.successful and text in bad.reason, bad.reason
        assert getattr(node.processor.params, name) == getattr(ReconstructorParams(), name)
        for v in params.choices(ReconstructorParams, name):
            ok = node.set_parameters([Parameter(name, value=v)])[0]
            assert ok.successful, (v, ok.reason)
            assert getattr(node.processor.params, name) == v
    finally:
        node.destroy_node()


def test_scene_flow_ranges_are_the_cores():
    rng = np.random.default_rng(1)
    X = rng.normal(size=(30, 3))
    ids = np.arange(30)
    window = [(X, ids), (X + 0.01, ids), (X + 0.02, ids)]
    base = SceneFlowParams()
    K = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
    bad = []
    for name, make in (
            ('iterations', lambda p: object_poses(window, iterations=p.iterations,
                                                  softness=p.softness,
                                                  max_points=p.pose_points)),
            ('warm_iterations', lambda p: object_poses(window, iterations=p.warm_iterations)),
            ('softness', lambda p: object_poses(window, softness=p.softness)),
            ('pose_points', lambda p: object_poses(window, max_points=p.pose_points)),
            ('segments', lambda p: MSF(K, MSFConfig(segments=p.segments)))):
        bad += compare(SceneFlowParams, base, name, (), make)
    assert not bad, bad


def test_the_processors_hand_the_node_parameters_to_the_core():
    """What the probes rely on: the processors build their core objects from these values."""
    p = TrackerParams(stride=3, mask='full', rank=5, outlier_px=1.5)
    cfg = TrackerProcessor(FACTORY, p).tracker.config
    assert (cfg.stride, cfg.mask, cfg.rank, cfg.outlier_px) == (3, 'full', 5, 1.5)
    ref = TrackerProcessor(FACTORY, dataclasses.replace(p, method='reference',
                                                        occlusion_threshold=9.0)).tracker
    assert (ref.stride, ref.mask_mode, ref.occlusion_threshold) == (3, 'full', 9.0)
    s = ReconstructorProcessor(FACTORY, ReconstructorParams(window=7, rank=3)).stream
    assert (s.window, s.rank) == (7, 3)
    kw = registration_kwargs(RegistrarParams(trim=0.5, max_points=0, init='global'))
    assert (kw['trim'], kw['max_points'], kw['init']) == (0.5, 0, 'global')
    from nrsfm_ros.processing import ALL_POINTS
    kw = registration_kwargs(RegistrarParams(method='cpd-rigid', max_points=0))
    assert kw['max_points'] == ALL_POINTS and 'trim' not in kw
    assert SceneFlowProcessor(FACTORY).params == SceneFlowParams()


# ------------------------------------------------------------------ explicit tables

def test_every_verb_is_in_the_dispatch_table():
    import argparse
    sub = next(a for a in cli._parser()._actions if isinstance(a, argparse._SubParsersAction))
    assert set(cli.VERBS) == set(sub.choices)
    for verb, fn in cli.VERBS.items():
        assert fn.__name__ == 'cmd_' + verb.replace('-', '_')


@pytest.mark.parametrize('cls', [TrackerProcessor, ReconstructorProcessor, RegistrarProcessor,
                                 SceneFlowProcessor], ids=lambda c: c.name)
def test_every_input_handler_is_in_the_table(cls):
    proc = cls(FACTORY)
    table = proc.handlers()
    methods = {n[3:] for n in dir(cls) if n.startswith('on_')}
    assert set(table) == methods
    for kind, fn in table.items():
        assert fn.__func__ is getattr(cls, 'on_' + kind)


def test_an_unknown_input_kind_is_a_clear_error():
    with pytest.raises(ValueError, match=r"registrar: no input 'tracks' \(inputs: \['points', "
                                         r"'reference'\]\)"):
        RegistrarProcessor(FACTORY).handle('tracks', object())


def test_no_name_built_dispatch_or_magic_numbers_in_node_code():
    code = {p: p.read_text() for d in ('nrsfm_ros', 'nrsfm_ros/nodes')
            for p in (ROOT / d).glob('*.py')}
    for path, text in code.items():
        for pattern in (r"getattr\(self, f['\"]on_", r"globals\(\)\[", r'10 \*\* 9\)',
                        r'type=\d+, action=\d+'):
            assert not re.search(pattern, text), f'{path.name}: {pattern}'


def test_track_verb_takes_the_node_parameters(tmp_path, capsys):
    import cv2
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 255, (48, 64)).astype(np.uint8), (0, 0), 1.5)
    for k in range(3):
        cv2.imwrite(str(tmp_path / f'{k:02d}.png'), np.roll(img, k, axis=1))
    capsys.readouterr()
    assert cli.main(['track', str(tmp_path), '--stride', '0', '--out',
                     str(tmp_path / 't.npz')]) == 2
    assert 'stride=0: must be >= 1' in capsys.readouterr().err
    assert cli.main(['track', str(tmp_path), '--method', 'reference', '--mask', 'full',
                     '--stride', '4', '--out', str(tmp_path / 't.npz')]) == 0
    d = np.load(tmp_path / 't.npz')
    assert d['W'].shape == (6, 12 * 16)       # every 4th pixel of 64 x 48, all of them
    assert cli.main(['track', str(tmp_path), '--out', str(tmp_path / 'd.npz')]) == 0
    n_default = np.load(tmp_path / 'd.npz')['W'].shape[1]
    assert 0 < n_default <= 24 * 32           # stride 2 (the node's default), texture mask


def test_cli_defaults_are_the_cores():
    """Flags left unset mean what the core (or the node) means: synth's are SynthConfig's,
    scene-flow's segments the node's (= MSFConfig's), register's help quotes icp's and cpd's."""
    from nrsfm_ros.io.synth import SynthConfig
    parser = cli._parser()
    a = parser.parse_args(['synth', '--out', 'x'])
    sc = SynthConfig()
    assert cli._size(a.size) == (sc.width, sc.height)
    assert (a.surface, a.frames, a.fps, a.seed, a.noise, a.camera_motion, a.amplitude,
            a.distance, a.periodic, a.stride, a.occluder) == (
        sc.surface, sc.frames, sc.fps, sc.seed, sc.noise, sc.camera_motion_deg, sc.amplitude,
        sc.distance, sc.period_frames, sc.stride, sc.occluder)
    a = parser.parse_args(['scene-flow', 'd', '--out', 'x'])
    assert a.segments == SceneFlowParams().segments == MSFConfig().segments
    a = parser.parse_args(['track', 'd', '--out', 'x'])
    assert all(getattr(a, k) is None for k in cli.TRACK_FLAGS)     # TrackerParams decides
    sub = next(x for x in parser._actions if hasattr(x, 'choices') and
               isinstance(x.choices, dict)).choices
    text = ' '.join(sub['register'].format_help().split())
    for flag, value in (('trim', _ICP['trim']), ('w', _CPD['w']), ('init', _ICP['init'])):
        assert f'(default {value:g}' in text if not isinstance(value, str) else \
            f'(default {value})' in text, flag
