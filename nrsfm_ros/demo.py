"""``nrsfm-ros demo``: the main job on the embedded sample.

Generates (or reuses) the sample bag in bags/, starts the live graph as separate processes,
replays the bag into it, records every output topic, then writes a summary (frames in/out,
reconstruction e3D against ground truth, registration and scene-flow errors, per-node latency),
PLY files, perspective renders beside the ground truth with an error heat map, and a GIF of the
stream under the output folder.
"""
from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from .evaluation import MIN_POINTS, evaluate_outputs, read_outputs
from .io.export import write_ply
from .io.sequence_bag import write_sequence_bag
from .io.synth import SynthConfig, SynthSequence, generate
from .processing import TOPICS
from .render import render_stream

OUTPUTS = {TOPICS[k]: t for k, t in [
    ('tracks', 'sensor_msgs/msg/PointCloud2'), ('flow', 'sensor_msgs/msg/Image'),
    ('points', 'sensor_msgs/msg/PointCloud2'), ('nrsfm_depth', 'sensor_msgs/msg/Image'),
    ('object_pose', 'geometry_msgs/msg/TransformStamped'),
    ('aligned', 'sensor_msgs/msg/PointCloud2'),
    ('transform', 'geometry_msgs/msg/TransformStamped'),
    ('displacement', 'sensor_msgs/msg/PointCloud2'),
    ('camera_pose', 'geometry_msgs/msg/TransformStamped'),
    ('scene_flow', 'sensor_msgs/msg/PointCloud2'),
    ('markers', 'visualization_msgs/msg/MarkerArray'),
    ('diagnostics', 'diagnostic_msgs/msg/DiagnosticArray')]}

SAMPLE = SynthConfig(surface='flag', width=256, height=192, frames=60, fps=10.0, seed=0)


def sample_paths(bags_dir: Path, cfg: SynthConfig = SAMPLE) -> tuple[Path, Path]:
    stem = f'sample_{cfg.surface}_{cfg.width}x{cfg.height}_{cfg.frames}f_s{cfg.seed}'
    return bags_dir / stem, bags_dir / f'{stem}.npz'


def ensure_sample(bags_dir: Path, cfg: SynthConfig = SAMPLE) -> tuple[Path, Path]:
    """Generate the sample bag + ground-truth npz once; reuse them afterwards."""
    bag, npz = sample_paths(bags_dir, cfg)
    if bag.exists() and npz.exists():
        return bag, npz
    bags_dir.mkdir(parents=True, exist_ok=True)
    seq = generate(cfg)
    np.savez_compressed(npz, **seq.npz_dict())
    if bag.exists():
        import shutil
        shutil.rmtree(bag)
    write_sequence_bag(seq, bag)
    return bag, npz


def run_live(bag: Path, out_bag: Path, frames: int, rate: float, timeout: float,
             overrides: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Start the graph, replay ``bag`` into it, record every output; returns counts."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from .live import Graph, Recorder, ensure_loopback_env, replay
    ensure_loopback_env()
    graph = Graph(overrides=overrides)
    rclpy.init()
    node = Node('nrsfm_demo')
    recorder = Recorder(node, list(OUTPUTS), out_bag, known_types=OUTPUTS)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spin = threading.Thread(target=executor.spin, daemon=True)
    spin.start()
    result: dict[str, Any] = {'graph_exit': {}}
    try:
        # discovery: every pipeline input and output is matched before data flows
        need = {'/camera/image_raw': 1, '/nrsfm/tracks': 2, '/nrsfm/points': 3,
                '/registration/reference': 1}
        end = time.monotonic() + 30
        while time.monotonic() < end:
            if graph.poll():
                raise RuntimeError(f'a node died during start-up: {graph.poll()}')
            ok = all(node.count_subscribers(t) >= n for t, n in need.items()) and all(
                node.count_publishers(t) >= 1 for t in OUTPUTS)
            if ok:
                break
            time.sleep(0.1)
        else:
            raise RuntimeError('the node graph did not come up within 30 s')
        time.sleep(1.0)
        t0 = time.monotonic()
        result['replayed'] = replay(node, bag, rate=rate,
                                    wait_subscribers={'camera/image_raw': 1})
        expect = {TOPICS['points']: frames, TOPICS['nrsfm_depth']: frames,
                  TOPICS['aligned']: frames,
                  TOPICS['scene_flow']: frames, TOPICS['tracks']: frames}
        end = time.monotonic() + timeout
        while time.monotonic() < end and not graph.poll():
            if all(recorder.counts.get('/' + t, 0) >= n for t, n in expect.items()):
                break
            time.sleep(0.1)
        result['seconds'] = time.monotonic() - t0
        time.sleep(1.2)  # one more diagnostics period
    finally:
        result['graph_exit'] = graph.poll()
        graph.stop()
        executor.shutdown()
        result['recorded'] = recorder.close()
        node.destroy_node()
        rclpy.try_shutdown()
    return result


def summarise(out_bag: Path, seq: SynthSequence, out_dir: Path) -> dict[str, Any]:
    """Accuracy and latency of the recorded outputs against the ground truth
    (``evaluation.evaluate_outputs``, what ``nrsfm-ros evaluate`` prints), PLY files of the
    first, middle and last cloud, and the renders of ``nrsfm-ros evaluate --render``
    (``render.render_stream``: compare_FFF.png of those frames and stream.gif)."""
    out = read_outputs(out_bag, seq, colours=True)
    summary = {k: v for k, v in evaluate_outputs(out, seq).items()
               if not k.startswith('per_frame')}
    if out.clouds:
        out_dir.mkdir(parents=True, exist_ok=True)
        frames = sorted(out.clouds)
        stills = sorted({frames[0], frames[len(frames) // 2], frames[-1]})
        for f in stills:
            write_ply(out_dir / f'points_{f:03d}.ply', out.clouds[f][0], out.colours[f])
        rr = render_stream(out.clouds, seq.S, seq.track_ids, out_dir, fps=seq.config.fps,
                           stills=stills, min_points=MIN_POINTS)
        summary['renders'] = [str(p) for p in rr.stills] + ([str(rr.video)] if rr.video else [])
    summary['latency_ms'] = out.latency
    return summary


# every output topic of the node graph, in pipeline order: the summary and `evaluate` count each
OUTPUT_TOPICS = tuple(TOPICS[k] for k in ('tracks', 'points', 'nrsfm_depth', 'object_pose',
                                          'aligned',
                                          'transform', 'displacement', 'camera_pose',
                                          'scene_flow', 'markers', 'flow'))


def format_summary(s: dict[str, Any], live: dict[str, Any] | None = None) -> str:
    rows = [('frames in (camera/image_raw)', str(s['frames_in']))]
    for topic in OUTPUT_TOPICS:
        rows.append((f'frames out ({topic})', str(s['outputs'].get(topic, 0))))
    if 'e3d_B_frame_scaled' in s:
        rows.append(('points per frame (matched to ground truth)',
                     f"{s['points_per_frame']} ({s['points_matched_per_frame']:.0f})"))
        rows.append(('frames scored', f"{s['frames_scored']} of {s['frames_in']}"))
        rows.append(('e3D metric B, per-frame Procrustes + scale',
                     f"{s['e3d_B_frame_scaled']:.4f}"))
        rows.append(('  static oracle (frame 0 repeated), same frames',
                     f"{s['e3d_static_oracle']:.4f}"))
        rows.append(('  flat plane, same frames', f"{s['e3d_flat_plane']:.4f}"))
        rows.append(('frames with depths reflected against the truth',
                     f"{s['frames_depth_reflected']} of {s['frames_scored']}"))
    if 'registration_rmse_m' in s:
        rows.append(('registration RMSE to reference (m)', f"{s['registration_rmse_m']:.4f}"))
    if 'registration_rotation_error_deg_median' in s:
        rows.append(('registration rotation error, median (deg)',
                     f"{s['registration_rotation_error_deg_median']:.2f}"))
    if 'scene_flow_relative_epe' in s:
        rows.append(('scene flow relative EPE', f"{s['scene_flow_relative_epe']:.3f}"))
    for node, ms in sorted(s.get('latency_ms', {}).items()):
        rows.append((f'latency {node} (ms/message)', f'{ms:.1f}'))
    if live and 'seconds' in live:
        rows.append(('live graph wall time (s)', f"{live['seconds']:.1f}"))
    w = max(len(r[0]) for r in rows)
    lines = [f"| {'quantity':<{w}} | value |", f"|{'-' * (w + 2)}|-------|"]
    lines += [f'| {a:<{w}} | {b} |' for a, b in rows]
    return '\n'.join(lines)


def write_summary(out_dir: Path, summary: dict[str, Any], table: str) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / 'summary.json').write_text(json.dumps(summary, indent=2, default=float))
    (out_dir / 'summary.md').write_text(table + '\n')
