from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from rclpy.parameter import Parameter

HERE = Path(__file__).resolve().parent


def spin_until(ctx, node, pred, timeout):
    from rclpy.executors import SingleThreadedExecutor
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    end = time.monotonic() + timeout
    while not pred() and time.monotonic() < end:
        ex.spin_once(timeout_sec=0.05)
    ex.remove_node(node)
    return pred()


def test_two_process_100k_cloud_bytes_identical(rclpy_context):
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2
    sys.path.insert(0, str(HERE))
    from pub_cloud import cloud
    node = Node('sub_cloud', context=rclpy_context)
    got = []
    node.create_subscription(PointCloud2, 'test/cloud', got.append,
                             QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    proc = subprocess.Popen([sys.executable, str(HERE / 'pub_cloud.py')], env=dict(os.environ))
    try:
        assert spin_until(rclpy_context, node, lambda: len(got) >= 1, 25)
    finally:
        proc.wait(30)
        node.destroy_node()
    expected = cloud()
    assert bytes(got[0].data) == bytes(expected.data)
    assert got[0].width == 100_000 and got[0].point_step == 16


def test_parameters_validated_on_set(rclpy_context):
    from nrsfm_ros.nodes.common import ProcessorNode
    from nrsfm_ros.processing import ReconstructorProcessor
    node = ProcessorNode('reconstructor', ReconstructorProcessor,
                         [('points', 'sensor_msgs/msg/PointCloud2')], context=rclpy_context)
    try:
        bad = node.set_parameters([Parameter('window', value=1)])[0]
        assert not bad.successful and 'window=1' in bad.reason
        bad = node.set_parameters([Parameter('mode', value='magic')])[0]
        assert not bad.successful and 'mode' in bad.reason
        ok = node.set_parameters([Parameter('window', value=12)])[0]
        assert ok.successful and node.processor.params.window == 12
    finally:
        node.destroy_node()


def test_malformed_message_counted_and_skipped(rclpy_context):
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.node import Node
    from sensor_msgs.msg import Image

    from nrsfm_ros.io import image as img_io
    from nrsfm_ros.io.msgtypes import RclpyFactory
    from sensor_msgs.msg import PointCloud2

    from nrsfm_ros.io.synth import SynthConfig, generate
    from nrsfm_ros.nodes.common import RELIABLE, ProcessorNode
    from nrsfm_ros.processing import TrackerProcessor
    tracker = ProcessorNode('tracker', TrackerProcessor,
                            [('tracks', 'sensor_msgs/msg/PointCloud2')], context=rclpy_context)
    tracker.subscribe('image', 'sensor_msgs/msg/Image', RELIABLE)
    probe = Node('probe', context=rclpy_context)
    pub = probe.create_publisher(Image, 'camera/image_raw', 10)
    tracks, diags = [], []
    probe.create_subscription(PointCloud2, 'nrsfm/tracks', tracks.append, 10)
    probe.create_subscription(DiagnosticArray, '/diagnostics', diags.append, 10)
    seq = generate(SynthConfig(surface='face', width=96, height=72, frames=3))
    fac = RclpyFactory()
    good = [img_io.array_to_image(im, 'rgb8', fac, i, 'cam') for i, im in enumerate(seq.images)]
    bad = img_io.array_to_image(seq.images[0], 'rgb8', fac, 99, 'cam')
    bad.encoding = 'yuv422'
    from rclpy.executors import SingleThreadedExecutor
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(tracker)
    ex.add_node(probe)
    try:
        end = time.monotonic() + 10
        while pub.get_subscription_count() < 1 and time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
        for m in [good[0], bad, good[1], good[2]]:
            pub.publish(m)
            ex.spin_once(timeout_sec=0.05)
        end = time.monotonic() + 10
        while time.monotonic() < end and not (
                len(tracks) >= 3 and any(_value(d, 'malformed') == '1' for d in diags)):
            ex.spin_once(timeout_sec=0.05)
    finally:
        ex.shutdown()
        tracker.destroy_node()
        probe.destroy_node()
    assert len(tracks) == 3  # the malformed frame is skipped, the others processed
    assert tracker.processor.stats.malformed == 1
    assert any(_value(d, 'malformed') == '1' for d in diags)
    assert 'encoding' in tracker.processor.stats.last_error


def _value(diag, key):
    for st in diag.status:
        for kv in st.values:
            if kv.key == key:
                return kv.value
    return None


def test_tracker_node_streams_mfof_tracks_with_occlusion(rclpy_context):
    """Images in over rclpy -> one nrsfm/tracks per frame, same stamps, tracks on the true
    positions, the occluder's points flagged by visibility and the occlusion field."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import Image, PointCloud2

    from nrsfm_ros.io import image as img_io
    from nrsfm_ros.io import pointcloud2 as pc2
    from nrsfm_ros.io.msgtypes import RclpyFactory, stamp_ns
    from nrsfm_ros.io.synth_tracks import DeformConfig, generate_deforming
    from nrsfm_ros.nodes.common import RELIABLE, ProcessorNode
    from nrsfm_ros.processing import TrackerProcessor
    seq = generate_deforming(DeformConfig(width=160, height=128, frames=20, seed=1,
                                          occluder_frames=8, max_motion_px=25))
    tracker = ProcessorNode('tracker', TrackerProcessor,
                            [('tracks', 'sensor_msgs/msg/PointCloud2')], context=rclpy_context)
    assert tracker.processor.params.method == 'mfof'
    tracker.set_parameters([Parameter('mask', value='full'), Parameter('reliable', value=True)])
    tracker.subscribe('image', 'sensor_msgs/msg/Image', RELIABLE)
    probe = Node('probe_tracks', context=rclpy_context)
    pub = probe.create_publisher(Image, 'camera/image_raw', 30)
    got = []
    probe.create_subscription(PointCloud2, 'nrsfm/tracks', got.append, 30)
    fac = RclpyFactory()
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(tracker)
    ex.add_node(probe)
    try:
        end = time.monotonic() + 10
        while pub.get_subscription_count() < 1 and time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
        for i, im in enumerate(seq.images):
            pub.publish(img_io.array_to_image(im, 'mono8', fac, 1000 + i, 'cam'))
            for _ in range(3):
                ex.spin_once(timeout_sec=0.02)
        end = time.monotonic() + 20
        while len(got) < 20 and time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
    finally:
        ex.shutdown()
        tracker.destroy_node()
        probe.destroy_node()
    assert [stamp_ns(m.header) for m in got] == [1000 + i for i in range(20)]
    assert {'u', 'v', 'track_id', 'visibility', 'occlusion'} <= set(pc2.field_names(got[0]))
    errs, vis_occ, vis_free = [], [], []
    for f, m in enumerate(got):
        uv = pc2.read_fields(m, ('u', 'v'), np.float64)
        vis = pc2.read_fields(m, ('visibility',), np.float64)[:, 0]
        ids = pc2.read_fields(m, ('track_id',), np.uint32)[:, 0].astype(np.int64)
        gt = np.stack([seq.W[2 * f][ids], seq.W[2 * f + 1][ids]], 1)
        ok = seq.V[f][ids]
        errs.append(np.hypot(*(uv - gt)[ok].T).mean())
        occ = seq.occluded[f][ids]
        if occ.sum() > 50:
            vis_occ.append(vis[occ].mean())
            vis_free.append(vis[ok].mean())
    assert np.mean(errs) < 0.6
    assert vis_occ and np.mean(vis_occ) < 0.35 < 0.7 < np.mean(vis_free)


def test_config_yaml_matches_parameter_defaults():
    """config/<node>.yaml is what params.to_yaml writes: every parameter, its default, its doc."""
    from nrsfm_ros.params import NODE_PARAMS, to_yaml
    for name in NODE_PARAMS:
        text = (HERE.parent / 'config' / f'{name}.yaml').read_text()
        assert text == to_yaml(name), f'config/{name}.yaml is stale: regenerate with to_yaml'


def test_registrar_processor_cpd_methods():
    """The registrar's processing with CPD: transform and displacement per the method."""
    from scipy.spatial.transform import Rotation

    from nrsfm_ros.io import pointcloud2 as pc2
    from nrsfm_ros.io.msgtypes import RosbagsFactory
    from nrsfm_ros.params import RegistrarParams
    from nrsfm_ros.processing import RegistrarProcessor
    rng = np.random.default_rng(0)
    u, v = rng.uniform(-1, 1, (2, 800))
    X = np.stack([u, v, 0.4 * np.sin(2 * u) * np.cos(1.5 * v) + 0.2 * u * v], 1)
    R = Rotation.from_rotvec([0.0, 0.5, 0.1]).as_matrix()
    src = (X - [0.1, 0, 0]) @ R
    fac = RosbagsFactory()

    def cloud(P, stamp):
        P = P.astype(np.float32)
        return pc2.to_msg({'x': P[:, 0], 'y': P[:, 1], 'z': P[:, 2]}, fac, stamp, 'cam')
    bent = X + 0.1 * np.exp(-(X[:, :1] ** 2 + X[:, 1:2] ** 2)) * [0, 0, 1]
    for method in ('cpd-rigid', 'cpd-nonrigid', 'ga', 'nrga'):
        proc = RegistrarProcessor(fac, RegistrarParams(method=method, try_reflection=False,
                                                       w=0.0, max_iterations=300))
        if method == 'nrga':    # no rigid stage: a smooth bend without the large rotation
            src = bent
        proc.handle('reference', cloud(X, 0))
        out = dict((topic, msg) for topic, _, msg in proc.handle('points', cloud(src, 1)))
        aligned = pc2.read_xyz(out['registration/aligned'])
        assert np.sqrt(((aligned - X) ** 2).sum(1).mean()) < 0.02, method
        disp = pc2.read_fields(out['registration/displacement'], ('dx', 'dy', 'dz'))
        np.testing.assert_allclose(disp, aligned - src, atol=1e-4)


def test_registrar_processor_priors_from_shared_track_ids():
    """ECPD/BH-RGA in the registrar: prior matches come from track ids the cloud shares with
    the reference; they pull a 150-degree pose right where plain CPD fails.  ICP with
    ``init: global`` needs no priors."""
    from scipy.spatial.transform import Rotation

    from nrsfm_ros.core.metrics import rotation_error_deg
    from nrsfm_ros.io import pointcloud2 as pc2
    from nrsfm_ros.io.errors import MessageError
    from nrsfm_ros.io.msgtypes import RosbagsFactory
    from nrsfm_ros.params import RegistrarParams
    from nrsfm_ros.processing import RegistrarProcessor, transform_matrix
    rng = np.random.default_rng(4)
    u, v = rng.uniform(-1, 1, (2, 1500))
    X = np.stack([u, v, 0.4 * np.sin(2 * u) * np.cos(1.5 * v) + 0.2 * u * v], 1)
    X[:, 2] += 0.6 * np.exp(-((X[:, 0] - 0.5) ** 2 + (X[:, 1] + 0.4) ** 2) / 0.05)
    R = Rotation.from_rotvec(np.radians(150) * np.array([0.3, 1.0, 0.2])
                             / np.linalg.norm([0.3, 1.0, 0.2])).as_matrix()
    perm = rng.permutation(1500)
    src = ((X - [0.1, -0.2, 0.05]) @ R)[perm]
    fac = RosbagsFactory()

    def cloud(P, ids, stamp):
        P = P.astype(np.float32)
        fields = {'x': P[:, 0], 'y': P[:, 1], 'z': P[:, 2]}
        if ids is not None:
            fields['track_id'] = ids.astype(np.uint32)
        return pc2.to_msg(fields, fac, stamp, 'cam')
    ids = np.arange(1500) + 1000
    for method, priors, init in (('icp-point-to-plane', 0, 'global'), ('cpd-rigid', 0, 'centroid'),
                                 ('ecpd-rigid', 15, 'centroid'), ('bhrga', 15, 'centroid')):
        proc = RegistrarProcessor(fac, RegistrarParams(method=method, try_reflection=False,
                                                       w=0.3, prior_matches=priors,
                                                       max_iterations=100, init=init))
        proc.handle('reference', cloud(X, ids, 0))
        out = {topic: msg for topic, _, msg in proc.handle('points',
                                                           cloud(src, ids[perm], 1))}
        err = rotation_error_deg(transform_matrix(out['registration/transform'])[:3, :3], R)
        assert (err > 10) if priors == 0 and init != 'global' else (err < 1.0), (method, err)
    proc.handle('reference', cloud(X, None, 2))          # a reference without track ids
    with pytest.raises(MessageError, match='track_id'):
        proc.handle('points', cloud(src, ids[perm], 3))
    assert proc.stats.malformed == 1
    with pytest.raises(ValueError, match='needs prior_matches > 0'):
        RegistrarParams(method='ecpd-nonrigid').updated({})


def test_scene_flow_node_lookahead_flushes_when_the_clouds_stop(rclpy_context):
    """Live, with ``lookahead`` 2 the last two clouds' flows wait for clouds that never come:
    ``idle_flush_s`` after the last cloud the node publishes them (every cloud one flow)."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import PointCloud2

    from nrsfm_ros.io import pointcloud2 as pc2
    from nrsfm_ros.io.msgtypes import RclpyFactory
    from nrsfm_ros.nodes.common import RELIABLE
    from nrsfm_ros.nodes.scene_flow import SceneFlowNode
    node = SceneFlowNode(context=rclpy_context, parameter_overrides=[
        Parameter('lookahead', value=2), Parameter('idle_flush_s', value=1.5)])
    probe = Node('probe', context=rclpy_context)
    pub = probe.create_publisher(PointCloud2, 'nrsfm/points', RELIABLE)
    flows: list = []
    probe.create_subscription(PointCloud2, 'scene_flow/points', flows.append, RELIABLE)
    rng = np.random.default_rng(0)
    X0 = rng.normal(size=(300, 3)) * [0.2, 0.2, 0.02] + [0, 0, 2.0]
    fac = RclpyFactory()
    ex = SingleThreadedExecutor(context=rclpy_context)
    ex.add_node(node)
    ex.add_node(probe)
    try:
        end = time.monotonic() + 10
        while (pub.get_subscription_count() < 1 or node.count_publishers('scene_flow/points') < 1
               ) and time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
        for f in range(5):
            X = (X0 + 0.002 * f).astype(np.float32)
            pub.publish(pc2.to_msg({'x': X[:, 0], 'y': X[:, 1], 'z': X[:, 2],
                                    'track_id': np.arange(300, dtype=np.uint32)}, fac,
                                   int(1e9 + f * 1e8), 'cam'))
        end = time.monotonic() + 10
        while len(flows) < 3 and time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
        t3 = time.monotonic()
        assert len(flows) == 3                    # clouds 0..2; 3 and 4 wait
        while len(flows) < 5 and time.monotonic() < t3 + 10:
            ex.spin_once(timeout_sec=0.05)
        waited = time.monotonic() - t3
    finally:
        ex.shutdown()
        node.destroy_node()
        probe.destroy_node()
    assert [f.header.stamp.nanosec for f in flows] == [int(f * 1e8) for f in range(5)]
    assert 0.5 < waited < 8.0, waited            # after the idle time, not at once


def test_executor_has_a_second_thread_only_for_keep_all_inputs(rclpy_context):
    """``make_executor``: keep_latest inputs (every callback short) spin on one thread;
    keep_all ones on two, so a subscription held by a full queue never stops the timers."""
    from types import SimpleNamespace

    from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor

    from nrsfm_ros.nodes.common import make_executor

    def node(policy: str) -> SimpleNamespace:
        return SimpleNamespace(processor=SimpleNamespace(
            params=SimpleNamespace(queue_policy=policy)))
    assert isinstance(make_executor(node('keep_latest'), rclpy_context), SingleThreadedExecutor)
    assert isinstance(make_executor(node('keep_all'), rclpy_context), MultiThreadedExecutor)


def test_input_queue_depth_by_qos_and_keep_latest():
    """queue_size 0 (the default): a best-effort input holds only its newest message, a
    reliable one 64; a set queue_size applies to every input; a full input drops its oldest."""
    from nrsfm_ros.nodes.common import InputQueue, queue_depth
    from nrsfm_ros.params import NODE_PARAMS
    assert all(NODE_PARAMS[n]().queue_size == 0 for n in NODE_PARAMS)
    assert (queue_depth(0, False), queue_depth(0, True), queue_depth(5, False)) == (1, 64, 5)
    dropped = []
    q = InputQueue(lambda kind: 1 if kind == 'image' else 3, lambda: 'keep_latest',
                   dropped.append)
    for i in range(4):
        q.put('image', i)
        q.put('points', i)
    got = [q.get(0.01) for _ in range(len(q))]
    assert got == [('points', 1), ('points', 2), ('image', 3), ('points', 3)]
    assert dropped.count('image') == 3 and dropped.count('points') == 1


def _spun(ex, node, probe) -> threading.Thread:
    """``ex`` with both nodes, spinning in its own thread (as a node's main spins)."""
    ex.add_node(node)
    ex.add_node(probe)
    spinner = threading.Thread(target=ex.spin, daemon=True)
    spinner.start()
    return spinner


def _stop_spun(ex, spinner, node, probe) -> None:
    """Stop an executor spun in its own thread, the node's worker, and both nodes."""
    ex.shutdown()
    spinner.join(5)
    node.queue.close()
    node.destroy_node()
    probe.destroy_node()


def test_a_state_input_keeps_its_newest_message_in_place_uncounted():
    """A ``latest`` kind (CameraInfo, sent with every image): a new message replaces the one
    still queued, in its place (it applies no later than that one would have), and is not a
    dropped message; other kinds keep their depth and count their drops."""
    from nrsfm_ros.nodes.common import InputQueue
    dropped = []
    q = InputQueue(lambda kind: 2, lambda: 'keep_latest', dropped.append, latest=['info'])
    q.put('info', 'K0')
    q.put('tracks', 0)
    q.put('info', 'K1')
    q.put('tracks', 1)
    q.put('info', 'K2')
    q.put('tracks', 2)
    assert [q.get(0.01) for _ in range(len(q))] == [('info', 'K2'), ('tracks', 1), ('tracks', 2)]
    assert dropped == ['tracks']
    q.put('info', 'K3')                       # none queued: it takes its place at the end
    assert q.get(0.01) == ('info', 'K3') and len(q) == 0


def test_reconstructor_tracks_input_holds_what_arrives_during_a_batch_solve():
    """``queue_size`` 0: the reconstructor's reliable tracks input holds BATCH_QUEUE_BATCHES
    batches in the modes that solve batches (a batch call of seconds at camera rate), 64 in
    the others, 1 on a best-effort input; a set queue_size wins."""
    from nrsfm_ros.nodes.reconstructor import BATCH_QUEUE_BATCHES, tracks_queue_depth
    assert tracks_queue_depth(0, True, 'batch', 60) == BATCH_QUEUE_BATCHES * 60 == 240
    assert tracks_queue_depth(0, True, 'dspr', 20) == 80
    assert tracks_queue_depth(0, True, 'spva', 10) == 64      # never below a reliable input's
    assert tracks_queue_depth(0, True, 'window', 60) == 64
    assert tracks_queue_depth(0, False, 'batch', 60) == 1
    assert tracks_queue_depth(7, True, 'batch', 60) == 7


def test_reconstructor_node_loses_no_tracks_while_it_solves(rclpy_context):
    """Live, the reconstructor's worker is busy for the whole of a batch solve while the tracker
    goes on publishing: 150 tracks messages sent during a 1.5 s solve are all handled, none
    dropped (with the 64 of any reliable input, 86 were); CameraInfo sent with each of them is
    a state, not 150 drops."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import CameraInfo, PointCloud2

    from nrsfm_ros.nodes.common import RELIABLE, SENSOR
    from nrsfm_ros.nodes.reconstructor import ReconstructorNode
    node = ReconstructorNode(context=rclpy_context)
    handled: list[tuple[str, int]] = []

    def slow_handle(kind, msg):
        handled.append((kind, msg.header.stamp.nanosec))
        if kind == 'tracks' and len([h for h in handled if h[0] == 'tracks']) == 1:
            time.sleep(1.5)                      # the batch solve
        return []
    node.processor.handle = slow_handle
    probe = Node('tracks_probe', context=rclpy_context)
    pub = probe.create_publisher(PointCloud2, 'nrsfm/tracks', RELIABLE)
    info = probe.create_publisher(CameraInfo, 'camera/camera_info', SENSOR)
    ex = SingleThreadedExecutor(context=rclpy_context)
    spinner = _spun(ex, node, probe)
    try:
        end = time.monotonic() + 10
        while (pub.get_subscription_count() < 1 or info.get_subscription_count() < 1) and \
                time.monotonic() < end:
            time.sleep(0.05)
        for i in range(151):
            msg = PointCloud2()
            msg.header.stamp.nanosec = i
            pub.publish(msg)
            info.publish(CameraInfo())
            time.sleep(0.005)
        end = time.monotonic() + 20
        while time.monotonic() < end and \
                len([h for h in handled if h[0] == 'tracks']) + node.processor.stats.dropped < 151:
            time.sleep(0.05)
    finally:
        _stop_spun(ex, spinner, node, probe)
    assert node.processor.stats.dropped == 0
    assert [n for k, n in handled if k == 'tracks'] == list(range(151))
    # 4 batches of batch_seconds (6 s) at a 30 frames/s camera
    assert node.queue_depth('tracks') == 720 and 'camera_info' in node.queue.latest


def test_camera_input_latency_stays_bounded_under_overload(rclpy_context):
    """A tracker node that needs 0.15 s a frame, fed 40 frames at 50 Hz on its default
    (best-effort) camera input: it works on the newest frame, so each frame it processes
    waited about one processing time (bounded here at 1 s for loaded machines), and the frames
    it skipped are counted as dropped.  With the old fixed depth of 64 the last frames waited
    for all before them (~5 s)."""
    from rclpy.node import Node
    from sensor_msgs.msg import Image

    from nrsfm_ros.io import image as img_io
    from nrsfm_ros.io.msgtypes import RclpyFactory
    from nrsfm_ros.nodes.common import SENSOR, ProcessorNode, make_executor
    from nrsfm_ros.processing import TrackerProcessor

    waited: list[float] = []

    class SlowTracker(TrackerProcessor):
        def on_image(self, msg):
            waited.append(time.monotonic() - sent[msg.header.stamp.nanosec])
            time.sleep(0.15)
            return []

    sent: dict[int, float] = {}
    node = ProcessorNode('tracker', SlowTracker, [], context=rclpy_context)
    node.subscribe('image', 'sensor_msgs/msg/Image', SENSOR)
    probe = Node('overload_probe', context=rclpy_context)
    pub = probe.create_publisher(Image, 'camera/image_raw', SENSOR)
    fac = RclpyFactory()
    frame = np.zeros((48, 64, 3), np.uint8)
    ex = make_executor(node, rclpy_context)          # the executor the node's main uses
    # spun in its own thread as the nodes' main does (executor.spin()): on some machines rclpy's
    # multi-threaded executor driven by spin_once from a test thread took the frames so late
    # that DDS overwrote half of them unreported
    spinner = _spun(ex, node, probe)
    try:
        end = time.monotonic() + 10
        while pub.get_subscription_count() < 1 and time.monotonic() < end:
            time.sleep(0.05)
        # until the node has taken one frame: on a loaded machine the publisher can match
        # before the subscriber does, and best-effort frames sent then are gone unreported
        k = 0
        while not waited and time.monotonic() < end + 10:
            msg = img_io.array_to_image(frame, 'rgb8', fac, 0, 'cam')
            msg.header.stamp.nanosec = 1000 + k
            sent[1000 + k] = time.monotonic()
            pub.publish(msg)
            k += 1
            time.sleep(0.1)
        time.sleep(0.5)                              # the warm-up frames done with
        assert waited, 'the node never received a frame'
        waited.clear()
        dropped0 = node.processor.stats.dropped
        for i in range(40):
            msg = img_io.array_to_image(frame, 'rgb8', fac, 0, 'cam')
            msg.header.stamp.nanosec = i
            sent[i] = time.monotonic()
            pub.publish(msg)
            time.sleep(0.02)
        end = time.monotonic() + 5
        while time.monotonic() < end and \
                len(waited) + node.processor.stats.dropped - dropped0 < 40:
            time.sleep(0.05)
    finally:
        _stop_spun(ex, spinner, node, probe)
    dropped = node.processor.stats.dropped - dropped0
    assert node.queue_depth('image') == 1
    assert 3 <= len(waited) <= 20 and dropped >= 15
    # every frame processed or counted as dropped, but for what DDS's own best-effort history
    # overwrote before the node took it (DDS does not report those; none on an idle machine)
    assert 30 <= len(waited) + dropped <= 40
    assert max(waited) < 1.0, waited                 # 64 deep: the last waited ~5 s
