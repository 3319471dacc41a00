"""read_points for .npy and text files, extension dispatch, and the LZF codec."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from point_gn_ros.datasets import read_points
from point_gn_ros.datasets.lzf import LZFError, compress, decompress
from point_gn_ros.errors import DatasetError


def test_npy_first_three_columns_as_float32(tmp_path: Path) -> None:
    arr = np.arange(24, dtype=np.float64).reshape(4, 6)
    np.save(tmp_path / 'six.npy', arr)
    xyz = read_points(tmp_path / 'six.npy')
    assert xyz.dtype == np.float32 and xyz.flags.c_contiguous
    np.testing.assert_array_equal(xyz, arr[:, :3])


def test_npy_drops_non_finite_rows(tmp_path: Path) -> None:
    arr = np.array([[1, 2, 3], [np.nan, 0, 0], [4, 5, 6]], dtype=np.float32)
    np.save(tmp_path / 'nan.npy', arr)
    np.testing.assert_array_equal(read_points(tmp_path / 'nan.npy'), arr[[0, 2]])
    assert read_points(tmp_path / 'nan.npy', drop_nan=False).shape == (3, 3)


@pytest.mark.parametrize(('arr', 'words'), [
    (np.zeros(5, np.float32), 'shape'),
    (np.zeros((5, 2), np.float32), 'shape'),
    (np.array([[1, 2, 3]], dtype=object), 'not a readable .npy'),  # needs pickle: refused
    (np.array([['a', 'b', 'c']]), 'numeric'),
])
def test_bad_npy(tmp_path: Path, arr: np.ndarray, words: str) -> None:
    f = tmp_path / 'bad.npy'
    np.save(f, arr)  # object arrays are written pickled by default: the reader must refuse
    with pytest.raises(DatasetError, match=words) as err:
        read_points(f)
    assert str(f) in str(err.value)


def test_truncated_npy(tmp_path: Path) -> None:
    f = tmp_path / 'cut.npy'
    np.save(f, np.zeros((100, 3), np.float32))
    f.write_bytes(f.read_bytes()[:-10])
    with pytest.raises(DatasetError, match='cut.npy'):
        read_points(f)


@pytest.mark.parametrize(('name', 'text'), [
    ('space.txt', '1 2 3\n4   5\t6 0.5\n'),
    ('comma.txt', '1,2,3,9\n4, 5, 6\n'),
    ('commented.xyz', '# x y z\n\n1 2 3\n// note\n4 5 6\n'),
    ('crlf.csv', '1,2,3\r\n4,5,6\r\n'),
])
def test_text_formats(tmp_path: Path, name: str, text: str) -> None:
    f = tmp_path / name
    f.write_text(text)
    np.testing.assert_array_equal(read_points(f), [[1, 2, 3], [4, 5, 6]])


@pytest.mark.parametrize(('text', 'words'), [
    ('x y z\n1 2 3\n', "row 1: 'x y z'"),
    ('1 2 3\n4 5\n', 'line 2 has 2 values'),
])
def test_bad_text(tmp_path: Path, text: str, words: str) -> None:
    f = tmp_path / 'bad.txt'
    f.write_text(text)
    with pytest.raises(DatasetError, match=words) as err:
        read_points(f)
    assert str(f) in str(err.value)


def test_unsupported_extension(tmp_path: Path) -> None:
    f = tmp_path / 'mesh.off'
    f.write_text('OFF\n')
    with pytest.raises(DatasetError, match="mesh.off: unsupported point file extension '.off'"):
        read_points(f)


def test_lzf_hand_made_stream_with_overlapping_back_reference() -> None:
    # literal 'ab', then copy 6 bytes from 2 back: the copy overlaps what it writes
    assert decompress(b'\x01ab\x80\x01', 8) == b'abababab'
    # long form: length code 7 + extra byte 3 -> 12 bytes, distance 1
    assert decompress(b'\x00z\xe0\x03\x00', 13) == b'z' * 13


@pytest.mark.parametrize('data', [
    b'', b'a', bytes(range(256)) * 3, b'\x00' * 5000,
    np.random.default_rng(0).integers(0, 4, 20000, dtype=np.uint8).tobytes(),
    np.repeat(np.float32([1.5, np.nan, -2.0]), 700).tobytes(),
])
def test_lzf_round_trip(data: bytes) -> None:
    packed = compress(data)
    assert decompress(packed, len(data)) == data
    if len(data) > 1000 and len(set(data)) < 8:
        assert len(packed) < len(data)  # back-references were used


@pytest.mark.parametrize(('stream', 'size', 'words'), [
    (b'\x05abc', 6, 'past the end'),
    (b'\x00a\x20', 4, 'offset byte missing'),
    (b'\x00a\xe0', 12, 'length byte missing'),
    (b'\x00a\x20\x05', 4, 'before the start'),
    (b'\x02abc', 2, 'more than the expected'),
    (b'\x02abc', 4, 'expected 4'),
])
def test_lzf_errors(stream: bytes, size: int, words: str) -> None:
    with pytest.raises(LZFError, match=words):
        decompress(stream, size)
