"""PointCloud2 encoding: real ``sensor_msgs.msg.PointCloud2`` messages (imported lazily).

Packed and little-endian, ``data`` handed over as ``array.array('B')`` so rclpy does no
per-byte checks.
"""

from __future__ import annotations

import array
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from point_gn_ros.pointcloud2.decode import _DATATYPE_OF, _XYZ


def _field_dtype(name: str, arr: np.ndarray) -> np.ndarray:
    """Return ``arr`` cast to the PointField type that represents it (int64 -> int32, ...)."""
    kind, size = arr.dtype.kind, arr.dtype.itemsize
    if kind == 'b':
        return arr.astype(np.uint8)
    if kind == 'f' and size < 4:
        return arr.astype(np.float32)
    if kind in 'iu' and size == 8:  # no 64-bit ints in PointField: narrow when values fit
        target = np.dtype(np.int32 if kind == 'i' else np.uint32)
        info = np.iinfo(target)
        if arr.size and (arr.min() < info.min or arr.max() > info.max):
            raise ValueError(f'field {name!r}: {arr.dtype} values do not fit in {target}')
        return arr.astype(target)
    if arr.dtype.newbyteorder('=') not in _DATATYPE_OF:
        raise ValueError(f'field {name!r}: dtype {arr.dtype} has no PointField datatype')
    return arr


def _header(header: Any, frame_id: str | None) -> Any:
    from std_msgs.msg import Header

    if header is None:
        header = Header()
    if frame_id is not None:
        header = Header(stamp=header.stamp, frame_id=frame_id)  # don't mutate the caller's
    return header


def make_pointcloud2(header: Any, arrays: Mapping[str, np.ndarray], *,
                     frame_id: str | None = None, height: int = 1,
                     is_dense: bool | None = None) -> Any:
    """Build a packed little-endian sensor_msgs.msg.PointCloud2 from named (N,) arrays.

    Fields are laid out in ``arrays`` order with no padding; datatypes follow the array
    dtypes (int8..float64; bool -> UINT8, float16 -> FLOAT32, int64/uint64 -> INT32/UINT32
    when the values fit, else ValueError). ``header`` may be None (empty Header);
    ``frame_id`` overrides its frame. ``height`` > 1 makes an organized cloud of width
    N / height. ``is_dense`` defaults to "x/y/z all finite".
    """
    cols: dict[str, np.ndarray] = {}
    n = None
    for name, values in arrays.items():
        arr = np.asarray(values)
        if arr.ndim != 1:
            raise ValueError(f'field {name!r} must be 1-D (N,), got shape {arr.shape}')
        if n is None:
            n = arr.shape[0]
        elif arr.shape[0] != n:
            raise ValueError(f'field {name!r} has {arr.shape[0]} values, expected {n}')
        cols[name] = _field_dtype(name, arr)
    n = n or 0
    if height < 1 or n % height:
        raise ValueError(f'{n} points cannot form an organized cloud of height {height}')

    offsets, formats, spec = [], [], []
    offset = 0
    for name, arr in cols.items():
        native = arr.dtype.newbyteorder('=')
        offsets.append(offset)
        formats.append(native.newbyteorder('<'))
        spec.append((name, offset, _DATATYPE_OF[native]))
        offset += native.itemsize
    point_step = offset
    rec = np.empty(n, dtype=np.dtype({'names': list(cols), 'formats': formats,
                                      'offsets': offsets, 'itemsize': point_step}))
    for name, arr in cols.items():
        rec[name] = arr
    if is_dense is None:
        is_dense = all(bool(np.isfinite(cols[a]).all()) for a in _XYZ
                       if a in cols and cols[a].dtype.kind == 'f')
    return assemble_pointcloud2(header, rec, spec, point_step, frame_id=frame_id,
                                height=height, is_dense=bool(is_dense))


def assemble_pointcloud2(header: Any, rec: np.ndarray, spec: Sequence[tuple[str, int, int]],
                         point_step: int, *, frame_id: str | None = None, height: int = 1,
                         is_dense: bool = True) -> Any:
    """The PointCloud2 of packed little-endian records.

    rec: (N,) records of point_step bytes; spec: (name, offset, PointField datatype) per
    field, count 1. The caller has checked the layout (make_pointcloud2, make_classifications).
    """
    from sensor_msgs.msg import PointCloud2, PointField

    n = rec.shape[0]
    data = array.array('B')
    data.frombytes(rec.view(np.uint8) if n and point_step else b'')  # one copy, no loop
    msg = PointCloud2()
    msg.header = _header(header, frame_id)
    msg.height = height if n else 1
    msg.width = n // height if n else 0
    msg.fields = [PointField(name=name, offset=off, datatype=dt, count=1)
                  for name, off, dt in spec]
    msg.is_bigendian = False
    msg.point_step = point_step
    msg.row_step = point_step * msg.width
    msg.data = data
    msg.is_dense = is_dense
    return msg


def xyz_to_pointcloud2(header: Any, xyz: np.ndarray,
                       extra: Mapping[str, np.ndarray] | None = None, *,
                       frame_id: str | None = None) -> Any:
    """Build a PointCloud2 with FLOAT32 x, y, z from xyz (N, 3) plus extra (N,) fields."""
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f'xyz must have shape (N, 3), got {xyz.shape}')
    xyz = xyz.astype(np.float32, copy=False)
    arrays: dict[str, np.ndarray] = {'x': xyz[:, 0], 'y': xyz[:, 1], 'z': xyz[:, 2]}
    for name, values in (extra or {}).items():
        if name in arrays:
            raise ValueError(f'extra field {name!r} clashes with x/y/z')
        arrays[name] = values
    return make_pointcloud2(header, arrays, frame_id=frame_id)
