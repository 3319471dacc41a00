"""Unit tests for point_gn_ros.pointcloud2: layouts, malformations, segments, builders."""

from __future__ import annotations

import array
import struct
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from point_gn_ros.errors import DecodeError
from point_gn_ros.pointcloud2 import (
    FLOAT32,
    FLOAT64,
    INT8,
    INT16,
    INT32,
    UINT8,
    UINT16,
    UINT32,
    DecodedCloud,
    classification_fields,
    decode_classifications,
    decode_xyz,
    make_classifications,
    make_pointcloud2,
    split_segments,
    xyz_to_pointcloud2,
)
from point_gn_ros.pointcloud2.decode import _structured_view

_FMT = {INT8: 'b', UINT8: 'B', INT16: 'h', UINT16: 'H', INT32: 'i', UINT32: 'I',
        FLOAT32: 'f', FLOAT64: 'd'}
_NP = {INT8: np.int8, UINT8: np.uint8, INT16: np.int16, UINT16: np.uint16, INT32: np.int32,
       UINT32: np.uint32, FLOAT32: np.float32, FLOAT64: np.float64}


def pack_cloud(fields: list[tuple[str, int, int, int]], values: dict[str, np.ndarray], *,
               point_step: int, height: int = 1, width: int | None = None,
               row_pad: int = 0, bigendian: bool = False, is_dense: bool = False,
               data_as: type = bytes) -> SimpleNamespace:
    """Independent struct-based packer for arbitrary layouts (the decoder's oracle).

    fields: (name, offset, datatype, count); values: name -> (N,) or (N, count) arrays.
    Padding bytes are 0xEE so misreads show up as garbage, not zeros.
    """
    n = len(next(iter(values.values())))
    width = n // height if width is None else width
    row_step = width * point_step + row_pad
    buf = bytearray(b'\xee' * (row_step * height))
    order = '>' if bigendian else '<'
    for name, offset, datatype, count in fields:
        vals = np.asarray(values[name]).reshape(n, -1)
        for p in range(n):
            base = (p // width) * row_step + (p % width) * point_step + offset
            struct.pack_into(f'{order}{max(count, 1)}{_FMT[datatype]}', buf, base,
                             *vals[p].tolist())
    pfields = [SimpleNamespace(name=nm, offset=o, datatype=d, count=c) for nm, o, d, c in fields]
    data: Any = bytes(buf)
    if data_as is array.array:
        data = array.array('B', data)
    elif data_as is not bytes:
        data = data_as(data)
    return SimpleNamespace(height=height, width=width, fields=pfields, is_bigendian=bigendian,
                           point_step=point_step, row_step=row_step, data=data,
                           is_dense=is_dense)


def xyz_fields(datatype: int = FLOAT32, order: str = 'xyz', gap: int = 0) -> list:
    size = np.dtype(_NP[datatype]).itemsize
    return [(a, i * (size + gap), datatype, 1) for i, a in enumerate(order)]


RNG = np.random.default_rng(0)
XYZ = RNG.normal(size=(12, 3)).astype(np.float32)


def cols(xyz: np.ndarray) -> dict[str, np.ndarray]:
    return {'x': xyz[:, 0], 'y': xyz[:, 1], 'z': xyz[:, 2]}


# ------------------------------------------------------------------------------- layouts


@pytest.mark.parametrize('data_as', [
    bytes, bytearray, array.array, list, tuple, memoryview,
    lambda b: np.frombuffer(b, np.uint8),
    lambda b: np.repeat(np.frombuffer(b, np.uint8), 2)[::2],  # strided numpy view
    lambda b: np.frombuffer(b, np.uint8).astype(np.int64),   # ints that are bytes
], ids=['bytes', 'bytearray', 'array', 'list', 'tuple', 'memoryview', 'numpy', 'strided',
        'int64'])
def test_packed_xyz_any_container(data_as: Any) -> None:
    msg = pack_cloud(xyz_fields(), cols(XYZ), point_step=12, data_as=data_as)
    out = decode_xyz(msg)
    assert isinstance(out, DecodedCloud)
    assert out.xyz.dtype == np.float32 and out.xyz.flags.c_contiguous
    np.testing.assert_array_equal(out.xyz, XYZ)
    assert out.n_dropped_nonfinite == 0 and out.fields == {} and len(out) == 12


def test_reordered_fields_with_padding_and_row_padding() -> None:
    # PCL-like: z first, 4-byte gaps, 32-byte point_step, 5 bytes of row padding.
    fields = xyz_fields(order='zxy', gap=4) + [('intensity', 24, FLOAT32, 1)]
    vals = {**cols(XYZ), 'intensity': np.arange(12, dtype=np.float32)}
    msg = pack_cloud(fields, vals, point_step=32, height=3, row_pad=5)
    out = decode_xyz(msg, ['intensity'])
    np.testing.assert_array_equal(out.xyz, XYZ)
    np.testing.assert_array_equal(out.fields['intensity'], vals['intensity'])
    assert (out.height, out.width) == (3, 4)


@pytest.mark.parametrize('bigendian', [False, True])
@pytest.mark.parametrize('datatype', [FLOAT32, FLOAT64])
def test_xyz_datatypes_and_endianness(datatype: int, bigendian: bool) -> None:
    xyz = XYZ.astype(_NP[datatype])
    msg = pack_cloud(xyz_fields(datatype), cols(xyz), point_step=3 * xyz.itemsize + 2,
                     bigendian=bigendian)
    out = decode_xyz(msg)
    np.testing.assert_array_equal(out.xyz, XYZ)


@pytest.mark.parametrize('bigendian', [False, True])
@pytest.mark.parametrize('datatype', sorted(_NP))
def test_extra_field_every_datatype(datatype: int, bigendian: bool) -> None:
    dt = np.dtype(_NP[datatype])
    if dt.kind == 'f':
        vals = np.linspace(-3.5, 7.25, 12).astype(dt)
    else:
        info = np.iinfo(dt)
        vals = np.linspace(info.min, info.max, 12).astype(dt)
    fields = [*xyz_fields(), ('v', 13, datatype, 1)]  # odd offset: unaligned on purpose
    msg = pack_cloud(fields, {**cols(XYZ), 'v': vals}, point_step=13 + dt.itemsize,
                     bigendian=bigendian)
    out = decode_xyz(msg, ('v',))
    assert out.fields['v'].dtype == dt  # native order, the field's own type
    np.testing.assert_array_equal(out.fields['v'], vals)


def test_organized_cloud_with_nans_ignores_is_dense() -> None:
    xyz = XYZ.copy()
    xyz[[1, 5, 11], [0, 2, 1]] = [np.nan, np.inf, -np.inf]
    ids = np.arange(12, dtype=np.int32)
    msg = pack_cloud([*xyz_fields(), ('id', 12, INT32, 1)], {**cols(xyz), 'id': ids},
                     point_step=16, height=4, is_dense=True)  # lies about density
    out = decode_xyz(msg, ['id'])
    keep = np.isfinite(xyz).all(axis=1)
    np.testing.assert_array_equal(out.xyz, xyz[keep])
    np.testing.assert_array_equal(out.fields['id'], ids[keep])  # fields stay aligned
    assert out.n_dropped_nonfinite == 3


def test_float64_overflow_to_float32_is_dropped() -> None:
    xyz = XYZ.astype(np.float64)
    xyz[2, 0] = 1e300
    out = decode_xyz(pack_cloud(xyz_fields(FLOAT64), cols(xyz), point_step=24))
    assert out.n_dropped_nonfinite == 1 and len(out) == 11


def test_count_greater_than_one_takes_first_element() -> None:
    rgb = np.arange(36, dtype=np.uint8).reshape(12, 3)
    xs = np.stack([XYZ[:, 0], np.full(12, 99, np.float32)], axis=1)
    fields = [('x', 0, FLOAT32, 2), ('y', 8, FLOAT32, 1), ('z', 12, FLOAT32, 1),
              ('rgb', 16, UINT8, 3)]
    msg = pack_cloud(fields, {**cols(XYZ), 'x': xs, 'rgb': rgb}, point_step=19)
    out = decode_xyz(msg, ['rgb'])
    np.testing.assert_array_equal(out.xyz, XYZ)
    np.testing.assert_array_equal(out.fields['rgb'], rgb[:, 0])


def test_count_zero_is_read_as_one() -> None:
    fields = [(a, o, d, 0) for a, o, d, _ in xyz_fields()]
    np.testing.assert_array_equal(decode_xyz(pack_cloud(fields, cols(XYZ),
                                                        point_step=12)).xyz, XYZ)


def test_unrequested_odd_fields_are_ignored() -> None:
    fields = [*xyz_fields(), ('junk', 12, FLOAT32, 1)]
    msg = pack_cloud(fields, {**cols(XYZ), 'junk': np.zeros(12)}, point_step=16)
    msg.fields.append(SimpleNamespace(name='weird', offset=999, datatype=42, count=1))
    np.testing.assert_array_equal(decode_xyz(msg).xyz, XYZ)


def test_extra_fields_as_single_string_and_xyz_as_extra() -> None:
    fields = [*xyz_fields(FLOAT64), ('label', 24, UINT16, 1)]
    vals = {**cols(XYZ.astype(np.float64)), 'label': np.arange(12, dtype=np.uint16)}
    out = decode_xyz(pack_cloud(fields, vals, point_step=26), 'label')
    assert list(out.fields) == ['label']
    out = decode_xyz(pack_cloud(fields, vals, point_step=26), ['x'])
    assert out.fields['x'].dtype == np.float64


def test_decode_is_a_view_onto_message_bytes() -> None:
    msg = pack_cloud(xyz_fields(), cols(XYZ), point_step=12, height=2, row_pad=3,
                     data_as=array.array)
    view, h, w, _ = _structured_view(msg, ['x', 'y', 'z'], max_points=100, allow_empty=False)
    assert (h, w) == (2, 6)
    assert np.shares_memory(view, np.frombuffer(msg.data, np.uint8))  # zero copy


def test_allow_empty() -> None:
    msg = pack_cloud(xyz_fields(), cols(XYZ), point_step=12)
    msg.width, msg.row_step, msg.data = 0, 0, b''
    assert decode_xyz(msg, allow_empty=True).xyz.shape == (0, 3)
    nan = pack_cloud(xyz_fields(), cols(np.full((2, 3), np.nan, np.float32)), point_step=12)
    out = decode_xyz(nan, allow_empty=True)
    assert out.xyz.shape == (0, 3) and out.n_dropped_nonfinite == 2


# ---------------------------------------------------------------------------- malformed


def _valid() -> SimpleNamespace:
    return pack_cloud([*xyz_fields(), ('label', 12, INT32, 1)],
                      {**cols(XYZ), 'label': np.zeros(12, np.int32)}, point_step=16, height=2)


def _field(msg: SimpleNamespace, name: str) -> SimpleNamespace:
    return next(f for f in msg.fields if f.name == name)


MALFORMED = {
    'truncated data': (lambda m: setattr(m, 'data', m.data[:-1]), r'data has 191 bytes'),
    'extended data': (lambda m: setattr(m, 'data', m.data + b'\0'), r'expected row_step\*'),
    'row_step too small': (lambda m: setattr(m, 'row_step', 95), r'row_step 95 < width'),
    'row_step too big': (lambda m: setattr(m, 'row_step', 97), r'data has 192 bytes'),
    'field past point_step': (lambda m: setattr(_field(m, 'z'), 'offset', 13),
                              r"'z'.*does not fit in point_step 16"),
    'count past point_step': (lambda m: setattr(_field(m, 'y'), 'count', 4),
                              r"'y'.*does not fit"),
    'negative offset': (lambda m: setattr(_field(m, 'x'), 'offset', -1), r"'x'.*not fit"),
    'point_step zero': (lambda m: setattr(m, 'point_step', 0), r'does not fit in point_step 0'),
    'missing x': (lambda m: m.fields.pop(0), r"missing field 'x' \(fields: label, y, z\)"),
    'missing z': (lambda m: m.fields.pop(2), r"missing field 'z'"),
    'unsupported datatype 0': (lambda m: setattr(_field(m, 'y'), 'datatype', 0),
                               r"'y' has unsupported datatype 0"),
    'unsupported datatype 9': (lambda m: setattr(_field(m, 'x'), 'datatype', 9),
                               r'unsupported datatype 9'),
    'duplicate x': (lambda m: m.fields.append(m.fields[0]), r"'x' appears 2 times"),
    'negative count': (lambda m: setattr(_field(m, 'x'), 'count', -1), r'negative count'),
    'width zero': (lambda m: setattr(m, 'width', 0), r'empty \(width=0, height=2\)'),
    'height zero': (lambda m: setattr(m, 'height', 0), r'empty \(width=6, height=0\)'),
    'negative width': (lambda m: setattr(m, 'width', -6), r'negative'),
    'height not int': (lambda m: setattr(m, 'height', 2.0), r'height is not an integer'),
    'all nan': (lambda m: setattr(m, 'data', b'\xff' * len(m.data)),
                r'all 12 points have non-finite'),
    'data is str': (lambda m: setattr(m, 'data', 'x' * 192), r'not a byte sequence'),
    'data is None': (lambda m: setattr(m, 'data', None), r'not a byte sequence'),
    'data list out of range': (lambda m: setattr(m, 'data', [300] * 192), r'outside 0\.\.255'),
    'data list of floats': (lambda m: setattr(m, 'data', [0.5] * 192), r'not a byte sequence'),
    'fields not a list': (lambda m: setattr(m, 'fields', 3), r'fields is not a sequence'),
    'field without offset': (lambda m: m.fields.__setitem__(0, SimpleNamespace(name='x')),
                             r'malformed PointField'),
    'no data attribute': (lambda m: delattr(m, 'data'), r'not a PointCloud2'),
    # uint32 values past a C int: refused at the boundary, never a ValueError/OverflowError.
    'point_step 2**31': (lambda m: setattr(m, 'point_step', 2**31), r'point_step 2147483648 is'),
    'row_step 2**32-1': (lambda m: setattr(m, 'row_step', 2**32 - 1), r'row_step .* out of range'),
    'width 2**31': (lambda m: setattr(m, 'width', 2**31), r'width .* out of range'),
    'height 2**31': (lambda m: setattr(m, 'height', 2**31), r'height .* out of range'),
    'offset 2**31': (lambda m: setattr(_field(m, 'x'), 'offset', 2**31), r"'x' offset .* range"),
    'count 2**32-1': (lambda m: setattr(_field(m, 'y'), 'count', 2**32 - 1), r"'y' count"),
}


@pytest.mark.parametrize('case', list(MALFORMED), ids=list(MALFORMED))
def test_malformed_raises_decode_error(case: str) -> None:
    mutate, reason = MALFORMED[case]
    msg = _valid()
    mutate(msg)
    with pytest.raises(DecodeError, match=reason):
        decode_xyz(msg)


@pytest.mark.parametrize('attr', ['point_step', 'row_step'])
def test_empty_cloud_with_huge_step_is_a_decode_error(attr: str) -> None:
    """The campaign's escape: an empty cloud, point_step >= 2**31, allow_empty (the node)."""
    msg = _valid()
    msg.width, msg.data = 0, b''
    setattr(msg, attr, 2**31 + 5)
    with pytest.raises(DecodeError, match=f'{attr} 2147483653 is out of range'):
        decode_xyz(msg, allow_empty=True)
    with pytest.raises(DecodeError, match='out of range'):
        decode_classifications(msg)


def test_missing_extra_field_and_max_points() -> None:
    with pytest.raises(DecodeError, match="missing field 'rgb'"):
        decode_xyz(_valid(), ['rgb'])
    with pytest.raises(DecodeError, match=r'too many points: 12 > max_points=11'):
        decode_xyz(_valid(), max_points=11)
    assert len(decode_xyz(_valid(), max_points=12)) == 12


def test_huge_header_rejected_before_reading_data() -> None:
    msg = _valid()
    msg.width, msg.height = 100_000, 100  # 10M points, tiny data
    with pytest.raises(DecodeError, match='max_points=5,000,000'):
        decode_xyz(msg)


def test_decode_error_is_not_other_exception_for_garbage_object() -> None:
    with pytest.raises(DecodeError, match='not a PointCloud2'):
        decode_xyz(object())


# ------------------------------------------------------------------------------ segments


def _segmented(ids: np.ndarray, datatype: int = INT32) -> DecodedCloud:
    vals = {**cols(XYZ), 'seg': ids.astype(_NP[datatype])}
    size = np.dtype(_NP[datatype]).itemsize
    msg = pack_cloud([*xyz_fields(), ('seg', 12, datatype, 1)], vals, point_step=12 + size)
    return decode_xyz(msg, ['seg'])


@pytest.mark.parametrize('datatype', [INT32, UINT8, UINT32, INT16, FLOAT32, FLOAT64])
def test_split_segments_sorted_and_order_preserving(datatype: int) -> None:
    ids = np.array([5, 2, 5, 2, 9, 5, 2, 9, 0, 0, 5, 2])
    segs = split_segments(_segmented(ids, datatype), 'seg')
    assert [s for s, _ in segs] == [0, 2, 5, 9]
    assert all(isinstance(s, int) for s, _ in segs)
    for seg_id, xyz in segs:
        np.testing.assert_array_equal(xyz, XYZ[ids == seg_id])


def test_split_segments_skip_ids_negative_and_large() -> None:
    ids = np.array([-1, 3, -1, 3, 7, 7, -1, 3, 3, 7, 7, -1])
    segs = split_segments(_segmented(ids), 'seg', skip_ids=[-1])
    assert [s for s, _ in segs] == [3, 7]
    big = np.array([4_000_000_000] * 6 + [1] * 6)
    # segment_id is an INT32 in the answer: an id beyond it is refused at the boundary ...
    with pytest.raises(DecodeError, match=r'out of range for segment_id \(4000000000 does not'):
        split_segments(_segmented(big, UINT32), 'seg')
    # ... unless it is skipped (e.g. a UINT32 'no label' value).
    segs = split_segments(_segmented(big, UINT32), 'seg', skip_ids=[4_000_000_000])
    assert [s for s, _ in segs] == [1]
    edge = np.array([2**31 - 1] * 6 + [-2**31] * 6)
    assert [s for s, _ in split_segments(_segmented(edge, INT32), 'seg')] == [-2**31, 2**31 - 1]


def test_split_segments_after_nan_removal() -> None:
    xyz = XYZ.copy()
    xyz[0, 0] = np.nan
    ids = np.arange(12, dtype=np.int32) % 2
    msg = pack_cloud([*xyz_fields(), ('seg', 12, INT32, 1)], {**cols(xyz), 'seg': ids},
                     point_step=16)
    segs = dict(split_segments(decode_xyz(msg, ['seg']), 'seg'))
    assert len(segs[0]) == 5 and len(segs[1]) == 6


@pytest.mark.parametrize('ids', [
    np.array([127, -128, 0, 127, -128, 5] * 2, np.int8),        # full int8 range (wraps)
    np.array([-32768, 32767, 1] * 4, np.int16),                # full int16 range
    np.array([70000, -70000, 3] * 4, np.int32),                 # too wide for the radix path
    np.array([2**64 - 1, 0, 2**63] * 4, np.uint64),
    np.array([True, False, False] * 4),
], ids=['int8', 'int16', 'int32-wide', 'uint64', 'bool'])
def test_split_segments_id_ranges(ids: np.ndarray) -> None:
    decoded = DecodedCloud(xyz=XYZ, fields={'seg': ids})
    # ids beyond int32 (uint64 case) must be skipped to be accepted; the sort still sees them
    wide = {int(v) for v in ids if not -2**31 <= int(v) < 2**31}
    segs = split_segments(decoded, 'seg', skip_ids=wide)
    assert [s for s, _ in segs] == sorted({int(v) for v in ids} - wide)
    for seg_id, xyz in segs:
        np.testing.assert_array_equal(xyz, XYZ[ids == seg_id])


def test_extra_fields_may_be_a_generator() -> None:
    msg = pack_cloud([*xyz_fields(), ('seg', 12, INT32, 1)],
                     {**cols(XYZ), 'seg': np.arange(12)}, point_step=16)
    out = decode_xyz(msg, (name for name in ['seg']))
    np.testing.assert_array_equal(out.fields['seg'], np.arange(12))


def test_split_segments_errors() -> None:
    with pytest.raises(DecodeError, match='non-integer'):
        split_segments(_segmented(np.linspace(0, 1, 12), FLOAT32), 'seg')
    nan_ids = np.zeros(12)
    nan_ids[3] = np.nan
    with pytest.raises(DecodeError, match='non-integer'):
        split_segments(_segmented(nan_ids, FLOAT64), 'seg')
    with pytest.raises(DecodeError, match="'label' was not decoded"):
        split_segments(_segmented(np.zeros(12)), 'label')
    empty = DecodedCloud(xyz=np.zeros((0, 3), np.float32), fields={'s': np.zeros(0, np.int32)})
    assert split_segments(empty, 's') == []


# ------------------------------------------------------------------------------ builders

sensor_msgs = pytest.importorskip('sensor_msgs.msg')


def _wire(msg: Any) -> Any:
    """Serialise to CDR and back: proves the message is wire-valid, gives rclpy's array data."""
    serialization = pytest.importorskip('rclpy.serialization')
    out = serialization.deserialize_message(serialization.serialize_message(msg),
                                            sensor_msgs.PointCloud2)
    assert isinstance(out.data, array.array)
    return out


def test_make_pointcloud2_dtypes_and_layout() -> None:
    n = 7
    arrays = {
        'x': np.arange(n, dtype=np.float32), 'y': np.ones(n, np.float64),
        'z': np.zeros(n, np.float16), 'i8': np.full(n, -3, np.int8),
        'u8': np.full(n, 250, np.uint8), 'i16': np.full(n, -300, np.int16),
        'u16': np.full(n, 60000, np.uint16), 'i32': np.full(n, -7, np.int32),
        'u32': np.full(n, 4_000_000_000, np.uint32), 'i64': np.arange(n),
        'u64': np.arange(n, dtype=np.uint64), 'flag': np.arange(n) % 2 == 0,
        'be': np.arange(n, dtype='>i4'),
    }
    msg = make_pointcloud2(None, arrays, frame_id='base_link')
    assert isinstance(msg, sensor_msgs.PointCloud2) and isinstance(msg.data, array.array)
    expect = [FLOAT32, FLOAT64, FLOAT32, INT8, UINT8, INT16, UINT16, INT32, UINT32, INT32,
              UINT32, UINT8, INT32]
    assert [f.datatype for f in msg.fields] == expect
    assert [f.name for f in msg.fields] == list(arrays)
    sizes = [np.dtype(_NP[d]).itemsize for d in expect]
    assert [f.offset for f in msg.fields] == list(np.cumsum([0, *sizes[:-1]]))
    assert msg.point_step == sum(sizes) and msg.row_step == msg.point_step * n
    assert (msg.height, msg.width, msg.is_bigendian, msg.is_dense) == (1, n, False, True)
    assert msg.header.frame_id == 'base_link'
    out = decode_xyz(_wire(msg), [k for k in arrays if k not in 'xyz'])
    for name, vals in arrays.items():
        if name not in 'xyz':
            np.testing.assert_array_equal(out.fields[name], vals)


def test_editing_a_built_message_leaves_the_next_one_alone() -> None:
    # layouts are cached per field spec; a caller (the fuzz clients) may edit its fields
    arrays = {'x': np.zeros(2, np.float32), 'y': np.ones(2, np.float32)}
    first = make_pointcloud2(None, arrays)
    first.fields[1].datatype, first.fields[0].offset = 9, 2**32 - 1
    second = make_pointcloud2(None, arrays)
    assert [(f.offset, f.datatype) for f in second.fields] == [(0, FLOAT32), (4, FLOAT32)]


def test_make_pointcloud2_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match='do not fit in int32'):
        make_pointcloud2(None, {'x': np.array([2**40])})
    with pytest.raises(ValueError, match='must be 1-D'):
        make_pointcloud2(None, {'x': np.zeros((3, 2))})
    with pytest.raises(ValueError, match='has 2 values, expected 3'):
        make_pointcloud2(None, {'x': np.zeros(3), 'y': np.zeros(2)})
    with pytest.raises(ValueError, match='no PointField datatype'):
        make_pointcloud2(None, {'x': np.zeros(3, np.complex64)})
    with pytest.raises(ValueError, match='organized cloud of height 2'):
        make_pointcloud2(None, {'x': np.zeros(3)}, height=2)
    with pytest.raises(ValueError, match=r'shape \(N, 3\)'):
        xyz_to_pointcloud2(None, np.zeros((3, 2)))
    with pytest.raises(ValueError, match='clashes'):
        xyz_to_pointcloud2(None, XYZ, {'x': np.zeros(12)})


def test_xyz_to_pointcloud2_round_trip_over_the_wire() -> None:
    from std_msgs.msg import Header

    header = Header(frame_id='cam')
    header.stamp.sec = 42
    xyz = XYZ.astype(np.float64)
    xyz[4] = np.nan
    msg = xyz_to_pointcloud2(header, xyz, {'seg': np.arange(12) // 4}, frame_id='lidar')
    assert header.frame_id == 'cam'  # the caller's header is not mutated
    assert msg.is_dense is False
    back = _wire(msg)
    assert (back.header.frame_id, back.header.stamp.sec) == ('lidar', 42)
    out = decode_xyz(back, ['seg'])
    np.testing.assert_array_equal(out.xyz, XYZ[np.arange(12) != 4])
    assert [s for s, _ in split_segments(out, 'seg')] == [0, 1, 2]


def test_organized_and_empty_builds() -> None:
    msg = make_pointcloud2(None, cols(XYZ), height=3)
    assert (msg.height, msg.width, msg.row_step) == (3, 4, 48)
    out = decode_xyz(_wire(msg))
    np.testing.assert_array_equal(out.xyz, XYZ)
    empty = _wire(xyz_to_pointcloud2(None, np.zeros((0, 3))))
    assert (empty.height, empty.width, len(empty.data)) == (1, 0, 0)
    with pytest.raises(DecodeError, match='empty'):
        decode_xyz(empty)
    assert decode_xyz(empty, allow_empty=True).xyz.shape == (0, 3)


# ------------------------------------------------------------------------ classifications


def _classes(m: int, k: int) -> dict[str, Any]:
    rng = np.random.default_rng(m * 10 + k)
    return dict(centroids=rng.normal(size=(m, 3)), class_id=rng.integers(-1, 40, m),
                score=rng.random(m), topk_ids=rng.integers(0, 40, (m, k)),
                topk_scores=rng.random((m, k)).astype(np.float32),
                segment_id=rng.integers(-1, 9, m), topic_index=rng.integers(0, 3, m))


@pytest.mark.parametrize(('m', 'k'), [(0, 5), (1, 5), (6, 3), (4, 0), (0, 0)])
def test_classifications_round_trip(m: int, k: int) -> None:
    args = _classes(m, k)
    msg = make_classifications(None, **args, frame_id='map')
    layout = classification_fields(k)
    assert [f.name for f in msg.fields] == [name for name, _ in layout]
    assert [f.datatype for f in msg.fields] == [
        INT32 if dt == np.int32 else FLOAT32 for _, dt in layout]
    out = decode_classifications(_wire(msg))
    assert set(out) == {'centroid', 'class_id', 'score', 'topk_ids', 'topk_scores',
                        'segment_id', 'topic_index'}
    assert out['centroid'].shape == (m, 3) and out['centroid'].dtype == np.float32
    assert out['topk_ids'].shape == (m, k) and out['topk_ids'].dtype == np.int32
    assert out['topk_scores'].shape == (m, k) and out['topk_scores'].dtype == np.float32
    np.testing.assert_array_equal(out['centroid'], args['centroids'].astype(np.float32))
    np.testing.assert_array_equal(out['topk_ids'], args['topk_ids'])
    np.testing.assert_array_equal(out['topk_scores'], args['topk_scores'])
    np.testing.assert_array_equal(out['score'], args['score'].astype(np.float32))
    for key in ('class_id', 'segment_id', 'topic_index'):
        assert out[key].dtype == np.int32 and out[key].shape == (m,)
        np.testing.assert_array_equal(out[key], args[key])
    # the packed-record fast path gives the generic builder's message, byte for byte
    cols = {'x': args['centroids'][:, 0].astype(np.float32),
            'y': args['centroids'][:, 1].astype(np.float32),
            'z': args['centroids'][:, 2].astype(np.float32),
            'class_id': args['class_id'].astype(np.int32),
            'score': args['score'].astype(np.float32)}
    cols.update({f'topk_id_{i}': args['topk_ids'][:, i].astype(np.int32) for i in range(k)})
    cols.update({f'topk_score_{i}': args['topk_scores'][:, i] for i in range(k)})
    cols.update(segment_id=args['segment_id'].astype(np.int32),
                topic_index=args['topic_index'].astype(np.int32))
    generic = make_pointcloud2(None, cols, frame_id='map')
    assert bytes(msg.data) == bytes(generic.data) and msg.is_dense == generic.is_dense
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        (f.name, f.offset, f.datatype, f.count) for f in generic.fields]
    assert (msg.point_step, msg.row_step, msg.width, msg.height) == (
        generic.point_step, generic.row_step, generic.width, generic.height)


def test_classifications_scalar_broadcast_and_package_reexport() -> None:
    import point_gn_ros

    args = _classes(3, 2)
    args.update(segment_id=-1, topic_index=2)
    out = point_gn_ros.decode_classifications(make_classifications(None, **args))
    np.testing.assert_array_equal(out['segment_id'], [-1, -1, -1])
    np.testing.assert_array_equal(out['topic_index'], [2, 2, 2])


def test_decode_classifications_any_layout() -> None:
    # Reordered, padded, big-endian stand-in built by the independent packer.
    k, m = 2, 4
    names = [name for name, _ in classification_fields(k)][::-1]
    fields, vals, offset = [], {}, 0
    for i, name in enumerate(names):
        dt = FLOAT64 if name in 'xyz' else (FLOAT32 if 'score' in name else INT16)
        fields.append((name, offset, dt, 1))
        vals[name] = np.arange(m) + i
        offset += np.dtype(_NP[dt]).itemsize + 1
    msg = pack_cloud(fields, vals, point_step=offset, height=2, row_pad=3, bigendian=True)
    out = decode_classifications(msg)
    np.testing.assert_array_equal(out['centroid'][:, 0], vals['x'])
    np.testing.assert_array_equal(out['topk_scores'][:, 1], vals['topk_score_1'])
    assert out['class_id'].dtype == np.int32


def test_classification_errors() -> None:
    args = _classes(3, 2)
    with pytest.raises(ValueError, match='topk_scores shape'):
        make_classifications(None, **{**args, 'topk_scores': np.zeros((3, 1))})
    with pytest.raises(ValueError, match=r'class_id must have shape \(3,\)'):
        make_classifications(None, **{**args, 'class_id': np.zeros(2, int)})
    with pytest.raises(ValueError, match='do not fit in int32'):
        make_classifications(None, **{**args, 'segment_id': 2**40})
    msg = make_classifications(None, **args)
    msg.fields = [f for f in msg.fields if f.name != 'topic_index']
    with pytest.raises(DecodeError, match="missing field 'topic_index'"):
        decode_classifications(msg)
    with pytest.raises(DecodeError, match='not a PointCloud2'):
        decode_classifications(object())
