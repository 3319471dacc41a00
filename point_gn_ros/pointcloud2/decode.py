"""PointCloud2 decoding: bytes viewed in place, only the requested fields copied out.

Duck-typed: any object with the PointCloud2 attributes (``height``, ``width``, ``fields``
[``name``, ``offset``, ``datatype``, ``count``], ``is_bigendian``, ``point_step``,
``row_step``, ``data``) works, so tests and tools can use simple stand-ins. The bytes are viewed
through a numpy structured dtype with explicit strides (row padding included). Every
malformation raises ``DecodeError`` with a short reason.
"""

from __future__ import annotations

import array
import operator
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from point_gn_ros.errors import DecodeError

# sensor_msgs/PointField datatype constants (duplicated so decoding needs no ROS import).
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)

# datatype -> numpy type (byte order is applied per message).
POINTFIELD_DTYPES: dict[int, np.dtype] = {
    INT8: np.dtype(np.int8),
    UINT8: np.dtype(np.uint8),
    INT16: np.dtype(np.int16),
    UINT16: np.dtype(np.uint16),
    INT32: np.dtype(np.int32),
    UINT32: np.dtype(np.uint32),
    FLOAT32: np.dtype(np.float32),
    FLOAT64: np.dtype(np.float64),
}
_DATATYPE_OF: dict[np.dtype, int] = {dt: code for code, dt in POINTFIELD_DTYPES.items()}
_DATATYPE_NAMES = {
    INT8: 'INT8', UINT8: 'UINT8', INT16: 'INT16', UINT16: 'UINT16',
    INT32: 'INT32', UINT32: 'UINT32', FLOAT32: 'FLOAT32', FLOAT64: 'FLOAT64',
}

DEFAULT_MAX_POINTS = 5_000_000
# Sizes, steps, offsets and counts must stay below this: numpy dtypes and strides are C ints,
# and the ~/classifications segment_id is an INT32. Checked here, at the boundary, so nothing
# downstream can overflow (sensor_msgs declares them uint32, up to 2**32 - 1).
INT32_LIMIT = 2**31
_XYZ = ('x', 'y', 'z')
_MSG_ATTRS = ('height', 'width', 'fields', 'is_bigendian', 'point_step', 'row_step', 'data')


@dataclass
class DecodedCloud:
    """Result of ``decode_xyz``.

    xyz: (N, 3) float32, finite points only, C-contiguous.
    fields: name -> (N,) array (native byte order, the field's own dtype) for each requested
        extra field, rows aligned with ``xyz``.
    n_dropped_nonfinite: how many points were removed because x, y or z was NaN/inf.
    height, width: the message's grid shape (before NaN removal), for organized clouds.
    """

    xyz: np.ndarray
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    n_dropped_nonfinite: int = 0
    height: int = 1
    width: int = 0

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


# --------------------------------------------------------------------------------------------
# decoding


def _as_int(value: Any, what: str, bounded: bool = True) -> int:
    """The value as an int (``bounded``: in [-2**31, 2**31), a C int), else DecodeError."""
    try:
        out = operator.index(value)
    except TypeError:
        raise DecodeError(f'{what} is not an integer ({value!r})') from None
    if bounded and not -INT32_LIMIT <= out < INT32_LIMIT:
        raise DecodeError(f'{what} {out} is out of range (must be below 2**31)')
    return out


def _byte_buffer(data: Any) -> np.ndarray:
    """View ``msg.data`` as a 1-D uint8 array: zero copy for bytes-like objects.

    rclpy hands over ``array.array('B')`` (deserialised) or whatever was assigned (bytes, list).
    """
    if isinstance(data, (bytes, bytearray, memoryview, array.array)):
        try:
            mv = memoryview(data)
            if mv.itemsize == 1 and mv.contiguous:
                return np.frombuffer(mv.cast('B') if mv.format != 'B' else mv, dtype=np.uint8)
        except (TypeError, ValueError):
            pass
    if isinstance(data, np.ndarray) and data.dtype == np.uint8 and data.ndim == 1:
        return np.ascontiguousarray(data)  # a no-op unless someone passed a strided slice
    if isinstance(data, (str, bytes)) or data is None:
        raise DecodeError(f'data is not a byte sequence ({type(data).__name__})')
    # Lists / tuples / odd arrays of ints: one C-level conversion, values must be bytes.
    try:
        arr = np.asarray(data)
    except (TypeError, ValueError):
        raise DecodeError(f'data is not a byte sequence ({type(data).__name__})') from None
    if arr.ndim != 1 or (arr.size and arr.dtype.kind not in 'iub'):
        raise DecodeError(f'data is not a byte sequence ({type(data).__name__})')
    if arr.size and (int(arr.min()) < 0 or int(arr.max()) > 255):
        raise DecodeError('data holds values outside 0..255')
    return arr.astype(np.uint8, copy=False)


@dataclass(frozen=True)
class _Field:
    name: str
    offset: int
    datatype: int
    count: int


def _index_fields(fields: Any) -> dict[str, list[_Field]]:
    """Map field name -> all PointFields with that name (duplicates are kept for reporting)."""
    try:
        items = list(fields)
    except TypeError:
        raise DecodeError('fields is not a sequence') from None
    out: dict[str, list[_Field]] = {}
    for f in items:
        try:
            name, offset, datatype, count = f.name, f.offset, f.datatype, f.count
        except AttributeError as exc:
            raise DecodeError(f'malformed PointField ({exc})') from None
        if not isinstance(name, str):
            continue  # cannot be requested by name; ignore like any other unused field
        # Range-checked only once requested: an unused field's values cannot hurt.
        out.setdefault(name, []).append(_Field(
            name, _as_int(offset, f'field {name!r} offset', bounded=False),
            _as_int(datatype, f'field {name!r} datatype', bounded=False),
            _as_int(count, f'field {name!r} count', bounded=False)))
    return out


def _structured_view(msg: Any, names: Sequence[str], *, max_points: int,
                     allow_empty: bool) -> tuple[np.ndarray, int, int, np.dtype]:
    """Validate ``msg`` and view its points as a structured array of shape (height, width).

    Only the fields in ``names`` are validated and exposed (one scalar per field: the first
    element when count > 1). Returns (view, height, width, the view's dtype); the view
    shares memory with ``msg.data`` whenever that is bytes-like.
    """
    try:
        attrs = {a: getattr(msg, a) for a in _MSG_ATTRS}
    except AttributeError as exc:
        raise DecodeError(f'not a PointCloud2 ({exc})') from None
    height = _as_int(attrs['height'], 'height')
    width = _as_int(attrs['width'], 'width')
    point_step = _as_int(attrs['point_step'], 'point_step')
    row_step = _as_int(attrs['row_step'], 'row_step')
    if height < 0 or width < 0 or point_step < 0 or row_step < 0:
        raise DecodeError('negative height/width/point_step/row_step')
    n = height * width
    if n == 0 and not allow_empty:
        raise DecodeError(f'cloud is empty (width={width}, height={height})')
    if n > max_points:
        raise DecodeError(f'too many points: {n:,} > max_points={max_points:,}')

    by_name = _index_fields(attrs['fields'])
    order = '>' if bool(attrs['is_bigendian']) else '<'
    formats, offsets = [], []
    for name in names:
        found = by_name.get(name)
        if not found:
            have = ', '.join(sorted(by_name)) or 'none'
            raise DecodeError(f'missing field {name!r} (fields: {have})')
        if len(found) > 1:
            raise DecodeError(f'field {name!r} appears {len(found)} times')
        f = found[0]
        _as_int(f.offset, f'field {name!r} offset')
        _as_int(f.count, f'field {name!r} count')
        base = POINTFIELD_DTYPES.get(f.datatype)
        if base is None:
            raise DecodeError(f'field {name!r} has unsupported datatype {f.datatype}')
        if f.count < 0:
            raise DecodeError(f'field {name!r} has negative count {f.count}')
        # count == 0 is a common publisher slip (PointField() defaults to 0): read one value.
        extent = f.offset + base.itemsize * max(f.count, 1)
        if f.offset < 0 or extent > point_step:
            raise DecodeError(f'field {name!r} (offset {f.offset}, {extent - f.offset} bytes) '
                              f'does not fit in point_step {point_step}')
        formats.append(base.newbyteorder(order))
        offsets.append(f.offset)
    if row_step < width * point_step:
        raise DecodeError(f'row_step {row_step} < width*point_step {width * point_step}')

    buf = _byte_buffer(attrs['data'])
    if buf.size != row_step * height:
        raise DecodeError(f'data has {buf.size} bytes, expected row_step*height = '
                          f'{row_step * height}')
    dtype = np.dtype({'names': list(names), 'formats': formats, 'offsets': offsets,
                      'itemsize': max(point_step, 1)})
    if n == 0:
        return np.empty((height, width), dtype=dtype), height, width, dtype
    # Strided view straight onto the message bytes: row padding is skipped via strides.
    view = np.ndarray(shape=(height, width), dtype=dtype, buffer=buf,
                      strides=(row_step, point_step))
    return view, height, width, dtype


def _column(view: np.ndarray, name: str, out_dtype: np.dtype | type | None = None) -> np.ndarray:
    """Copy one field of a (H, W) structured view into a contiguous native (H*W,) array."""
    src = view[name]
    dt = np.dtype(out_dtype) if out_dtype is not None else src.dtype.newbyteorder('=')
    out = np.empty(src.shape, dtype=dt)
    with np.errstate(over='ignore', invalid='ignore'):  # FLOAT64 -> FLOAT32 overflow is inf
        out[...] = src
    return out.reshape(-1)


def decode_xyz(msg: Any, extra_fields: Sequence[str] = (), *,
               max_points: int = DEFAULT_MAX_POINTS, allow_empty: bool = False) -> DecodedCloud:
    """Decode x, y, z (and optional extra fields) from a PointCloud2-like message.

    Handles any field order/offsets/padding, row padding (row_step > width*point_step),
    organized clouds (height > 1, flattened row-major), big-endian data, FLOAT32/FLOAT64 x/y/z,
    every PointField datatype for extras, and count > 1 fields (the first element is used).
    Points whose x, y or z is not finite (after conversion to float32) are removed whatever
    ``is_dense`` says.

    Returns DecodedCloud with xyz (N, 3) float32 and fields name -> (N,) arrays.
    Raises DecodeError on malformed messages, on empty clouds (unless ``allow_empty``: an
    empty grid or all-non-finite cloud then decodes to N = 0) and on clouds with more than
    ``max_points`` points.
    """
    if isinstance(extra_fields, str):
        extra_fields = (extra_fields,)  # a lone name is a common slip; don't split it per char
    extra_fields = tuple(extra_fields)  # may be a one-shot iterable; it is walked twice
    names = list(dict.fromkeys([*_XYZ, *extra_fields]))
    view, height, width, _ = _structured_view(msg, names, max_points=max_points,
                                              allow_empty=allow_empty)
    n = height * width
    xyz = np.empty((height, width, 3), dtype=np.float32)
    with np.errstate(over='ignore', invalid='ignore'):
        for i, axis in enumerate(_XYZ):
            xyz[..., i] = view[axis]
    xyz = xyz.reshape(n, 3)
    fields = {name: _column(view, name) for name in extra_fields}

    ok = np.isfinite(xyz)
    if ok.all():  # common case; a flat check is ~40x cheaper than .all(axis=1)
        n_keep = n
    else:  # only pay for the row mask and the gather when something must go
        finite = ok[:, 0] & ok[:, 1] & ok[:, 2]
        n_keep = int(np.count_nonzero(finite))
        if n_keep == 0 and not allow_empty:
            raise DecodeError(f'all {n} points have non-finite x/y/z')
        xyz = np.compress(finite, xyz, axis=0)  # ~2x faster than xyz[finite] for (N, 3)
        fields = {k: v[finite] for k, v in fields.items()}
    return DecodedCloud(xyz=xyz, fields=fields, n_dropped_nonfinite=n - n_keep,
                        height=height, width=width)


def split_segments(decoded: DecodedCloud, field_name: str, *,
                   skip_ids: Iterable[int] = (), skip_negative: bool = False,
                   skip_type_max: bool = False) -> list[tuple[int, np.ndarray]]:
    """Split a decoded cloud into objects by an integer segment field.

    ``field_name`` must have been requested via ``decode_xyz(..., extra_fields=[field_name])``.
    Float fields are accepted when every value is a finite integer. ``skip_ids`` drops e.g. a
    background label; ``skip_negative`` every id < 0; ``skip_type_max`` the largest value of an
    unsigned integer field's type (0xFFFFFFFF for UINT32, 65535 for UINT16, 255 for UINT8: a
    common "no label"). Returns [(segment_id, xyz (M_i, 3) float32)] sorted by id; each segment
    keeps the original point order. Raises DecodeError for non-integer ids and for ids (not
    skipped) outside the int32 range, which the ``~/classifications`` segment_id cannot carry.
    """
    if field_name not in decoded.fields:
        raise DecodeError(f'segment field {field_name!r} was not decoded '
                          f'(have: {", ".join(decoded.fields) or "none"})')
    ids = decoded.fields[field_name]
    skip = {int(s) for s in skip_ids}
    if skip_type_max and ids.dtype.kind == 'u':
        skip.add(int(np.iinfo(ids.dtype).max))
    if ids.shape[0] != decoded.xyz.shape[0]:
        raise DecodeError(f'segment field {field_name!r} has {ids.shape[0]} values for '
                          f'{decoded.xyz.shape[0]} points')
    if ids.dtype.kind == 'f':
        if not (np.isfinite(ids).all() and np.array_equal(ids, np.round(ids))):
            raise DecodeError(f'segment field {field_name!r} holds non-integer values')
        if ids.size and np.abs(ids).max() > 2.0**53:
            raise DecodeError(f'segment field {field_name!r} holds values too large for ids')
        ids = ids.astype(np.int64)
    elif ids.dtype.kind == 'b':
        ids = ids.astype(np.uint8)
    elif ids.dtype.kind not in 'iu':
        raise DecodeError(f'segment field {field_name!r} is not numeric ({ids.dtype})')
    if ids.size == 0:
        return []
    lo, hi = int(ids.min()), int(ids.max())
    # Stable sort so points keep their order within a segment. A small id range is shifted
    # into uint8/uint16, where numpy's stable sort is an O(N) radix sort (~10x faster).
    if hi - lo < 65536:
        key = (ids - ids.dtype.type(lo)).astype(np.uint8 if hi - lo < 256 else np.uint16)
        order = np.argsort(key, kind='stable')
    else:
        order = np.argsort(ids, kind='stable')
    sorted_ids = ids[order]
    starts = np.concatenate(([0], np.flatnonzero(sorted_ids[1:] != sorted_ids[:-1]) + 1))
    xyz_sorted = np.take(decoded.xyz, order, axis=0)  # np.take: much faster than xyz[order]
    out = []
    for start, chunk in zip(starts, np.split(xyz_sorted, starts[1:]), strict=True):
        seg_id = int(sorted_ids[start])
        if seg_id in skip or (skip_negative and seg_id < 0):
            continue
        if not -INT32_LIMIT <= seg_id < INT32_LIMIT:  # the answer's segment_id is an INT32
            raise DecodeError(f'segment field {field_name!r} holds an id out of range for '
                              f'segment_id ({seg_id} does not fit in int32)')
        out.append((seg_id, chunk))
    return out
