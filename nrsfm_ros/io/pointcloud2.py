"""sensor_msgs/PointCloud2 <-> NumPy.

Reading is zero-copy: ``np.frombuffer`` over ``msg.data`` with a structured dtype built from
``fields`` (offsets, ``point_step`` padding, ``row_step`` padding, ``count > 1``, big-endian).
Writing packs the columns straight into the one buffer the message keeps (for rclpy messages
its own ``array('B')``, grown in place: no copy, no per-element loop).

Every malformed message raises :class:`~nrsfm_ros.io.errors.MessageError` naming the field.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ..core.arrays import duplicates
from .errors import MessageError
from .msgtypes import MsgFactory

MSGTYPE = 'sensor_msgs/msg/PointCloud2'

# PointField datatype constants -> NumPy type (without byte order).
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)
_DATATYPES: dict[int, str] = {
    INT8: 'i1', UINT8: 'u1', INT16: 'i2', UINT16: 'u2',
    INT32: 'i4', UINT32: 'u4', FLOAT32: 'f4', FLOAT64: 'f8',
}
_FROM_NUMPY: dict[str, int] = {v: k for k, v in _DATATYPES.items()}


def dtype_from_fields(fields: Sequence[Any], point_step: int, is_bigendian: bool = False,
                      ) -> np.dtype:
    """Structured dtype (itemsize ``point_step``) for a list of PointField-like objects."""
    if point_step <= 0:
        raise MessageError('point_step', point_step, 'must be positive')
    order = '>' if is_bigendian else '<'
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    for i, f in enumerate(fields):
        name = str(f.name)
        if not name:
            raise MessageError(f'fields[{i}].name', name, 'empty field name')
        if name in names:
            raise MessageError(f'fields[{i}].name', name, 'duplicate field name')
        if int(f.datatype) not in _DATATYPES:
            raise MessageError(f'fields[{i}].datatype', int(f.datatype),
                               'unknown PointField datatype (expected 1..8)')
        count = int(f.count)
        if count < 1:
            # count 0 is seen in the wild and means 1.
            count = 1
        base = np.dtype(order + _DATATYPES[int(f.datatype)])
        size = base.itemsize * count
        offset = int(f.offset)
        if offset < 0 or offset + size > point_step:
            raise MessageError(f'fields[{i}].offset', offset,
                               f'field {name!r} ({size} bytes) does not fit point_step '
                               f'{point_step}')
        names.append(name)
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(offset)
    try:
        return np.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                         'itemsize': point_step})
    except ValueError as err:  # overlapping fields
        raise MessageError('fields', names, f'fields overlap: {err}') from err


def read_points(msg: Any) -> np.ndarray:
    """Structured array view of a PointCloud2, shape (height, width); no copy where possible."""
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    if height < 0 or width < 0:
        raise MessageError('height' if height < 0 else 'width', min(height, width),
                           'negative size')
    dtype = dtype_from_fields(msg.fields, point_step, bool(msg.is_bigendian))
    if row_step < width * point_step:
        raise MessageError('row_step', row_step,
                           f'smaller than width*point_step = {width * point_step}')
    buf = np.frombuffer(msg.data, dtype=np.uint8) if len(msg.data) else np.zeros(0, np.uint8)
    need = row_step * height
    if buf.size < need:
        raise MessageError('data', f'{buf.size} bytes',
                           f'expected row_step*height = {need} bytes')
    if height * width == 0:
        return np.zeros((height, width), dtype=dtype)
    # Zero-copy view honouring row padding (read-only when the buffer is).
    return np.ndarray(shape=(height, width), dtype=dtype, buffer=buf, offset=0,
                      strides=(row_step, point_step))


def field_names(msg: Any) -> list[str]:
    return [str(f.name) for f in msg.fields]


def read_fields(msg: Any, names: Sequence[str], dtype: Any = np.float32,
                skip_nans: bool = False) -> np.ndarray:
    """The named scalar fields as one (N, len(names)) array in native byte order.

    ``skip_nans`` drops points with a NaN in any requested field.  Raises MessageError if a
    field is missing.
    """
    points = read_points(msg).reshape(-1)
    present = set(points.dtype.names or ())
    for name in names:
        if name not in present:
            raise MessageError('fields', sorted(present), f'missing required field {name!r}')
    out = np.empty((points.shape[0], len(names)), dtype=dtype)
    for j, name in enumerate(names):
        col = points[name]
        if col.ndim != 1:
            raise MessageError(f'fields[{name}].count', col.shape[1:], 'expected count 1')
        out[:, j] = col
    if skip_nans and out.size:
        out = out[~np.isnan(out).any(axis=1)]
    return out


def read_xyz(msg: Any, skip_nans: bool = True) -> np.ndarray:
    """(N, 3) float64 x, y, z."""
    return read_fields(msg, ('x', 'y', 'z'), np.float64, skip_nans)


def has_fields(msg: Any, names: Sequence[str]) -> bool:
    present = set(field_names(msg))
    return all(n in present for n in names)


def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 r, g, b -> (N,) float32 holding 0x00RRGGBB bits (the PCL convention)."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 2 or rgb.shape[1] != 3:
        raise ValueError(f'rgb: expected shape (N, 3), got {rgb.shape}')
    c = rgb.astype(np.uint32)
    return ((c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]).view(np.float32)


def unpack_rgb(packed: np.ndarray) -> np.ndarray:
    """(N,) float32 packed rgb -> (N, 3) uint8."""
    bits = np.ascontiguousarray(packed, dtype=np.float32).view(np.uint32)
    return np.stack([(bits >> 16) & 255, (bits >> 8) & 255, bits & 255], axis=1).astype(np.uint8)


# Columns are written into the message buffer in blocks of about this many bytes of output, so
# the destination block stays in cache while every field of it is written (a whole-column pass
# per field streams the full buffer once per field).
_BLOCK_BYTES = 1 << 18


def _column_layout(columns: Mapping[str, np.ndarray]) -> tuple[dict[str, np.ndarray], np.dtype]:
    """Checked columns and the packed little-endian structured dtype they make, in their order."""
    if not columns:
        raise ValueError('columns: at least one field is needed')
    arrays = {k: np.asarray(v) for k, v in columns.items()}
    n = {k: v.shape[0] if v.ndim else None for k, v in arrays.items()}
    for k, v in arrays.items():
        if v.ndim != 1:
            raise ValueError(f'columns[{k!r}]: expected a 1-D array, got shape {v.shape}')
        if v.dtype.str[1:] not in _FROM_NUMPY:
            raise ValueError(f'columns[{k!r}]: dtype {v.dtype} has no PointField datatype')
    if len(set(n.values())) != 1:
        raise ValueError(f'columns: all fields need the same length, got {n}')
    return arrays, np.dtype([(k, v.dtype.newbyteorder('<')) for k, v in arrays.items()])


def _fill(out: np.ndarray, arrays: Mapping[str, np.ndarray]) -> None:
    """Write each column into its field of the structured (N,) ``out``, block by block."""
    n = out.shape[0]
    step = max(1, _BLOCK_BYTES // max(out.dtype.itemsize, 1))
    pairs = [(out[k], v) for k, v in arrays.items()]
    if n <= step:
        for dst, src in pairs:
            dst[...] = src
        return
    for s in range(0, n, step):
        e = s + step
        for dst, src in pairs:
            dst[s:e] = src[s:e]


def pack(columns: Mapping[str, np.ndarray], shape: tuple[int, int] | None = None) -> np.ndarray:
    """Columns (name -> (N,) array) -> one packed structured array (N,) in their dtypes."""
    arrays, dtype = _column_layout(columns)
    out = np.empty(next(iter(arrays.values())).shape[0], dtype=dtype)
    _fill(out, arrays)
    return out


def _has_nan(arrays: Mapping[str, np.ndarray]) -> bool:
    return any(v.dtype.kind == 'f' and bool(np.isnan(v).any()) for v in arrays.values())


def to_msg(points: np.ndarray | Mapping[str, np.ndarray], factory: MsgFactory, stamp_ns: int,
           frame_id: str, height: int = 1, is_dense: bool | None = None) -> Any:
    """Build a PointCloud2 from a structured array or a mapping of columns.

    ``height > 1`` makes an organised cloud (N must equal height*width).  ``is_dense`` defaults to
    "no NaN in any float field".  Columns are packed straight into the one buffer the message
    keeps (fields in mapping order, no padding, little-endian); a structured array is copied
    byte for byte.  rclpy: that buffer is the message's own ``array('B')``, grown in place
    after construction (``data=`` in the constructor copies twice, and each extra buffer of a
    large cloud costs its page faults again once the allocator hands the memory back).
    """
    if isinstance(points, np.ndarray):
        if points.dtype.names is None:
            raise ValueError('points: expected a structured array or a mapping of columns')
        flat = np.ascontiguousarray(points.reshape(-1))
        dtype, n = flat.dtype, flat.shape[0]
        arrays = None
    else:
        arrays, dtype = _column_layout(points)
        n = next(iter(arrays.values())).shape[0]
    if height < 1 or n % height:
        raise ValueError(f'height: {height} does not divide the number of points {n}')
    width = n // height
    names = dtype.names or ()
    fields = []
    for name in names:
        ftype, offset = dtype.fields[name][:2]
        base, count = (ftype.base, int(np.prod(ftype.shape))) if ftype.shape else (ftype, 1)
        if base.byteorder == '>':
            raise ValueError(f'points[{name!r}]: write little-endian data')
        if base.str[1:] not in _FROM_NUMPY:
            raise ValueError(f'points[{name!r}]: dtype {base} has no PointField datatype')
        fields.append(factory.make('sensor_msgs/msg/PointField', name=name, offset=int(offset),
                                   datatype=_FROM_NUMPY[base.str[1:]], count=count))
    if is_dense is None:
        is_dense = not _has_nan(arrays if arrays is not None else {k: flat[k] for k in names})
    meta = dict(header=factory.header(stamp_ns, frame_id), height=height, width=width,
                fields=fields, is_bigendian=False, point_step=dtype.itemsize,
                row_step=dtype.itemsize * width, is_dense=bool(is_dense))
    nbytes = n * dtype.itemsize
    if factory.backend == 'rclpy':
        # grow the message's own (empty) array('B') in place: one memset, no second buffer
        msg = factory.make(MSGTYPE, **meta)
        data = msg.data
        data.append(0)
        data *= nbytes
        raw = np.frombuffer(data, np.uint8) if nbytes else np.zeros(0, np.uint8)
    else:
        raw = np.empty(nbytes, np.uint8)
        msg = factory.make(MSGTYPE, data=raw, **meta)
    if arrays is None:
        raw[...] = flat.view(np.uint8).reshape(-1)
    else:
        _fill(raw.view(dtype), arrays)
    return msg


def check_cloud(msg: Any, required: Sequence[str], optional: Sequence[str] = (),
                limit: float = np.inf) -> None:
    """The input rule of every cloud a node reads (raises MessageError naming the field).

    A cloud is rejected, never repaired, when its layout does not parse, a ``required`` field is
    missing, a field it uses (``required`` and the ``optional`` ones present) has ``count`` != 1,
    a used numeric field other than ``rgb`` holds +-inf or a magnitude above ``limit``, or
    ``track_id`` is not an integer field of at most 32 bits or repeats a value.  NaN is
    allowed: it is the PointCloud2 convention for "no value" and each stage skips such points.
    """
    points = read_points(msg).reshape(-1)
    present = set(points.dtype.names or ())
    for name in required:
        if name not in present:
            raise MessageError('fields', sorted(present), f'missing required field {name!r}')
    used = [n for n in (*required, *optional) if n in present]
    for name in used:
        col = points[name]
        if col.ndim != 1:
            raise MessageError(f'fields[{name}].count', int(np.prod(col.shape[1:])),
                               'expected count 1')
        if name == 'rgb' or col.dtype.kind != 'f' or not col.size:
            continue
        with np.errstate(invalid='ignore'):
            big = np.abs(col.astype(np.float64)) > limit
        if big.any():
            worst = col[big][0]
            raise MessageError(name, f'{int(big.sum())} value(s) like {worst}',
                               'infinite values are rejected (NaN marks a missing value)'
                               if np.isinf(worst) else f'magnitude above {limit:g}')
    if 'track_id' in used:
        kind = points.dtype['track_id']
        if kind.kind not in 'iu' or kind.itemsize > 4:
            raise MessageError('fields[track_id].datatype', str(kind),
                               'track ids must be an integer field of at most 32 bits')
    if 'track_id' in used and points.size:
        ids = points['track_id']
        dup = duplicates(ids)
        if dup:
            raise MessageError('track_id', f'{dup} duplicate(s)',
                               'track ids must be unique within a cloud')
