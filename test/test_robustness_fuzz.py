"""Seeded fuzz of the processors (offline, no DDS): >= 10,000 malformed messages with every field
of Image, CompressedImage, CameraInfo and PointCloud2 mutated, interleaved with valid ones.

Every message is counted (received = processed + malformed + failed), nothing but MessageError
ever leaves ``Processor.handle``, and each processor still works on valid input afterwards."""
from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from nrsfm_ros.io import image as img_io
from nrsfm_ros.io import pointcloud2 as pc2
from nrsfm_ros.io.errors import MessageError
from nrsfm_ros.io.msgtypes import RosbagsFactory
from nrsfm_ros.params import ReconstructorParams, RegistrarParams, TrackerParams
from nrsfm_ros.processing import (Processor, ReconstructorProcessor, RegistrarProcessor,
                                  SceneFlowProcessor, TrackerProcessor)

FAC = RosbagsFactory()
W, H = 40, 32
INTS = (0, 1, 2, 3, 7, 16, 31, 32, 33, 40, 64, 1000, 2 ** 31 - 1, 2 ** 32 - 1, -1, -2 ** 31)
ENCODINGS = ('rgb8', 'bgr8', 'mono8', 'mono16', '16UC1', '32FC1', '32FC2', 'rgba8', '8UC3',
             'yuv422', '', 'RGB8', 'bayer_rggb8', '\x00\xff')
FLOATS = (np.nan, np.inf, -np.inf, 0.0, -1.0, 1e30, -1e-30, 5.0, 1e6)


def textured(rng: np.random.Generator, shift: int = 0, size: tuple[int, int] = (H, W)
             ) -> np.ndarray:
    base = cv2.GaussianBlur(rng.uniform(0, 255, (size[0], size[1] + 8)).astype(np.float32),
                            (0, 0), 1.2)
    img = np.clip(base[:, shift:shift + size[1]] * 2 - 128, 0, 255).astype(np.uint8)
    return np.repeat(img[..., None], 3, axis=2)


def header(stamp: int) -> Any:
    return FAC.header(stamp, 'cam')


def some_bytes(rng: np.random.Generator, data: np.ndarray) -> np.ndarray:
    n = data.size
    choice = int(rng.integers(6))
    if choice == 0:
        return data[:int(rng.integers(0, max(n, 1)))]
    if choice == 1:
        return np.concatenate([data, rng.integers(0, 256, int(rng.integers(1, 64)), np.uint8)])
    if choice == 2:
        return rng.integers(0, 256, n, np.uint8)
    if choice == 3:
        return np.zeros(0, np.uint8)
    out = data.copy()
    idx = rng.integers(0, max(n, 1), max(1, n // 50)) if n else np.zeros(0, np.intp)
    out[idx] = rng.integers(0, 256, idx.size, np.uint8)
    return out


def mutate_header(rng: np.random.Generator, msg: Any) -> Any:
    sec = int(rng.choice([-5, 0, 1, 2 ** 31 - 1, -2 ** 31]))
    nsec = int(rng.choice([0, 999_999_999, 2 ** 32 - 1]))
    frame = str(rng.choice(['', 'x' * 300, 'cam\x00', '/other']))
    return dataclasses.replace(msg, header=FAC.make(
        'std_msgs/msg/Header', stamp=FAC.make('builtin_interfaces/msg/Time', sec=sec,
                                              nanosec=nsec), frame_id=frame))


def pick(rng: np.random.Generator, values: tuple) -> Any:
    return values[int(rng.integers(len(values)))]


# --------------------------------------------------------------------- per-type mutations
def image_mutations(rng: np.random.Generator) -> dict[str, Callable[[Any], Any]]:
    return {
        'header': lambda m: mutate_header(rng, m),
        'height': lambda m: dataclasses.replace(m, height=pick(rng, INTS)),
        'width': lambda m: dataclasses.replace(m, width=pick(rng, INTS)),
        'encoding': lambda m: dataclasses.replace(m, encoding=pick(rng, ENCODINGS)),
        'is_bigendian': lambda m: dataclasses.replace(m, is_bigendian=pick(rng, (0, 1, 2, 255))),
        'step': lambda m: dataclasses.replace(m, step=pick(rng, INTS + (W * 3 + 1, W * 3 - 1))),
        'data': lambda m: dataclasses.replace(m, data=some_bytes(rng, m.data)),
        'blank': lambda m: dataclasses.replace(m, data=np.full_like(m.data, pick(rng, (0, 255)))),
        'resize': lambda m: img_io.array_to_image(
            textured(rng, 0, (int(rng.integers(1, 48)), int(rng.integers(1, 56)))), 'rgb8',
            FAC, 5, 'cam'),
    }


def compressed_mutations(rng: np.random.Generator) -> dict[str, Callable[[Any], Any]]:
    def recode(m: Any) -> Any:
        kind = int(rng.integers(3))
        if kind == 0:   # 16-bit colour png
            img = (textured(rng).astype(np.uint16) * 257)
        elif kind == 1:
            img = np.zeros((int(rng.integers(1, 20)), int(rng.integers(1, 20))), np.uint8)
        else:
            img = textured(rng, 0, (int(rng.integers(16, 40)), int(rng.integers(16, 48))))
        ok, data = cv2.imencode('.png', img)
        return dataclasses.replace(m, data=data.reshape(-1))
    return {
        'header': lambda m: mutate_header(rng, m),
        'format': lambda m: dataclasses.replace(m, format=pick(
            rng, ('', 'png', 'jpeg', 'tiff', 'bgr8; jpeg compressed bgr8', '\xff'))),
        'data': lambda m: dataclasses.replace(m, data=some_bytes(rng, m.data)),
        'recode': recode,
    }


def camera_info_mutations(rng: np.random.Generator) -> dict[str, Callable[[Any], Any]]:
    def arr(m: Any, name: str) -> Any:
        v = np.asarray(getattr(m, name), np.float64).copy()
        if rng.random() < 0.3:
            v = rng.normal(size=int(rng.integers(0, 13)))
        elif v.size:
            v[int(rng.integers(v.size))] = pick(rng, FLOATS)
        return dataclasses.replace(m, **{name: v})
    return {
        'header': lambda m: mutate_header(rng, m),
        'height': lambda m: dataclasses.replace(m, height=pick(rng, INTS)),
        'width': lambda m: dataclasses.replace(m, width=pick(rng, INTS)),
        'distortion_model': lambda m: dataclasses.replace(m, distortion_model=pick(
            rng, ('', 'equidistant', 'rational_polynomial', '\x00'))),
        'd': lambda m: arr(m, 'd'), 'k': lambda m: arr(m, 'k'), 'r': lambda m: arr(m, 'r'),
        'p': lambda m: arr(m, 'p'),
        'binning': lambda m: dataclasses.replace(m, binning_x=pick(rng, INTS),
                                                 binning_y=pick(rng, INTS)),
        'roi': lambda m: dataclasses.replace(m, roi=FAC.make(
            'sensor_msgs/msg/RegionOfInterest', x_offset=pick(rng, INTS),
            y_offset=pick(rng, INTS), height=pick(rng, INTS), width=pick(rng, INTS),
            do_rectify=bool(rng.integers(2)))),
    }


def cloud_mutations(rng: np.random.Generator) -> dict[str, Callable[[Any], Any]]:
    def field_change(m: Any) -> Any:
        fields = list(m.fields)
        i = int(rng.integers(len(fields)))
        f = fields[i]
        what = int(rng.integers(6))
        if what == 0:
            fields.pop(i)
        elif what == 1:
            fields.append(f)
        else:
            change = [{'name': pick(rng, ('', 'x', 'track_id', 'u', 'rgb', 'zz'))},
                      {'datatype': pick(rng, (0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 255))},
                      {'offset': pick(rng, INTS)},
                      {'count': pick(rng, (0, 1, 2, 3, 1000, 2 ** 32 - 1))}][what - 2]
            fields[i] = dataclasses.replace(f, **change)
        return dataclasses.replace(m, fields=fields)

    def values(m: Any) -> Any:
        pts = pc2.read_points(m).reshape(-1).copy()
        name = pick(rng, pts.dtype.names)
        idx = rng.integers(0, pts.size, max(1, pts.size // 10))
        if name == 'track_id':
            pts[name][idx] = pts[name][0]          # duplicate ids
        elif pts.dtype[name].kind == 'f':
            pts[name][idx] = pick(rng, FLOATS)
        else:
            pts[name][idx] = rng.integers(0, 2 ** 16, idx.size)
        return dataclasses.replace(m, data=pts.view(np.uint8))

    def rgb3(m: Any) -> Any:          # an rgb field of count 3 (the example)
        n = int(m.width) * int(m.height)
        cols = {k: pc2.read_points(m).reshape(-1)[k] for k in pc2.field_names(m)
                if k != 'rgb'}
        dt = np.dtype([(k, v.dtype) for k, v in cols.items()] + [('rgb', 'f4', (3,))])
        arr = np.zeros(n, dt)
        for k, v in cols.items():
            arr[k] = v
        out = pc2.to_msg(arr, FAC, 1, 'cam')
        return out
    return {
        'header': lambda m: mutate_header(rng, m),
        'height': lambda m: dataclasses.replace(m, height=pick(rng, INTS)),
        'width': lambda m: dataclasses.replace(m, width=pick(rng, INTS)),
        'fields': field_change,
        'is_bigendian': lambda m: dataclasses.replace(m, is_bigendian=not m.is_bigendian),
        'point_step': lambda m: dataclasses.replace(m, point_step=pick(rng, INTS)),
        'row_step': lambda m: dataclasses.replace(m, row_step=pick(rng, INTS)),
        'data': lambda m: dataclasses.replace(m, data=some_bytes(rng, m.data)),
        'is_dense': lambda m: dataclasses.replace(m, is_dense=not m.is_dense),
        'values': values,
        'rgb_count3': rgb3,
    }


# --------------------------------------------------------------------- valid messages
def tracks_msg(rng: np.random.Generator, f: int, P: int = 60) -> Any:
    g = np.stack(np.meshgrid(np.arange(10), np.arange(6)), -1).reshape(-1, 2)[:P] * 3.0 + 5
    t = 0.2 * f
    uv = g + np.stack([np.sin(t + g[:, 1] * 0.2), 0.5 * np.cos(t + g[:, 0] * 0.1)], 1)
    return pc2.to_msg({'u': uv[:, 0].astype(np.float32), 'v': uv[:, 1].astype(np.float32),
                       'track_id': np.arange(P, dtype=np.uint32),
                       'visibility': np.ones(P, np.float32),
                       'rgb': pc2.pack_rgb(rng.integers(0, 256, (P, 3)))},
                      FAC, 10 ** 9 + f * 10 ** 8, 'cam')


def points_msg(rng: np.random.Generator, f: int, P: int = 80) -> Any:
    u, v = np.meshgrid(np.linspace(-1, 1, 10), np.linspace(-1, 1, 8))
    X = np.stack([u.ravel(), v.ravel(), 0.2 * np.sin(2 * u.ravel() + 0.1 * f)], 1)[:P]
    X = (X + [0.0, 0.0, 4.0]).astype(np.float32)
    return pc2.to_msg({'x': X[:, 0], 'y': X[:, 1], 'z': X[:, 2].astype(np.float32),
                       'rgb': pc2.pack_rgb(rng.integers(0, 256, (P, 3))),
                       'track_id': np.arange(P, dtype=np.uint32)},
                      FAC, 10 ** 9 + f * 10 ** 8, 'cam')


def camera_info() -> Any:
    K = np.array([[50.0, 0, W / 2], [0, 50.0, H / 2], [0, 0, 1]])
    return img_io.make_camera_info(K, W, H, FAC, 0, 'cam')


def feed(proc: Processor, kind: str, msg: Any, tally: dict[str, int]) -> None:
    try:
        proc.handle(kind, msg)
    except MessageError:
        tally['raised'] += 1


MESSAGES = 11_500     # every 10th valid: >= 10,000 malformed


def test_fuzz_every_field_no_uncaught_exception_every_message_counted():
    rng = np.random.default_rng(16)
    t0, c0 = time.perf_counter(), time.process_time()
    tracker = TrackerProcessor(FAC, TrackerParams(rank=2, window=4, publish_flow=False))
    rec = ReconstructorProcessor(FAC, ReconstructorParams(mode='window', window=4, iterations=2,
                                                          publish_depth=True))
    reg = RegistrarProcessor(FAC, RegistrarParams(max_iterations=5, try_reflection=False))
    flow = SceneFlowProcessor(FAC)
    procs = {'tracker': tracker, 'reconstructor': rec, 'registrar': reg, 'scene_flow': flow}
    tally = {name: {'raised': 0} for name in procs}
    muts = {'image': image_mutations(rng), 'compressed': compressed_mutations(rng),
            'camera_info': camera_info_mutations(rng), 'cloud': cloud_mutations(rng)}
    mutated = {k: {f: 0 for f in v} for k, v in muts.items()}
    valid_img = img_io.array_to_image(textured(rng), 'rgb8', FAC, 1, 'cam')
    valid_comp = img_io.array_to_compressed(textured(rng), 'rgb8', FAC, 1, 'cam')
    sent = 0
    # (kind of base message, processor, input kind, base factory)
    targets = [('image', 'tracker', 'image', lambda f: img_io.array_to_image(
                   textured(rng, f % 8), 'rgb8', FAC, f, 'cam')),
               ('compressed', 'tracker', 'image_compressed', lambda f: valid_comp),
               ('camera_info', 'reconstructor', 'camera_info', lambda f: camera_info()),
               ('cloud', 'reconstructor', 'tracks', lambda f: tracks_msg(rng, f)),
               ('cloud', 'registrar', 'points', lambda f: points_msg(rng, f)),
               ('cloud', 'registrar', 'reference', lambda f: points_msg(rng, 0)),
               ('cloud', 'scene_flow', 'points', lambda f: points_msg(rng, f))]
    weights = np.array([3, 2, 2, 3, 2, 1, 2], float)
    for f in range(MESSAGES):
        base_kind, stage, kind, make = targets[int(rng.choice(len(targets),
                                                               p=weights / weights.sum()))]
        if f % 10 == 0:     # keep the state moving with valid input
            feed(procs[stage], kind, make(f), tally[stage])
            continue
        msg = make(f)
        names = list(muts[base_kind])
        for _ in range(int(rng.integers(1, 3))):
            name = names[int(rng.integers(len(names)))]
            try:
                msg = muts[base_kind][name](msg)
            except (MessageError, ValueError):
                continue      # the mutation itself needed a readable cloud
            mutated[base_kind][name] += 1
        feed(procs[stage], kind, msg, tally[stage])
        sent += 1
    assert sent >= 10_000
    assert all(n > 20 for fields in mutated.values() for n in fields.values()), mutated
    for name, p in procs.items():
        s = p.stats
        assert s.received == s.processed + s.malformed + s.failed, name
        assert tally[name]['raised'] == s.malformed + s.failed, name
        assert sum(s.errors.values()) == s.malformed + s.failed, name
    # every processor still works on valid input afterwards
    assert valid_img is not None
    out = []
    for i in range(3):
        out += tracker.handle('image', img_io.array_to_image(textured(np.random.default_rng(1),
                                                                       i), 'rgb8', FAC,
                                                              10 ** 12 + i, 'cam'))
    assert sum(t == 'nrsfm/tracks' for t, _, _ in out) == 3
    reg.handle('reference', points_msg(rng, 0))
    assert len(reg.handle('points', points_msg(rng, 1))) == 4
    assert len(flow.handle('points', points_msg(rng, 10 ** 6))) == 2
    elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
    failed = {k: v for p in procs.values() for k, v in p.stats.errors.items()
              if k.split(':')[1][:1].isupper()}     # contained exceptions, by type
    print(f'fuzz: {sent} malformed + {MESSAGES - sent} valid messages in {elapsed:.1f} s '
          f'({cpu:.1f} s CPU); contained exceptions {failed}')
    # no message costs much: CPU time, not wall time, which a shared machine stretches (30 s
    # CPU in 49 s at load 2.5; 134 s wall at load ~8 failed the former wall-time bound)
    assert cpu < 60
