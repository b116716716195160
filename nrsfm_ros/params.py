"""Parameter sets of the four nodes: one vocabulary for the core, the YAML files in config/,
the ROS parameters and the CLI.  Each field has a default and a validator that gives a reason."""
from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from .core.registration.base import PARAM_RULES as _REG
from .core.nrsfm.stream import BATCH_METHODS, MODES
from .core.tracking import PARAM_RULES as _TRK
from .core.tracking import MFOFConfig, ReferenceFlowTracker

# the tracker's defaults are the core's: MFOFConfig's, and ReferenceFlowTracker's for what only
# the reference method takes; the checks are core.tracking.PARAM_RULES
_MFOF = MFOFConfig()
_REF_TRACKER = {k: p.default for k, p in
                inspect.signature(ReferenceFlowTracker).parameters.items()}
TRACKER_METHODS = ('mfof', 'reference')
# the stream's modes, and hdmnet: the node's own (per image, no tracks)
RECONSTRUCTOR_MODES = (*MODES, 'hdmnet')

# Defaults a node sets on purpose apart from the core function it calls (test/
# test_params_vocabulary.py fails on any other disagreement, and on an entry here that agrees).
NODE_DEFAULTS = {
    ('registrar', 'max_iterations'): 'icp() 50: a live budget per cloud (30 converge on '
                                     'consecutive clouds, warm-started)',
    ('registrar', 'max_points'): 'icp() 5000: a live budget per cloud (1000 evenly strided '
                                 'source points; the transform moves all)',
    ('reconstructor', 'mode'): "StreamNRSfM 'window': the node's default is the most accurate "
                               'mode on the pipeline benchmark',
    ('reconstructor', 'projection'): "StreamNRSfM 'weak': the node refines batch solves for "
                                     'the perspective camera of CameraInfo',
    ('scene_flow', 'pose_points'): 'object_poses() max_points 0 (all): the ego-motion on 2000 '
                                   'tracks costs half the CPU of all 6k at the same accuracy',
}


def _one_of(*values: str) -> Callable[[Any], str | None]:
    def check(v: Any) -> str | None:
        return None if v in values else f'expected one of {list(values)}'
    check.choices = values          # type: ignore[attr-defined]
    return check


def choices(cls: type, name: str) -> tuple[str, ...]:
    """The values a one-of parameter ``name`` of ``cls`` allows."""
    return next(f for f in fields(cls) if f.name == name).metadata['rule'].choices


def _frame_id(v: Any) -> str | None:
    ok = isinstance(v, str) and v != '' and not v.startswith('/') and ' ' not in v
    return None if ok else 'expected a non-empty frame id without a leading / or spaces'


def _positive(v: Any) -> str | None:
    return None if v > 0 and math.isfinite(v) else 'must be a finite number > 0'


def _non_negative(v: Any) -> str | None:
    return None if v >= 0 and math.isfinite(v) else 'must be a finite number >= 0'


def _at_least(n: float) -> Callable[[Any], str | None]:
    return lambda v: None if v >= n else f'must be >= {n}'


def _unit(v: Any) -> str | None:
    return None if 0 < v <= 1 else 'must be in (0, 1]'


def _unit_or_zero(v: Any) -> str | None:
    return None if 0 <= v <= 1 else 'must be in [0, 1]'


@dataclass(frozen=True)
class Params:
    """Base: ``validate`` returns a list of (name, reason); ``updated`` validates a change."""

    def check(self) -> list[tuple[str, str]]:
        errors = []
        for f in fields(self):
            rule = f.metadata.get('rule') if f.metadata else None
            value = getattr(self, f.name)
            if rule is not None:
                reason = rule(value)
                if reason:
                    errors.append((f.name, f'{f.name}={value!r}: {reason}'))
        return errors

    def updated(self, changes: Mapping[str, Any]) -> Params:
        unknown = set(changes) - {f.name for f in fields(self)}
        if unknown:
            raise ValueError(f'unknown parameter(s): {sorted(unknown)}')
        new = replace(self, **{k: _typed(k, v, getattr(self, k)) for k, v in changes.items()})
        errors = new.check()
        if errors:
            raise ValueError('; '.join(reason for _, reason in errors))
        return new

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def _typed(name: str, value: Any, current: Any) -> Any:
    """``value`` as the type of the parameter (an int is a valid float), else a ValueError."""
    kind = type(current)
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, kind) and (kind is bool or not isinstance(value, bool)):
        return value
    raise ValueError(f'{name}={value!r}: expected a {kind.__name__}, got a '
                     f'{type(value).__name__}')


def rule(default: Any, check: Callable[[Any], str | None] | None = None,
         doc: str = '') -> Any:
    from dataclasses import field
    return field(default=default, metadata={'rule': check, 'doc': doc})


def _queue_size(extra: str = '') -> Any:
    return rule(0, _at_least(0), 'live: messages each input subscription may hold while the '
                'node is busy; 0: by the input\'s QoS, 1 on a best-effort (camera-rate) input, '
                'so that its latency stays bounded when the node cannot keep up, 64 on a '
                'reliable one' + extra)


def _queue_policy() -> Any:
    return rule('keep_latest', _one_of('keep_latest', 'keep_all'),
                'live: a full input queue discards its oldest message (keep_latest; counted '
                'as dropped on /diagnostics) or holds the subscription until there is room '
                '(keep_all: reliable publishers are slowed instead)')


@dataclass(frozen=True)
class TrackerParams(Params):
    method: str = rule('mfof', _one_of(*TRACKER_METHODS),
                       'mfof: multi-frame subspace flow with occlusion tensor; reference: '
                       'plain DIS reference->frame seeded by the previous frame')
    preset: str = rule(_MFOF.preset, _TRK['preset'], 'OpenCV DIS preset of the flow data step')
    stride: int = rule(_MFOF.stride, _TRK['stride'], 'track every stride-th reference pixel')
    downsample: int = rule(1, _at_least(1), 'track on the image shrunk by this factor (area '
                           'average; 2: ~3x less CPU at 640x480, about twice the median track '
                           'error); u, v in full-image pixels, stride counted in full-image '
                           "pixels, track_id naming the block's first full-image pixel")
    mask: str = rule(_MFOF.mask, _TRK['mask'], 'which reference pixels to track')
    min_std: float = rule(_MFOF.min_std, _TRK['min_std'],
                          'texture mask: local intensity std threshold')
    roi_mask: bool = rule(False, None, 'track only the surface a segmentation gives: the '
                          'camera/mask image (mono8, nonzero: the surface) of each image\'s '
                          'stamp, else the latest received; what lies outside it is blacked '
                          'out before the flow, and a new reference tracks the mask eroded by '
                          'roi_margin; images before the first mask are skipped and counted')
    roi_margin: int = rule(2, _at_least(0), 'roi_mask: px (of the input image) taken off the '
                           "mask's edge for a new reference's tracks")
    rank: int = rule(_MFOF.rank, _TRK['rank'], 'mfof: learned trajectory-basis images (plus 6 '
                     'polynomial ones)')
    window: int = rule(_MFOF.window, _TRK['window'],
                       'mfof: frames in the subspace refinement window')
    refine_every: int = rule(_MFOF.refine_every, _TRK['refine_every'],
                             'mfof: re-fit the subspace every N frames')
    subspace_weight: float = rule(_MFOF.subspace_weight, _TRK['subspace_weight'],
                                  'mfof: pull of the subspace on visible pixels (occluded ones '
                                  'follow it fully)')
    spatial_sigma: float = rule(_MFOF.spatial_sigma, _TRK['spatial_sigma'],
                                'mfof: smoothing of the basis images (px)')
    backward_preset: str = rule(_MFOF.backward_preset, _TRK['backward_preset'],
                                'mfof: DIS preset of the backward flow for the forward-backward '
                                'check')
    fb_threshold: float = rule(_MFOF.fb_threshold, _TRK['fb_threshold'],
                               'mfof: forward-backward error (px) at occlusion probability 1/2')
    ncc_threshold: float = rule(_MFOF.ncc_threshold, _TRK['ncc_threshold'],
                                'mfof: 1 - local ZNCC of the reference and the aligned frame at '
                                'occlusion probability 1/2')
    recapture_margin: float = rule(_MFOF.recapture_margin, _TRK['recapture_margin'],
                                   'mfof: a second DIS pass on the frame '
                                   'itself, seeded by the prediction, replaces the residual flow '
                                   'where its local 1 - ZNCC is lower by this much (lost tracks '
                                   'found again on foreshortened views; 0: off)')
    recapture_finest_scale: int = rule(
        _MFOF.recapture_finest_scale, _TRK['recapture_finest_scale'],
        "mfof: DIS's finest pyramid level of the recapture pass (-1: the preset's own below "
        '640 px on the long side of the tracked image, one level coarser per doubling from '
        'there: 640x480 tracks at ~1.25x the frame rate, the same track error)')
    chain_check_px: float = rule(_MFOF.chain_check_px, _TRK['chain_check_px'],
                                 'mfof: a track is reported not visible where its position '
                                 'and its previous one moved by a frame-to-frame flow differ '
                                 'by more than this (px; catches a flow drifting off a surface '
                                 'whose occlusion checks still pass; 0: off)')
    support_radius: int = rule(_MFOF.support_radius, _TRK['support_radius'],
                               'mfof: the neighbourhood (px of the input image) of the '
                               'visibility support check (0: off)')
    support_fraction: float = rule(_MFOF.support_fraction, _TRK['support_fraction'],
                                   'mfof: a track is reported not visible where less than this '
                                   'share of its reference neighbourhood is visible (tracks '
                                   'dragged by an occluder or slid off a surface turning away)')
    lk_radius: int = rule(_MFOF.lk_radius, _TRK['lk_radius'],
                          'mfof: each visible track refined against the reference by affine '
                          'Lucas-Kanade on a (2r+1)^2 template (px of the tracked image, '
                          'after downsample; 0: off)')
    lk_iterations: int = rule(_MFOF.lk_iterations, _TRK['lk_iterations'],
                              'mfof: Gauss-Newton iterations of the Lucas-Kanade refinement')
    fusion_gap_px: float = rule(_MFOF.fusion_gap_px, _TRK['fusion_gap_px'],
                                'mfof: a track is reported not visible where its published '
                                'position (the data fused with the motion subspace) is more '
                                'than this from the frame\'s own flow measurement (px of the '
                                'tracked image; 0: off)')
    predict_offset: bool = rule(_MFOF.predict_offset, None,
                                'mfof: the data step starts each pixel at its own '
                                'last position moved by the subspace (off: the smooth subspace '
                                'prediction alone; strong deformation is lost on fast folds)')
    outlier_px: float = rule(_MFOF.outlier_px, _TRK['outlier_px'],
                             'mfof: data further than this from the subspace loses weight '
                             '(0: off)')
    reselect_fraction: float = rule(_MFOF.reselect_fraction, _TRK['reselect_fraction'],
                                    'mfof: new reference when less of it stays in view')
    collapse_fraction: float = rule(_MFOF.collapse_fraction, _TRK['collapse_fraction'],
                                    'mfof: ... or less of the in-view part stays consistent')
    reselect_patience: int = rule(_MFOF.reselect_patience, _TRK['reselect_patience'],
                                  'mfof: ... for this many frames in a row')
    occlusion_threshold: float = rule(_REF_TRACKER['occlusion_threshold'],
                                      _TRK['occlusion_threshold'],
                                      'reference: photometric residual for visibility 0')
    publish_flow: bool = rule(True, None, 'publish the dense flow image')
    reliable: bool = rule(False, None, 'reliable QoS on the camera input (default best effort)')
    queue_size: int = _queue_size()
    queue_policy: str = _queue_policy()

    def mfof_config(self):
        from .core.tracking.mfof import MFOFConfig
        names = {f.name for f in fields(MFOFConfig)}
        return MFOFConfig(**{k: v for k, v in self.as_dict().items() if k in names})


@dataclass(frozen=True)
class ReconstructorParams(Params):
    mode: str = rule('batch', _one_of(*RECONSTRUCTOR_MODES),
                     'batch: batch_frames frames at a time with method (the most accurate on '
                     'the pipeline benchmark); window: sliding window re-solved per frame '
                     '(lowest latency); online: the first window, then each frame fitted alone '
                     'to its shape basis; dspr: the first batch as batch, then each frame '
                     'matched against a dynamic shape prior of distinct states (a recurring '
                     'state stored as camera + index: compression; else a per-frame energy, '
                     'the new shape joining the prior); spva: the first batch as batch, a '
                     'shape prior from its least-occluded frames, then each frame by the '
                     'variational energy (visible tracks, Huber-TV on the track grid, the '
                     "batch's shape subspace) plus the prior weighted by the occlusion; "
                     'hdmnet: no tracks, each camera image '
                     'alone through the learned HDM-Net (a 73 x 73 grid of a thin sheet-like '
                     'surface in metres, every frame; track_id = grid node)')
    method: str = rule('auto', _one_of(*BATCH_METHODS),
                       'NRSfM method in batch mode (auto: planar when the rest shape tests '
                       'planar, else bmm, or where bmm explains too little or the cameras '
                       'turn too little the rigid shape as the start of a rank-K basis; '
                       'window and online modes run the rank-K alternation)')
    window: int = rule(15, _at_least(3), 'frames per sliding window')
    batch_frames: int = rule(60, _at_least(3), 'frames per batch (batch mode; dspr: the '
                             'batch the prior is built from) where batch_seconds is 0 or the '
                             'frame rate unknown')
    batch_seconds: float = rule(6.0, _at_least(0), 'batch modes: a batch spans this much of '
                                'the stream, its frames from the frame rate of the first '
                                'tracks\' stamps (60 at 10 frames/s, 180 at 30; 3..300), and '
                                'batch_context keeps its share of batch_frames; 0: '
                                'batch_frames as given')
    batch_context: int = rule(30, _at_least(0), 'batch mode: each batch after the first is '
                              'solved with up to this many frames before it that share its '
                              'tracks (published already: context only, for the camera motion '
                              'before the batch), and the last partial batch with the frames '
                              'before it up to batch_frames; 0: every batch alone')
    min_seen: float = rule(0.7, _unit_or_zero, 'batch and dspr: a track enters a batch solve, '
                           'and its clouds, where the tracker saw it (visibility >= 0.5) in at '
                           'least this share of the batch frames that report it: one lost most '
                           'of the time (a textured background sliding behind the surface, '
                           'the rim) has depths the batch does not observe; the status '
                           'tracks_left_out counts them (0: every track seen in 2 frames); '
                           'spva: at most 0.3 of them (its prior fills what an occluder '
                           'hides), none where most tracks are seen in few frames')
    rank: int = rule(2, _at_least(1), "shape basis rank K (window mode, lowrank, auto's "
                     'rigid basis in batch mode)')
    iterations: int = rule(10, _at_least(1), 'alternation iterations per window (warm-started)')
    projection: str = rule('perspective', _one_of('perspective', 'weak'),
                           'camera model of batch solves: perspective (with CameraInfo: the '
                           'weak-perspective solution refined by affine iterations, kept only '
                           'where it reprojects better) or weak (weak perspective); window and '
                           'online modes are weak perspective')
    dspr_recurrence_px: float = rule(0.0, _non_negative,
                                     'dspr: RMS reprojection residual (px) under which a frame '
                                     'is a recurrence of a prior state (0: 1.5 x the first '
                                     "batch's residual, at least 0.75 px; 3 x where the batch "
                                     "was auto's rigid basis)")
    dspr_distinct: float = rule(0.0, _non_negative,
                                'dspr: shape distance (sine of the angle after Procrustes) '
                                'above which a shape is a new state (merges the batch, grows '
                                "the prior; 0: half the first batch's mean distance from its "
                                'first shape)')
    dspr_prior_weight: float = rule(0.01, _positive,
                                    'dspr: weight of the closeness to the prior states against '
                                    'the data term (px^2) in the per-frame energy')
    spva_prior_frames: int = rule(10, _at_least(1),
                                  'spva: least-occluded frames of the first batch (total '
                                  'occlusion sum_p (1 - visibility)) the shape prior is the '
                                  'mean of; at most batch_frames')
    spva_weighting: str = rule('pixel', _one_of('pixel', 'frame', 'sequence'),
                               "spva: the prior term's weight: pixel (each track's occlusion "
                               "1 - visibility), frame (the frame's mean occlusion) or sequence "
                               '(1 everywhere)')
    spva_prior_weight: float = rule(10.0, _non_negative,
                                    'spva: weight of the prior term against the data term '
                                    '(0: no prior, the variational energy alone)')
    spva_smoothness: float = rule(0.05, _non_negative,
                                  'spva: weight of the Huber total variation of the shape on '
                                  'the track grid (px per edge)')
    spva_refresh: float = rule(0.0, _unit_or_zero,
                               'spva: rate at which the prior follows the visible tracks\' '
                               'shapes after each frame (0: fixed prior)')
    spva_iterations: int = rule(10, _at_least(1),
                                'spva: ADMM iterations per frame, warm-started from the '
                                'previous frame\'s duals (the per-frame latency: about linear '
                                'in them)')
    hdmnet_model: str = rule('', None, 'hdmnet: ONNX model file (empty: the shipped '
                             'nrsfm_ros/models/hdmnet.onnx)')
    hdmnet_threads: int = rule(2, _at_least(1), 'hdmnet: ONNX Runtime threads')
    mean_depth: float = rule(4.0, _positive, 'distance to the surface centroid (m) over the '
                             'first solve\'s frames: the global scale of the metric output, '
                             'which one camera cannot observe (each frame\'s depth follows '
                             'its weak-perspective scale)')
    object_frame: str = rule('nrsfm_object', _frame_id, 'child frame of nrsfm/object_pose '
                             '(the reconstruction\'s object frame, posed in the camera optical '
                             'frame of each cloud)')
    publish_depth: bool = rule(True, None, 'publish nrsfm/depth (32FC1 metres, NaN off the '
                               'surface; needs CameraInfo or focal_length_px)')
    focal_length_px: float = rule(0.0, _non_negative,
                                  'fx when no CameraInfo arrives (0: output '
                                  'stays in orthographic image units)')
    idle_flush_s: float = rule(2.0, _non_negative, 'live: publish the frames still pending '
                               '(a window or batch not yet full) after this long without tracks '
                               '(0: never)')
    reliable: bool = rule(True, None, 'reliable QoS on the tracks input')
    queue_size: int = _queue_size(' (reliable tracks in modes batch, dspr and spva: '
                                  '4 x batch_frames, what arrives while a batch is solved)')
    queue_policy: str = _queue_policy()

    def check(self) -> list[tuple[str, str]]:
        errors = super().check()
        if self.mode == 'spva' and self.spva_prior_frames > self.batch_frames:
            errors.append(('spva_prior_frames', f'spva_prior_frames={self.spva_prior_frames}: '
                           f'must be <= batch_frames ({self.batch_frames}), the frames it '
                           'is chosen from'))
        return errors


@dataclass(frozen=True)
class RegistrarParams(Params):
    method: str = rule('icp', _one_of('icp', 'icp-point-to-point', 'icp-point-to-plane',
                                      'cpd-rigid', 'cpd-affine', 'cpd-nonrigid', 'ecpd-rigid',
                                      'ecpd-nonrigid', 'ga', 'bhrga', 'nrga'),
                       'registration method')
    max_iterations: int = rule(30, _REG['max_iterations'],
                               'iteration cap (ICP and CPD iterations; '
                               'GA dynamics steps, which needs ~300; BH-RGA L-BFGS '
                               'iterations per softening stage)')
    max_points: int = rule(1000, _REG['max_points'],
                           'source points used while iterating (0: all)')
    tolerance: float = rule(1e-6, _REG['tolerance'], 'relative RMSE change to stop')
    trim: float = rule(0.9, _REG['trim'], 'icp*: fraction of closest pairs kept each iteration '
                       '(about the overlap)')
    voxel: float = rule(0.0, _REG['voxel'], 'icp*: voxel-grid edge (m) of the coarse-to-fine '
                        'levels (4, 2, 1 x voxel; centroids average the noise; 0: off)')
    init: str = rule('centroid', _one_of('centroid', 'global', 'identity'),
                     'icp*: start of the first cloud and of every reflection re-check: centroid '
                     '(translation only), global (search over all rotations, robust to '
                     'outliers and missing parts, ~1 s at 35k points) or identity (the clouds '
                     'as they are); other clouds start from the previous transform')
    w: float = rule(0.1, _REG['w'], 'cpd: weight of the uniform outlier component')
    beta: float = rule(2.0, _REG['beta'], 'cpd-nonrigid, ecpd-nonrigid, nrga: kernel width of '
                       'the displacement field (units of the RMS radius)')
    lam: float = rule(2.0, _REG['lam'], 'cpd-nonrigid: smoothness of the displacement field')
    inlier_threshold: float = rule(0.0, _REG['inlier_threshold'],
                                   'distance (m) of the reported fitness and inlier RMSE and of '
                                   'the identity guard (0: 2% of the reference diagonal)')
    identity_guard: bool = rule(True, None,
                                'publish the unmoved cloud (identity) when the registration '
                                'explains the reference worse than it (robust residual: mean '
                                'of min(d, inlier_threshold)^2; match track_id: the same on '
                                'the ray residual of the matches)')
    match: str = rule('track_id', _one_of('track_id', 'nearest'),
                      'track_id: a cloud sharing >= 6 track ids with the reference, all in '
                      'front of its camera (a camera optical frame, as nrsfm/points), is posed '
                      'from those matches trusting its viewing rays over its depth (robust '
                      'Gauss-Newton from the previous pose; the previous pose or the identity '
                      'wins where it explains the matches better); other clouds (and those '
                      'whose matches are < 5% inliers: ids naming other points), and nearest, '
                      'use method')
    depth_weight: float = rule(0.1, _REG['depth_weight'],
                               'match track_id: weight of the error along each viewing ray '
                               'against the error across it (0: rays only, the cloud\'s depth '
                               'unused; 1: plain point-to-point)')
    prior_matches: int = rule(0, _non_negative,
                              'ecpd-*, ga, bhrga: prior correspondences taken from track_id '
                              'values the cloud shares with the reference (evenly spread; 0: '
                              'none; ecpd-* needs > 0)')
    try_reflection: bool = rule(True, None,
                                'also try the depth-mirrored source (orthographic NRSfM has a '
                                'depth reflection ambiguity) on the first cloud and every '
                                '10th, and keep the better fit (match track_id: the cost ratios '
                                'of the checks add up and their sum decides)')
    world_frame: str = rule('nrsfm_reference', _frame_id,
                            'parent frame of registration/camera_pose (child: the clouds\' '
                            'camera optical frame): the reference camera\'s optical frame at '
                            'the reference\'s stamp, fixed to the registered surface (a '
                            'world-fixed frame in the sense of REP-105 while the surface stays)')
    queue_size: int = _queue_size()
    queue_policy: str = _queue_policy()

    def check(self) -> list[tuple[str, str]]:
        errors = super().check()
        if self.method.startswith('ecpd') and self.prior_matches == 0:
            errors.append(('prior_matches', f'method={self.method!r} needs prior_matches > 0 '
                           '(track ids shared with the reference)'))
        return errors


@dataclass(frozen=True)
class SceneFlowParams(Params):
    method: str = rule('nrsfm', _one_of('nrsfm', 'msf'),
                       'nrsfm: difference of consecutive nrsfm/points clouds; msf: RGB-D '
                       'multi-frame scene flow (piecewise rigid) from camera/image_raw + '
                       'camera/depth/image_raw (32FC1 m or 16UC1 mm) + camera/camera_info')
    frame: str = rule('object', _one_of('object', 'camera'),
                      'nrsfm: object (camera ego-motion, estimated from the stream, removed) '
                      'in the previous camera\'s axes, or camera (raw difference); msf '
                      'publishes the camera frame (its camera pose is unknown)')
    window: int = rule(5, _at_least(2), 'nrsfm object frame: clouds (the current one '
                       'included) the ego-motion is estimated over')
    iterations: int = rule(8, _at_least(0), 'nrsfm object frame: re-weightings of the '
                           'ego-motion fit (weights from each track\'s spread) on a cold start')
    warm_iterations: int = rule(3, _at_least(0), 'nrsfm object frame: re-weightings when '
                                'warm-started from the previous window\'s weights')
    pose_points: int = rule(2000, _at_least(0), 'nrsfm object frame: tracks the ego-motion '
                            'is fitted on (a fixed subset of the ids; 0: all)')
    softness: float = rule(0.1, _positive, 'nrsfm object frame: track weight 1 / (spread^2 + '
                           '(softness * median spread)^2)')
    ego_motion: str = rule('auto', _one_of('auto', 'estimate'), 'nrsfm object frame: auto '
                           '(the reconstructor\'s cameras from nrsfm/object_pose where they '
                           'come with the clouds, its clouds\' shared centroid held still; '
                           'else estimated) or estimate (always estimated from the clouds: '
                           'the most rigid part held still)')
    shrinkage: str = rule('jitter', _one_of('jitter', 'none'), 'nrsfm object frame: jitter '
                          '(scale each point\'s flow toward zero by max(0, 1 - 6 sigma^2 / mean '
                          '|d|^2 over its 16 nearest points), sigma the jitter measured over the '
                          'window: pure jitter gives ~zero flow; times the point\'s visibility: '
                          'an occluded fill-in gets none) or none (the raw difference)')
    lookahead: int = rule(3, _at_least(0), 'nrsfm object frame: clouds of look-ahead L; '
                          '0: the flow of a cloud from the window ending at it, published at '
                          'once; L > 0: from a per-track quadratic over the clouds f-1-m .. f+m '
                          '(centred on the pair; m = L, fewer at a stream\'s ends), published '
                          'when cloud f+L arrives (at the end of a bag, or live after '
                          'idle_flush_s without a cloud, with the clouds there are)')
    idle_flush_s: float = rule(2.0, _non_negative, 'live, nrsfm with lookahead: publish the '
                               'clouds still waiting for their look-ahead after this long '
                               'without a cloud (0: never)')
    stride: int = rule(4, _at_least(1), 'msf: publish every stride-th reference pixel')
    segments: int = rule(300, _at_least(1), 'msf: SLIC segments of the reference frame')
    sync_tolerance_s: float = rule(0.005, _non_negative, 'msf: image and depth stamps closer '
                                   'than this are one RGB-D frame')
    marker_stride: int = rule(50, _at_least(1), 'one arrow per marker_stride points')
    marker_scale: float = rule(0.1, _positive, 'arrow length per (m/s)')
    queue_size: int = _queue_size()
    queue_policy: str = _queue_policy()


NODE_PARAMS: dict[str, type[Params]] = {
    'tracker': TrackerParams, 'reconstructor': ReconstructorParams,
    'registrar': RegistrarParams, 'scene_flow': SceneFlowParams,
}


def from_mapping(cls: type[Params], values: Mapping[str, Any]) -> Params:
    """Build and validate a parameter set from a mapping (YAML ros__parameters)."""
    return cls().updated(dict(values))


def to_yaml(name: str) -> str:
    """The config/<name>.yaml text: every parameter with its default and its doc line."""
    import yaml
    cls = NODE_PARAMS[name]
    lines = [f'# {name} node parameters (same names in the core, the CLI and ROS).',
             '# Used by launch_scripts/graph.sh and nrsfm-ros demo (--ros-args --params-file '
             'this file).', f'{name}:', '  ros__parameters:']
    for f in fields(cls):
        doc = f.metadata.get('doc', '') if f.metadata else ''
        if doc:
            lines.append(f'    # {doc}')
        value = yaml.safe_dump(getattr(cls(), f.name), default_flow_style=True).strip()
        value = value.removesuffix('\n...').removesuffix('...').strip()
        lines.append(f'    {f.name}: {value}')
    return '\n'.join(lines) + '\n'
