"""A seeded mix of valid and invalid PointCloud2 messages, each with the answer it must get.

ROS-free except for the message classes (sensor_msgs, imported lazily). Used by the node
fuzz (`point_gn_ros.clients.fuzz`, `make fuzz`, test/node/test_node_fuzz.py) and by the
pipeline's fault tests. The expected answer of a valid message is computed here by the
documented rules (docs/NODE.md), independently of the node's code: the segment ids of
non-negative segments with at least `min_points` finite points, and when there are more
than `max_objects`, the largest ones (ties: lower id).
"""

from __future__ import annotations

import array
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

SEGMENT_FIELD = 'segment'
VALID_KINDS = ('single', 'multi', 'small_segments', 'empty', 'nan_points', 'float64',
               'big_endian', 'organized', 'padded', 'uint32_ids', 'many_objects')
INVALID_KINDS = ('truncated', 'missing_x', 'missing_segment', 'bad_datatype',
                 'huge_point_step', 'empty_huge_point_step', 'row_step_small',
                 'duplicate_field', 'huge_segment_id', 'float_segment_id', 'too_many_points',
                 'huge_width', 'huge_offset')


@dataclass(frozen=True)
class Limits:
    """The node settings the expectations depend on (pass the same to the node)."""

    min_points: int = 16
    max_points: int = 6000          # max_points_per_message
    max_objects: int = 8            # max_objects_per_message


@dataclass
class FuzzCase:
    """One message and what the node must do with it."""

    index: int
    kind: str
    msg: Any                               # sensor_msgs/msg/PointCloud2
    valid: bool                            # True: exactly one answer; False: none
    expected_segments: tuple[int, ...]     # valid only: answered segment ids, ascending

    @property
    def stamp(self) -> tuple[int, int]:
        return (self.msg.header.stamp.sec, self.msg.header.stamp.nanosec)


def _shape(rng: np.random.Generator, n: int) -> np.ndarray:
    """A small object of n points (a box, a ball or a rod), metres, somewhere ahead."""
    kind = rng.integers(3)
    if kind == 0:
        xyz = rng.uniform(-0.5, 0.5, (n, 3)) * rng.uniform(0.2, 1.0, 3)
    elif kind == 1:
        v = rng.normal(size=(n, 3))
        xyz = v / np.linalg.norm(v, axis=1, keepdims=True) * rng.uniform(0.1, 0.6)
    else:
        xyz = np.c_[rng.normal(0, 0.03, (n, 2)), rng.uniform(0, 1.5, n)]
    return (xyz + rng.uniform([2, -3, 0], [8, 3, 1])).astype(np.float32)


def _expected(ids: np.ndarray, finite: np.ndarray, limits: Limits) -> tuple[int, ...]:
    keep = ids[finite]
    uniq, counts = np.unique(keep[keep >= 0], return_counts=True)
    big = [(int(i), int(c)) for i, c in zip(uniq, counts, strict=True) if c >= limits.min_points]
    if len(big) > limits.max_objects:
        big = sorted(big, key=lambda ic: (-ic[1], ic[0]))[:limits.max_objects]
    return tuple(sorted(i for i, _ in big))


def _scene(rng: np.random.Generator, sizes: list[int], ids: list[int], clutter: int
           ) -> tuple[np.ndarray, np.ndarray]:
    parts = [_shape(rng, n) + np.float32(3.0 * k) for k, n in enumerate(sizes)]
    seg = [np.full(n, i, np.int64) for n, i in zip(sizes, ids, strict=True)]
    if clutter:
        parts.append(rng.uniform(-10, 10, (clutter, 3)).astype(np.float32))
        seg.append(np.full(clutter, -1, np.int64))
    xyz = np.concatenate(parts) if parts else np.zeros((0, 3), np.float32)
    segs = np.concatenate(seg) if seg else np.zeros(0, np.int64)
    order = rng.permutation(len(xyz))
    return xyz[order], segs[order]


def pack_cloud(header: Any, cols: list[tuple[str, np.ndarray]], *, big_endian: bool = False,
          height: int = 1, pad: int = 0, row_pad: int = 0) -> Any:
    """PointCloud2 from named (N,) columns, any byte order, padding after each point/row."""
    from sensor_msgs.msg import PointCloud2, PointField

    from point_gn_ros.pointcloud2.decode import _DATATYPE_OF

    order = '>' if big_endian else '<'
    n = len(cols[0][1])
    fields, names, formats, offsets, off = [], [], [], [], 0
    for name, arr in cols:
        dt = arr.dtype.newbyteorder('=')
        fields.append(PointField(name=name, offset=off, datatype=_DATATYPE_OF[dt], count=1))
        names.append(name)
        formats.append(dt.newbyteorder(order))
        offsets.append(off)
        off += dt.itemsize
    step = off + pad
    width = n // height if n else 0
    rec = np.zeros(n, dtype=np.dtype({'names': names, 'formats': formats, 'offsets': offsets,
                                      'itemsize': step}))
    for name, arr in cols:
        rec[name] = arr
    rows = rec.view(np.uint8).reshape(height if n else 0, width * step)
    data = np.zeros((rows.shape[0], width * step + row_pad), np.uint8)
    data[:, :width * step] = rows
    msg = PointCloud2(header=header, height=height if n else 1, width=width, fields=fields,
                      is_bigendian=big_endian, point_step=step,
                      row_step=width * step + row_pad, is_dense=False)
    msg.data = array.array('B', data.tobytes())
    return msg


def fuzz_header(index: int) -> Any:
    from builtin_interfaces.msg import Time
    from std_msgs.msg import Header
    # Unique, non-zero stamps (a fixed epoch): answers are matched by stamp.
    return Header(frame_id='fuzz', stamp=Time(sec=1_000_000 + index // 1000,
                                              nanosec=(index % 1000) * 1000 + 1))


def make_case(index: int, kind: str, rng: np.random.Generator, limits: Limits) -> FuzzCase:
    """One message of `kind` (see VALID_KINDS / INVALID_KINDS)."""
    header = fuzz_header(index)
    mp = limits.min_points
    seg_dtype: type = np.int32
    if kind in ('single', 'float64', 'big_endian', 'organized', 'padded', 'nan_points',
                'uint32_ids') or kind in INVALID_KINDS:
        n = int(rng.integers(mp, 1500))
        xyz, seg = _scene(rng, [n], [int(rng.integers(0, 1000))], int(rng.integers(0, 50)))
    elif kind == 'multi':
        k = int(rng.integers(2, 6))
        xyz, seg = _scene(rng, [int(rng.integers(mp, 500)) for _ in range(k)],
                          list(rng.choice(1000, k, replace=False)), int(rng.integers(0, 80)))
    elif kind == 'small_segments':
        k = int(rng.integers(1, 4))
        xyz, seg = _scene(rng, [int(rng.integers(1, mp)) for _ in range(k)],
                          list(rng.choice(1000, k, replace=False)), 5)
    elif kind == 'many_objects':
        k = limits.max_objects + int(rng.integers(1, 6))
        xyz, seg = _scene(rng, [int(rng.integers(mp, 200)) for _ in range(k)],
                          list(rng.choice(1000, k, replace=False)), 0)
    elif kind == 'empty':
        xyz, seg = np.zeros((0, 3), np.float32), np.zeros(0, np.int64)
    else:
        raise ValueError(f'unknown fuzz kind {kind!r}')
    if kind == 'organized' and len(xyz) % 2:
        xyz, seg = xyz[:-1], seg[:-1]
    if kind == 'nan_points':
        bad = rng.random(len(xyz)) < 0.2
        xyz[bad, rng.integers(0, 3)] = np.nan
    if kind == 'uint32_ids':   # unsigned ids near the int32 limit; clutter becomes id 0
        seg_dtype = np.uint32
        seg = np.where(seg < 0, 0, seg + (2**31 - 2000))
    finite = np.isfinite(xyz).all(axis=1)
    fxyz = xyz.astype(np.float64 if kind == 'float64' else np.float32)
    cols = [('x', fxyz[:, 0]), ('y', fxyz[:, 1]), ('z', fxyz[:, 2])]
    if kind == 'huge_segment_id':
        seg = seg.copy()
        seg[seg >= 0] = 2**31 + 5
        cols.append((SEGMENT_FIELD, np.where(seg < 0, 0, seg).astype(np.uint32)))
    elif kind == 'float_segment_id':
        cols.append((SEGMENT_FIELD, seg.astype(np.float32) + np.float32(0.5)))
    elif kind != 'missing_segment':
        cols.append((SEGMENT_FIELD, seg.astype(seg_dtype)))
    if kind == 'padded':
        cols.insert(1, ('intensity', rng.random(len(xyz)).astype(np.float32)))
    if kind == 'too_many_points':
        extra = limits.max_points + 1 - len(xyz)
        more = rng.uniform(-5, 5, (max(extra, 0), 3)).astype(np.float32)
        cols = [(a, np.concatenate([c, more[:, i]])) for i, (a, c) in enumerate(cols[:3])]
        cols.append((SEGMENT_FIELD, np.concatenate([seg, np.full(len(more), -1)])
                     .astype(np.int32)))
    msg = pack_cloud(header, cols, big_endian=kind == 'big_endian',
                height=2 if kind == 'organized' and len(xyz) else 1,
                pad=3 if kind == 'padded' else 0, row_pad=5 if kind == 'organized' else 0)
    _corrupt(msg, kind)
    valid = kind in VALID_KINDS
    expected = _expected(seg, finite, limits) if valid else ()
    return FuzzCase(index, kind, msg, valid, expected)


def _corrupt(msg: Any, kind: str) -> None:
    """Make a well-formed message invalid in the way `kind` names (no-op for valid kinds)."""
    if kind == 'truncated':
        msg.data = msg.data[:-1] if len(msg.data) else array.array('B', b'\0')
    elif kind == 'missing_x':
        msg.fields = [f for f in msg.fields if f.name != 'x']
    elif kind == 'bad_datatype':
        msg.fields[1].datatype = 9
    elif kind == 'huge_point_step':
        msg.point_step = 2**31 + 3
    elif kind == 'empty_huge_point_step':   # the campaign's decoder escape
        msg.width, msg.row_step, msg.data = 0, 0, array.array('B')
        msg.point_step = 2**31 + 3
    elif kind == 'row_step_small':
        msg.row_step = max(msg.row_step - 1, 0)
    elif kind == 'duplicate_field':
        msg.fields = [*msg.fields, msg.fields[0]]
    elif kind == 'huge_width':
        msg.width = 2**31
    elif kind == 'huge_offset':
        msg.fields[2].offset = 2**32 - 1


def generate(seed: int, count: int, limits: Limits = Limits(),
             invalid_share: float = 0.4) -> Iterator[FuzzCase]:
    """`count` cases, reproducible from `seed`; about `invalid_share` of them invalid."""
    rng = np.random.default_rng(seed)
    for i in range(count):
        bad = rng.random() < invalid_share
        kind = str(rng.choice(INVALID_KINDS if bad else VALID_KINDS))
        yield make_case(i, kind, rng, limits)
