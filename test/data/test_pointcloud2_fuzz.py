"""Property-based fuzzing of the PointCloud2 codec.

A slow, obviously-correct reference decoder (struct.unpack_from per point) states the rules;
hypothesis draws random layouts (field order, offsets and padding, point_step, row padding,
endianness, dtypes, counts, organized shapes, NaNs, data containers) and random corruptions.
Every message must either decode to exactly what the reference says or raise DecodeError
exactly when the reference rejects it; any other exception fails the test.
"""

from __future__ import annotations

import array
import math
import os
import struct
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from point_gn_ros.errors import DecodeError
from point_gn_ros.pointcloud2 import (
    DecodedCloud,
    decode_classifications,
    decode_xyz,
    make_classifications,
    split_segments,
)

# Reproducible CI: fixed seed derivation, no example database, no deadline (shared 2-core box).
settings.register_profile(
    'pointcloud2-ci', max_examples=int(os.environ.get('POINTGN_FUZZ_EXAMPLES', '1000')),
    deadline=None, derandomize=True, database=None, print_blob=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
CI = settings.get_profile('pointcloud2-ci')

_FMT = {1: 'b', 2: 'B', 3: 'h', 4: 'H', 5: 'i', 6: 'I', 7: 'f', 8: 'd'}
_NP = {1: np.int8, 2: np.uint8, 3: np.int16, 4: np.uint16, 5: np.int32, 6: np.uint32,
       7: np.float32, 8: np.float64}
_SIZE = {code: struct.calcsize(fmt) for code, fmt in _FMT.items()}
MAX_POINTS = 40


class RejectedError(Exception):
    """The reference decoder says the message is malformed."""


def reference_decode(msg: SimpleNamespace, extras: list[str], max_points: int,
                     allow_empty: bool = False) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Decode by the written rules, one point at a time. Raises RejectedError when malformed.

    Every integer (sizes, steps, offsets, counts) must be below 2**31 (a C int); an empty
    grid or an all-non-finite cloud is valid (0 points) only with ``allow_empty``.
    """
    h, w, step, row = msg.height, msg.width, msg.point_step, msg.row_step
    if min(h, w, step, row) < 0 or max(h, w, step, row) >= 2**31 or h * w > max_points:
        raise RejectedError
    if h * w == 0 and not allow_empty:
        raise RejectedError
    layout = {}
    for name in dict.fromkeys(['x', 'y', 'z', *extras]):
        found = [f for f in msg.fields if f.name == name]
        if len(found) != 1:
            raise RejectedError
        f = found[0]
        if f.datatype not in _FMT or f.count < 0 or f.offset < 0:
            raise RejectedError
        if max(f.offset, f.count) >= 2**31:
            raise RejectedError
        if f.offset + _SIZE[f.datatype] * max(f.count, 1) > step:
            raise RejectedError
        layout[name] = f
    if row < w * step:
        raise RejectedError
    data = msg.data
    if not isinstance(data, (bytes, bytearray, array.array, np.ndarray)) and not (
            isinstance(data, list) and all(type(b) is int and 0 <= b <= 255 for b in data)):
        raise RejectedError
    data = bytes(data)
    if len(data) != row * h:
        raise RejectedError
    order = '>' if msg.is_bigendian else '<'
    values: dict[str, list] = {name: [] for name in layout}
    for r in range(h):
        for c in range(w):
            for name, f in layout.items():
                at = r * row + c * step + f.offset
                values[name].append(struct.unpack_from(order + _FMT[f.datatype], data, at)[0])
    with np.errstate(over='ignore', invalid='ignore'):
        xyz = np.array([values['x'], values['y'], values['z']], dtype=np.float64)
        xyz = xyz.T.astype(np.float32)
    keep = np.isfinite(xyz).all(axis=1)
    if not keep.any() and not allow_empty:
        raise RejectedError
    fields = {name: np.array(values[name], dtype=_NP[layout[name].datatype])[keep]
              for name in extras}
    return xyz[keep], fields


# ------------------------------------------------------------------------------ strategies


# Edge values hypothesis injects at random positions on top of seeded bulk values.
_FINITE_SPECIALS = [0.0, -0.0, 1e-45, -1e-38, 3.4028234663852886e38, -1.5, 2.0**24 + 1]
_NONFINITE_SPECIALS = [math.nan, -math.nan, math.inf, -math.inf, 1e300, -1e39]  # 1e300: f64 only


def _bulk_values(rng: np.random.Generator, datatype: int, shape: tuple[int, int]) -> np.ndarray:
    """Random values of a PointField type, shape (N, count) (floats span many magnitudes)."""
    dt = np.dtype(_NP[datatype])
    if dt.kind == 'f':
        return (rng.normal(size=shape) * 10.0 ** rng.integers(-3, 4, size=shape)).astype(dt)
    info = np.iinfo(dt)
    return rng.integers(info.min, info.max, size=shape, endpoint=True, dtype=dt)


@st.composite
def valid_clouds(draw: st.DrawFn) -> tuple[SimpleNamespace, list[str]]:
    """A well-formed message with a random layout; returns (msg, requested extra fields)."""
    specs = [(a, draw(st.sampled_from([7, 8]))) for a in 'xyz']
    n_extra = draw(st.integers(0, 3))
    specs += [(f'e{i}', draw(st.sampled_from(sorted(_FMT)))) for i in range(n_extra)]
    specs = draw(st.permutations(specs))
    fields, offset = [], 0
    for name, dt in specs:
        offset += draw(st.integers(0, 3))  # padding before the field (unaligned allowed)
        count = draw(st.sampled_from([1, 1, 1, 0, 2, 3]))
        fields.append(SimpleNamespace(name=name, offset=offset, datatype=dt, count=count))
        offset += _SIZE[dt] * max(count, 1)
    point_step = offset + draw(st.integers(0, 5))
    height = draw(st.integers(1, 4))
    width = draw(st.integers(1, 6))
    n = height * width
    row_step = width * point_step + draw(st.sampled_from([0, 0, 1, 3, 8]))
    bigendian = draw(st.booleans())
    buf = bytearray(draw(st.binary(min_size=row_step * height, max_size=row_step * height)))
    order = '>' if bigendian else '<'

    # Bulk values from a drawn seed (fast); hypothesis then plants edge values. x/y/z get
    # finite specials only, a mix including NaN/inf/float32 overflow, or are all NaN.
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    values = {f.name: _bulk_values(rng, f.datatype, (n, max(f.count, 1))).astype(object)
              for f in fields}
    xyz_mode = draw(st.sampled_from(['finite', 'finite', 'finite', 'mixed', 'mixed', 'nan']))
    specials = _FINITE_SPECIALS + (_NONFINITE_SPECIALS if xyz_mode == 'mixed' else [])
    float_fields = [f for f in fields if f.datatype in (7, 8)]
    for _ in range(draw(st.integers(0, 6))):
        f = draw(st.sampled_from(float_fields))
        v = draw(st.sampled_from(specials))
        if f.datatype == 7 and abs(v) > 3.5e38 and math.isfinite(v):
            v = math.inf  # struct refuses out-of-range float32; inf is what it would become
        values[f.name][draw(st.integers(0, n - 1)), 0] = v
    if xyz_mode == 'nan':
        values['x'][:, 0] = math.nan
    for r in range(height):
        for c in range(width):
            for f in fields:
                struct.pack_into(f'{order}{max(f.count, 1)}{_FMT[f.datatype]}', buf,
                                 r * row_step + c * point_step + f.offset,
                                 *values[f.name][r * width + c])
    container = draw(st.sampled_from(['bytes', 'bytearray', 'array', 'list', 'numpy']))
    data: Any = {'bytes': bytes, 'bytearray': bytearray, 'list': list,
                 'array': lambda b: array.array('B', b),
                 'numpy': lambda b: np.frombuffer(bytes(b), np.uint8)}[container](buf)
    msg = SimpleNamespace(height=height, width=width, fields=fields, is_bigendian=bigendian,
                          point_step=point_step, row_step=row_step, data=data,
                          is_dense=draw(st.booleans()))
    extras = draw(st.lists(st.sampled_from([f.name for f in fields]), max_size=3, unique=True))
    return msg, extras


def _corrupt(draw: st.DrawFn, msg: SimpleNamespace) -> None:
    """Apply one random corruption in place."""
    kind = draw(st.sampled_from(['truncate', 'extend', 'row_step', 'point_step', 'remove',
                                 'datatype', 'offset', 'count', 'dims', 'duplicate', 'endian',
                                 'bad_data', 'huge', 'empty_huge']))
    try:
        data = bytes(msg.data)
    except (TypeError, ValueError):  # an earlier 'bad_data' corruption
        data = b''
    f = draw(st.sampled_from(msg.fields)) if msg.fields else None
    if kind == 'truncate':
        msg.data = data[:draw(st.integers(0, max(len(data) - 1, 0)))]
    elif kind == 'extend':
        msg.data = data + draw(st.binary(min_size=1, max_size=40))
    elif kind == 'row_step':
        msg.row_step = draw(st.integers(0, 2 * msg.row_step + 8))
    elif kind == 'point_step':
        msg.point_step = draw(st.integers(0, msg.point_step + 8))
    elif kind == 'remove' and f is not None:
        msg.fields = [g for g in msg.fields if g is not f]
    elif kind == 'datatype' and f is not None:
        f.datatype = draw(st.sampled_from([0, 9, 17, 255, -1, *_FMT]))
    elif kind == 'offset' and f is not None:
        end = msg.point_step - _SIZE.get(f.datatype, 4) * max(f.count, 1)
        f.offset = draw(st.one_of(st.sampled_from([end, end + 1, msg.point_step, -1]),
                                  st.integers(-4, msg.point_step + 8)))  # edges, then anything
    elif kind == 'count' and f is not None:
        f.count = draw(st.integers(-2, 6))
    elif kind == 'dims':
        msg.height = draw(st.integers(0, 5))
        msg.width = draw(st.integers(0, 7))
    elif kind == 'duplicate' and f is not None:
        msg.fields = [*msg.fields, SimpleNamespace(**vars(f))]
    elif kind == 'endian':
        msg.is_bigendian = not msg.is_bigendian
    elif kind in ('huge', 'empty_huge'):
        # uint32 values past a C int (what a real PointCloud2 can carry), one attribute at a
        # time; 'empty_huge' also empties the grid (the decoder's former ValueError escape).
        if kind == 'empty_huge':
            msg.width, msg.data = 0, b''
        big = draw(st.sampled_from([2**31 - 1, 2**31, 2**31 + 7, 2**32 - 1]))
        target = draw(st.sampled_from(['point_step', 'row_step', 'width', 'height', 'offset',
                                       'count']))
        if target in ('offset', 'count'):
            if f is not None:
                setattr(f, target, big)
        else:
            setattr(msg, target, big)
    elif kind == 'bad_data':
        msg.data = draw(st.sampled_from([[*data, 256], [-1, *data], 'abc', None, [0.5] * 4]))


@st.composite
def corrupted_clouds(draw: st.DrawFn) -> tuple[SimpleNamespace, list[str]]:
    msg, extras = draw(valid_clouds())
    for _ in range(draw(st.integers(1, 3))):
        _corrupt(draw, msg)
    if draw(st.booleans()):
        extras = [*extras, draw(st.sampled_from(['x', 'e0', 'e1', 'missing']))]
    return msg, extras


# ------------------------------------------------------------------------------ properties


def check_against_reference(msg: SimpleNamespace, extras: list[str], max_points: int,
                            allow_empty: bool = False) -> str:
    """Assert decode_xyz agrees with the reference; returns 'decoded' or 'rejected: <word>'."""
    try:
        expect_xyz, expect_fields = reference_decode(msg, extras, max_points, allow_empty)
    except RejectedError:
        with pytest.raises(DecodeError) as err:
            decode_xyz(msg, extras, max_points=max_points, allow_empty=allow_empty)
        return f'rejected: {str(err.value).split(" ")[0]}'  # coarse reason, for statistics
    # any exception here fails the test
    out = decode_xyz(msg, extras, max_points=max_points, allow_empty=allow_empty)
    np.testing.assert_array_equal(out.xyz, expect_xyz)
    assert out.xyz.dtype == np.float32 and out.xyz.shape == expect_xyz.shape
    assert out.n_dropped_nonfinite == msg.height * msg.width - len(expect_xyz)
    assert list(out.fields) == list(dict.fromkeys(extras))
    for name, expect in expect_fields.items():
        assert out.fields[name].dtype == expect.dtype
        np.testing.assert_array_equal(out.fields[name], expect)
    return 'decoded'


def _over_the_wire(msg: SimpleNamespace) -> Any:
    """Rebuild ``msg`` as a real PointCloud2, CDR round-tripped (data becomes array.array)."""
    serialization = pytest.importorskip('rclpy.serialization')
    sensor_msgs = pytest.importorskip('sensor_msgs.msg')
    real = sensor_msgs.PointCloud2(
        height=msg.height, width=msg.width, is_bigendian=msg.is_bigendian,
        point_step=msg.point_step, row_step=msg.row_step, is_dense=msg.is_dense,
        fields=[sensor_msgs.PointField(name=f.name, offset=f.offset, datatype=f.datatype,
                                       count=f.count) for f in msg.fields])
    real.data = array.array('B', bytes(msg.data))
    return serialization.deserialize_message(serialization.serialize_message(real),
                                             sensor_msgs.PointCloud2)


@CI
@given(valid_clouds(), st.sampled_from([False] * 19 + [True]), st.booleans())
def test_fuzz_valid_layouts_decode_exactly(case: tuple, tiny_limit: bool, wire: bool) -> None:
    msg, extras = case
    if wire:  # half the layouts go through a real rclpy message and CDR
        msg = _over_the_wire(msg)
    # Valid layouts must decode unless every point is non-finite or the point cap is hit.
    max_points = msg.height * msg.width - 1 if tiny_limit else MAX_POINTS
    event(check_against_reference(msg, extras, max_points))


@CI
@given(corrupted_clouds(), st.booleans())
def test_fuzz_corrupted_messages_raise_decode_error_only(case: tuple, allow_empty: bool
                                                         ) -> None:
    msg, extras = case
    # allow_empty is what the node passes: empty grids then go further into the checks.
    event(check_against_reference(msg, extras, MAX_POINTS, allow_empty))


def test_fuzz_reference_accepts_and_rejects() -> None:
    """Guard the oracle itself: a fixed valid message decodes, a truncated one is rejected."""
    data = struct.pack('<3f', 1, 2, 3) * 2
    fields = [SimpleNamespace(name=a, offset=4 * i, datatype=7, count=1)
              for i, a in enumerate('xyz')]
    msg = SimpleNamespace(height=1, width=2, fields=fields, is_bigendian=False, point_step=12,
                          row_step=24, data=data, is_dense=True)
    assert check_against_reference(msg, [], MAX_POINTS) == 'decoded'
    msg.data = data[:-1]
    assert check_against_reference(msg, [], MAX_POINTS) == 'rejected: data'


# ------------------------------------------------------------- wire round trip (classifications)


@settings(CI, max_examples=max(CI.max_examples // 10, 10))
@given(m=st.integers(0, 6), k=st.integers(0, 6), seed=st.integers(0, 2**16))
def test_fuzz_classifications_wire_round_trip(m: int, k: int, seed: int) -> None:
    serialization = pytest.importorskip('rclpy.serialization')
    sensor_msgs = pytest.importorskip('sensor_msgs.msg')
    rng = np.random.default_rng(seed)
    args = dict(centroids=rng.normal(size=(m, 3)).astype(np.float32),
                class_id=rng.integers(-1, 100, m), score=rng.random(m).astype(np.float32),
                topk_ids=rng.integers(0, 100, (m, k)),
                topk_scores=rng.random((m, k)).astype(np.float32),
                segment_id=rng.integers(-1, 2**31 - 1, m), topic_index=rng.integers(0, 8, m))
    wire = serialization.serialize_message(make_classifications(None, **args))
    out = decode_classifications(serialization.deserialize_message(wire,
                                                                   sensor_msgs.PointCloud2))
    np.testing.assert_array_equal(out['centroid'], args['centroids'])
    for key in ('class_id', 'score', 'topk_ids', 'topk_scores', 'segment_id', 'topic_index'):
        np.testing.assert_array_equal(out[key], args[key])
    assert out['topk_ids'].shape == (m, k)


# ------------------------------------------------------------------------------ segments


@settings(CI, max_examples=max(CI.max_examples // 5, 10))
@given(dtype=st.sampled_from(['i1', 'u1', 'i2', 'u2', 'i4', 'u4', 'i8', 'u8', 'f4', 'f8', '?']),
       n=st.integers(1, 60), seed=st.integers(0, 2**16), spread=st.sampled_from([1, 3, 300, 0]))
def test_fuzz_split_segments_matches_naive(dtype: str, n: int, seed: int, spread: int) -> None:
    rng = np.random.default_rng(seed)
    dt = np.dtype(dtype)
    if dt.kind == 'f':
        ids = rng.integers(-2**20, 2**20, n).astype(dt)
    elif dt.kind == 'b':
        ids = rng.integers(0, 2, n).astype(bool)
    else:
        info = np.iinfo(dt)
        base = rng.integers(info.min, info.max, endpoint=True, dtype=dt)
        # spread 0: ids anywhere in the dtype's range; else a few ids near a random base
        ids = (rng.integers(info.min, info.max, n, endpoint=True, dtype=dt) if spread == 0
               else base + rng.integers(0, spread, n).astype(dt))  # wraps: fine, still ids
    xyz = rng.normal(size=(n, 3)).astype(np.float32)
    decoded = DecodedCloud(xyz=xyz, fields={'s': ids})
    if any(not -2**31 <= int(v) < 2**31 for v in ids):  # segment_id is an INT32 downstream
        with pytest.raises(DecodeError, match='out of range for segment_id'):
            split_segments(decoded, 's')
        return
    segs = split_segments(decoded, 's')
    expect_ids = sorted({int(v) for v in ids})
    assert [s for s, _ in segs] == expect_ids
    for seg_id, part in segs:
        np.testing.assert_array_equal(part, xyz[ids.astype(object) == seg_id])
