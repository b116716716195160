"""PointCloud2 build benchmark: NumPy columns -> message, per layout, size and backend.

    .venv/bin/python bench/bench_pointcloud2.py [--repeat 200] [--sizes 5000,100000,1000000]
                                                [--json out.json]

Times ``pointcloud2.to_msg`` (the current code) against ``legacy_to_msg`` below (the code before
issue 17: pack a structured array, then hand ``view(uint8)`` to the factory, which copies it into
an ``array('B')``, which the rclpy constructor copies again and its setter a third time), in the
same process and loop, so both see the same machine load.  Medians and p90 of ``--repeat`` runs
(fewer at 1M points).  Layouts are the clouds the nodes publish: ``xyz+id`` (registrar, bag
ground truth, 16 B/point), ``tracks`` (tracker: u, v, track_id, visibility, rgb, occlusion;
24 B) and ``scene_flow`` (x, y, z, vx, vy, vz, track_id; 28 B).  Every row also checks that both
builds give identical bytes and fields.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from nrsfm_ros.io import pointcloud2 as pc2  # noqa: E402
from nrsfm_ros.io.msgtypes import MsgFactory, RclpyFactory, RosbagsFactory  # noqa: E402


def legacy_to_msg(columns: Mapping[str, np.ndarray], factory: MsgFactory, stamp_ns: int,
                  frame_id: str) -> Any:
    """to_msg as it was before issue 17 (mapping input, height 1), kept as the reference."""
    arrays = {k: np.asarray(v) for k, v in columns.items()}
    dtype = np.dtype([(k, v.dtype.newbyteorder('<')) for k, v in arrays.items()])
    points = np.empty(next(iter(arrays.values())).shape[0], dtype=dtype)
    for k, v in arrays.items():
        points[k] = v
    fields = []
    for name in points.dtype.names:
        ftype, offset = points.dtype.fields[name][:2]
        fields.append(factory.make('sensor_msgs/msg/PointField', name=name, offset=int(offset),
                                   datatype=pc2._FROM_NUMPY[ftype.str[1:]], count=1))
    is_dense = not any(points.dtype[n].kind == 'f' and np.isnan(points[n]).any()
                       for n in points.dtype.names)
    n = points.shape[0]
    return factory.make(
        pc2.MSGTYPE, header=factory.header(stamp_ns, frame_id), height=1, width=n,
        fields=fields, is_bigendian=False, point_step=points.dtype.itemsize,
        row_step=points.dtype.itemsize * n, data=points.view(np.uint8), is_dense=is_dense)


def layouts(n: int) -> dict[str, dict[str, np.ndarray]]:
    rng = np.random.default_rng(0)
    X = rng.normal(size=(n, 3)).astype(np.float32)
    V = rng.normal(size=(n, 3)).astype(np.float32)
    ids = np.arange(n, dtype=np.uint32)
    rgb = pc2.pack_rgb(rng.integers(0, 256, (n, 3)).astype(np.uint8))
    vis = (rng.random(n) > 0.1).astype(np.float32)
    return {
        'xyz+id': {'x': X[:, 0], 'y': X[:, 1], 'z': X[:, 2], 'track_id': ids},
        'tracks': {'u': X[:, 0], 'v': X[:, 1], 'track_id': ids, 'visibility': vis, 'rgb': rgb,
                   'occlusion': 1 - vis},
        'scene_flow': {'x': X[:, 0], 'y': X[:, 1], 'z': X[:, 2], 'vx': V[:, 0], 'vy': V[:, 1],
                       'vz': V[:, 2], 'track_id': ids},
    }


def times_ms(fn: Callable[[], Any], repeat: int) -> tuple[float, float]:
    fn()                                            # warm (imports, class caches)
    t = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        t.append((time.perf_counter() - t0) * 1e3)
    t.sort()
    return statistics.median(t), t[int(0.9 * (len(t) - 1))]


def same(a: Any, b: Any) -> bool:
    fa = [(f.name, f.offset, f.datatype, f.count) for f in a.fields]
    fb = [(f.name, f.offset, f.datatype, f.count) for f in b.fields]
    return (fa == fb and bytes(a.data) == bytes(b.data) and a.point_step == b.point_step
            and a.row_step == b.row_step and a.width == b.width and a.is_dense == b.is_dense)


def rows(sizes: list[int], repeat: int) -> list[dict[str, Any]]:
    out = []
    for backend, fac in (('rclpy', RclpyFactory()), ('rosbags', RosbagsFactory())):
        for n in sizes:
            r = max(5, repeat // 20) if n >= 1_000_000 else repeat
            for name, cols in layouts(n).items():
                new = times_ms(lambda: pc2.to_msg(cols, fac, 0, 'cam'), r)
                old = times_ms(lambda: legacy_to_msg(cols, fac, 0, 'cam'), r)
                ok = same(pc2.to_msg(cols, fac, 0, 'cam'), legacy_to_msg(cols, fac, 0, 'cam'))
                out.append({'backend': backend, 'points': n, 'layout': name,
                            'bytes': n * sum(v.dtype.itemsize for v in cols.values()),
                            'new_p50_ms': new[0], 'new_p90_ms': new[1],
                            'old_p50_ms': old[0], 'old_p90_ms': old[1],
                            'speedup': old[0] / new[0], 'identical_bytes': ok})
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--repeat', type=int, default=200)
    p.add_argument('--sizes', default='5000,100000,1000000')
    p.add_argument('--json', default=None)
    args = p.parse_args()
    sizes = [int(s) for s in args.sizes.split(',')]
    table = rows(sizes, args.repeat)
    print('| backend | points | layout | MB | to_msg p50 (ms) | p90 | legacy p50 (ms) | p90 | '
          'speed-up | same bytes |')
    print('|---|---|---|---|---|---|---|---|---|---|')
    for r in table:
        print(f"| {r['backend']} | {r['points']:,} | {r['layout']} | {r['bytes'] / 1e6:.2f} | "
              f"{r['new_p50_ms']:.3f} | {r['new_p90_ms']:.3f} | {r['old_p50_ms']:.3f} | "
              f"{r['old_p90_ms']:.3f} | {r['speedup']:.1f}x | {r['identical_bytes']} |")
    if args.json:
        Path(args.json).write_text(json.dumps(table, indent=2))
    return 0 if all(r['identical_bytes'] for r in table) else 1


if __name__ == '__main__':
    sys.exit(main())
