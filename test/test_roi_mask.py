"""Tracking only the surface a segmentation gives (tracker ``roi_mask``, camera/mask): the core's
region, the processor's mask input and its errors, the renderer's textured background and its
mask, and the pipeline on a background render against the same run without the mask."""
from __future__ import annotations

import numpy as np
import pytest

from nrsfm_ros.core.tracking import MFOFTracker
from nrsfm_ros.core.tracking.reference_flow import reference_pixels
from nrsfm_ros.io.errors import MessageError
from nrsfm_ros.io.image import array_to_image
from nrsfm_ros.io.msgtypes import RosbagsFactory
from nrsfm_ros.io.synth import SynthConfig, generate
from nrsfm_ros.params import ReconstructorParams, TrackerParams
from nrsfm_ros.processing import TrackerProcessor

FAC = RosbagsFactory()


@pytest.fixture(scope='module')
def seq():
    return generate(SynthConfig(surface='sheet', width=128, height=96, frames=30,
                                camera_motion_deg=30.0, background=True))


def _grey(seq, f):
    import cv2
    return cv2.cvtColor(seq.images[f], cv2.COLOR_RGB2GRAY)


def _seen(seq, f):
    return np.isfinite(seq.surface_st[f][..., 0])


def test_background_is_a_textured_wall_with_depth_and_a_mask(seq, tmp_path):
    from nrsfm_ros.io.bag import read_messages
    from nrsfm_ros.io.image import image_to_array
    from nrsfm_ros.io.bag import deserialize
    from nrsfm_ros.io.sequence_bag import write_sequence_bag
    off = _seen(seq, 0)
    assert 0.2 < off.mean() < 0.9
    grey = _grey(seq, 0).astype(float)
    assert grey[~off].std() > 20                     # textured, not the plain dark 20
    assert np.isfinite(seq.depth).all()              # the wall has a depth
    assert (seq.depth[0][~off] > seq.depth[0][off].max()).all()    # behind the surface
    write_sequence_bag(seq, tmp_path / 'bag')
    masks = [m for m in read_messages(tmp_path / 'bag') if m.topic == 'camera/mask']
    assert len(masks) == 30
    m = image_to_array(deserialize(masks[3].raw, masks[3].msgtype))
    np.testing.assert_array_equal(m == 255, _seen(seq, 3))
    plain = generate(SynthConfig(surface='sheet', width=128, height=96, frames=3))
    write_sequence_bag(plain, tmp_path / 'plain')
    assert not any(m.topic == 'camera/mask' for m in read_messages(tmp_path / 'plain'))
    with pytest.raises(ValueError, match='background=1'):
        SynthConfig(background=1).validate()


def test_reference_pixels_and_mfof_stay_in_the_region(seq):
    grey, roi = _grey(seq, 0), _seen(seq, 0)
    m_all, lin_all, _ = reference_pixels(grey, 'texture', 2, 4.0)
    m, lin, xy = reference_pixels(grey, 'texture', 2, 4.0, roi)
    assert roi.ravel()[lin].all() and not roi.ravel()[lin_all].all()
    assert (m <= roi).all() and lin.size < 0.9 * lin_all.size
    with pytest.raises(ValueError, match='roi: size'):
        reference_pixels(grey, 'texture', 2, 4.0, roi[:-1])
    with pytest.raises(ValueError, match='region of interest'):
        reference_pixels(grey, 'texture', 2, 4.0, np.zeros_like(roi))
    tr = MFOFTracker()
    tr.roi = roi
    tr.step(grey)
    assert roi.ravel()[tr.ids.astype(np.int64)].all()


def _image(seq, f):
    return array_to_image(seq.images[f], 'rgb8', FAC, int(seq.stamps_ns[f]), 'cam')


def _mask(seq, f, encoding='mono8'):
    return array_to_image(np.where(_seen(seq, f), 255, 0).astype(np.uint8), encoding, FAC,
                          int(seq.stamps_ns[f]), 'cam')


@pytest.mark.parametrize('downsample', [1, 2])
def test_processor_tracks_inside_the_eroded_mask(seq, downsample):
    import cv2
    proc = TrackerProcessor(FAC, TrackerParams(roi_mask=True, downsample=downsample))
    with pytest.raises(MessageError, match='camera/mask.*no mask has arrived'):
        proc.handle('image', _image(seq, 0))         # skipped and counted, never silent
    assert proc.stats.malformed == 1
    proc.handle('mask', _mask(seq, 1))
    out = dict((t, m) for t, _, m in proc.handle('image', _image(seq, 1)))
    from nrsfm_ros.io import pointcloud2 as pc2
    ids = pc2.read_fields(out['nrsfm/tracks'], ('track_id',), np.uint32)[:, 0].astype(np.int64)
    pix = ids % (128 * 96)
    r = 2                                            # roi_margin's default
    inner = cv2.erode(_seen(seq, 1).astype(np.uint8),
                      cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)))
    assert inner.ravel()[pix].all() and ids.size > 100
    if downsample == 1:     # the flow never sees what lies behind the surface
        ref = proc.tracker.reference
        assert (ref[~_seen(seq, 1)] == 0).all() and ref[_seen(seq, 1)].mean() > 50
    # off: the mask is not taken, and the tracks reach the background
    off = TrackerProcessor(FAC, TrackerParams(downsample=downsample))
    assert off.handle('mask', _mask(seq, 1)) == [] and off.stats.received == 0
    out = dict((t, m) for t, _, m in off.handle('image', _image(seq, 1)))
    ids = pc2.read_fields(out['nrsfm/tracks'], ('track_id',), np.uint32)[:, 0].astype(np.int64)
    assert not _seen(seq, 1).ravel()[ids % (128 * 96)].all()


def test_processor_names_a_bad_mask(seq):
    proc = TrackerProcessor(FAC, TrackerParams(roi_mask=True))
    with pytest.raises(MessageError, match="camera/mask encoding='rgb8'"):
        proc.handle('mask', array_to_image(seq.images[0], 'rgb8', FAC, 0, 'cam'))
    proc.handle('mask', array_to_image(np.full((48, 64), 255, np.uint8), 'mono8', FAC, 0, 'c'))
    with pytest.raises(MessageError, match='camera/mask height/width.*differs from the image'):
        proc.handle('image', _image(seq, 0))
    assert proc.stats.malformed == 2
    proc.handle('mask', _mask(seq, 0))                # a good one: tracking goes on
    assert proc.handle('image', _image(seq, 0))


def test_pipeline_on_a_background_render_beats_its_baselines_with_the_mask(seq, tmp_path):
    """Through tracker -> reconstructor on a sheet before a textured wall, every track seen
    twice in the batch (``min_seen`` 0, so the mask alone is measured): without the mask the
    wall's tracks break the reconstruction (above the static oracle); with it, below the
    static and flat baselines scored on the same frames, and under half the error."""
    from nrsfm_ros.evaluation import read_clouds, score
    from nrsfm_ros.io.sequence_bag import write_sequence_bag
    from nrsfm_ros.pipeline import process_bag
    write_sequence_bag(seq, tmp_path / 'bag')
    e3d = {}
    for roi in (False, True):
        out = tmp_path / f'out{int(roi)}'
        rep = process_bag(tmp_path / 'bag', out, stages=('tracker', 'reconstructor'),
                          progress=False, params={'tracker': TrackerParams(roi_mask=roi),
                                                  'reconstructor': ReconstructorParams(
                                                      min_seen=0.0)})
        assert rep.failures == [] and rep.outputs['nrsfm/points'] == 30
        sc = score(read_clouds(out, seq.stamps_ns), seq)
        assert sc.unscored == []
        e3d[roi] = (float(np.mean(sc.e3d)), float(np.mean(sc.static)),
                    float(np.mean(sc.flat)))
    (plain, *_), (masked, static, flat) = e3d[False], e3d[True]
    assert masked < 0.5 * plain, e3d
    assert masked < static and masked < flat, e3d


def test_tracker_node_takes_the_mask_over_rclpy(seq, rclpy_context):
    """Over real DDS: ``roi_mask`` set as a ROS parameter, a camera/mask then the image of the
    same stamp -> the frame's tracks all lie inside the mask."""
    import time

    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import Image, PointCloud2

    from nrsfm_ros.io import pointcloud2 as pc2
    from nrsfm_ros.io.msgtypes import RclpyFactory
    from nrsfm_ros.nodes.common import RELIABLE, ProcessorNode
    tracker = ProcessorNode('tracker', TrackerProcessor,
                            [('tracks', 'sensor_msgs/msg/PointCloud2')], context=rclpy_context)
    tracker.subscribe('image', 'sensor_msgs/msg/Image', RELIABLE)
    tracker.subscribe('mask', 'sensor_msgs/msg/Image', RELIABLE)
    assert tracker.set_parameters([Parameter('roi_mask', value=True)])[0].successful
    probe = Node('probe', context=rclpy_context)
    pub_img = probe.create_publisher(Image, 'camera/image_raw', 10)
    pub_mask = probe.create_publisher(Image, 'camera/mask', 10)
    tracks: list = []
    probe.create_subscription(PointCloud2, 'nrsfm/tracks', tracks.append, 10)
    fac = RclpyFactory()
    st = int(seq.stamps_ns[0])
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(tracker)
    ex.add_node(probe)

    def spin_until(pred, timeout=10.0):
        end = time.monotonic() + timeout
        while not pred() and time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
        return pred()
    try:
        assert spin_until(lambda: pub_img.get_subscription_count() >= 1
                          and pub_mask.get_subscription_count() >= 1)
        pub_mask.publish(array_to_image(np.where(_seen(seq, 0), 255, 0).astype(np.uint8),
                                        'mono8', fac, st, 'cam'))
        assert spin_until(lambda: len(tracker.processor._masks) == 1)
        pub_img.publish(array_to_image(seq.images[0], 'rgb8', fac, st, 'cam'))
        assert spin_until(lambda: len(tracks) == 1)
    finally:
        ex.shutdown()
        tracker.destroy_node()
        probe.destroy_node()
    ids = pc2.read_fields(tracks[0], ('track_id',), np.uint32)[:, 0].astype(np.int64)
    assert ids.size > 100 and _seen(seq, 0).ravel()[ids % (128 * 96)].all()
    assert tracker.processor.stats.malformed == 0


def test_track_cli_with_masks_tracks_inside_them(seq, tmp_path, capsys):
    """``nrsfm-ros track FRAMES --masks MASKS``: the batch verb takes one mask image per frame
    (as the node takes camera/mask); errors name the flag."""
    import cv2

    from nrsfm_ros.cli import main
    (tmp_path / 'f').mkdir()
    (tmp_path / 'm').mkdir()
    for f in range(8):
        cv2.imwrite(str(tmp_path / 'f' / f'{f:03d}.png'), cv2.cvtColor(seq.images[f],
                                                                    cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(tmp_path / 'm' / f'{f:03d}.png'),
                    np.where(_seen(seq, f), 255, 0).astype(np.uint8))
    for method in ('mfof', 'reference'):
        out = tmp_path / f'{method}.npz'
        assert main(['track', str(tmp_path / 'f'), '--masks', str(tmp_path / 'm'),
                     '--method', method, '--out', str(out)]) == 0
        ids = np.load(out)['track_ids'].astype(np.int64)
        assert ids.size > 100 and _seen(seq, 0).ravel()[ids % (128 * 96)].all()
    assert main(['track', str(tmp_path / 'f'), '--out', str(tmp_path / 'x.npz')]) == 0
    ids = np.load(tmp_path / 'x.npz')['track_ids'].astype(np.int64)
    assert not _seen(seq, 0).ravel()[ids % (128 * 96)].all()     # the wall too
    (tmp_path / 'm' / '007.png').unlink()
    capsys.readouterr()
    assert main(['track', str(tmp_path / 'f'), '--masks', str(tmp_path / 'm'), '--out',
                 str(tmp_path / 'y.npz')]) != 0
    assert '--masks' in (err := capsys.readouterr().err) and '7 masks for 8 frames' in err
    rc = main(['track', str(tmp_path / 'f'), '--roi-margin', '3', '--out',
               str(tmp_path / 'z.npz')])
    assert rc != 0 and '--roi-margin: only with --masks' in capsys.readouterr().err
