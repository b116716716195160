"""PLY files of point clouds: binary write, ascii and binary read (renders: nrsfm_ros.render)."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def write_ply(path: str | Path, points: np.ndarray, rgb: np.ndarray | None = None) -> None:
    """Binary little-endian PLY with x, y, z (float32) and optional red, green, blue (uint8)."""
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f'points: expected shape (N, 3), got {points.shape}')
    cols = [('x', 'f4'), ('y', 'f4'), ('z', 'f4')]
    if rgb is not None:
        cols += [('red', 'u1'), ('green', 'u1'), ('blue', 'u1')]
    arr = np.empty(points.shape[0], dtype=cols)
    arr['x'], arr['y'], arr['z'] = points.T
    if rgb is not None:
        rgb = np.asarray(rgb, dtype=np.uint8)
        arr['red'], arr['green'], arr['blue'] = rgb.T
    header = ['ply', 'format binary_little_endian 1.0', f'element vertex {points.shape[0]}']
    names = {'f4': 'float', 'u1': 'uchar'}
    header += [f'property {names[t]} {n}' for n, t in cols] + ['end_header']
    with open(path, 'wb') as fh:
        fh.write(('\n'.join(header) + '\n').encode())
        fh.write(arr.tobytes())


def read_ply(path: str | Path) -> np.ndarray:
    """x, y, z (N, 3) float64 of a PLY vertex element (ascii, binary little- or big-endian)."""
    data = Path(path).read_bytes()
    end = data.find(b'end_header')
    if not data.startswith(b'ply') or end < 0:
        raise ValueError(f'{path}: not a PLY file')
    header = data[:end].decode('ascii', 'replace').splitlines()
    body = data[data.index(b'\n', end) + 1:]
    fmt = next((h.split()[1] for h in header if h.startswith('format')), '')
    count, props, in_vertex = 0, [], False
    types = {'float': 'f4', 'float32': 'f4', 'double': 'f8', 'float64': 'f8', 'uchar': 'u1',
             'uint8': 'u1', 'char': 'i1', 'int8': 'i1', 'short': 'i2', 'int16': 'i2',
             'ushort': 'u2', 'uint16': 'u2', 'int': 'i4', 'int32': 'i4', 'uint': 'u4',
             'uint32': 'u4'}
    for h in header:
        parts = h.split()
        if parts[:1] == ['element']:
            in_vertex = parts[1] == 'vertex'
            if in_vertex:
                try:
                    count = int(parts[2])
                except (IndexError, ValueError) as err:
                    raise ValueError(f'{path}: bad element line {h!r}') from err
        elif parts[:1] == ['property'] and in_vertex:
            if parts[1] == 'list':
                raise ValueError(f'{path}: list properties in the vertex element are unsupported')
            if len(parts) < 3 or parts[1] not in types:
                raise ValueError(f'{path}: unsupported property line {h!r}')
            props.append((parts[2], types[parts[1]]))
    names = [n for n, _ in props]
    if not {'x', 'y', 'z'} <= set(names):
        raise ValueError(f'{path}: the vertex element has no x, y, z properties ({names})')
    if fmt == 'ascii':
        rows = [r.split() for r in body.decode('ascii', 'replace').splitlines() if r.strip()]
        if len(rows) < count or any(len(r) < len(props) for r in rows[:count]):
            raise ValueError(f'{path}: truncated: header says {count} vertices, the file has '
                             f'{sum(len(r) >= len(props) for r in rows[:count])} complete ones')
        try:
            arr = np.array([r[:len(props)] for r in rows[:count]], dtype=np.float64)
        except ValueError as err:
            raise ValueError(f'{path}: a vertex row is not numeric ({err})') from err
        return arr.reshape(count, len(props))[:, [names.index(a) for a in 'xyz']]
    order = {'binary_little_endian': '<', 'binary_big_endian': '>'}.get(fmt)
    if order is None:
        raise ValueError(f'{path}: unsupported PLY format {fmt!r}')
    dt = np.dtype([(n, order + t) for n, t in props])
    if len(body) < dt.itemsize * count:
        raise ValueError(f'{path}: truncated: header says {count} vertices, the file holds '
                         f'{len(body) // dt.itemsize}')
    arr = np.frombuffer(body[:dt.itemsize * count], dtype=dt)
    return np.stack([arr['x'], arr['y'], arr['z']], axis=1).astype(np.float64)
