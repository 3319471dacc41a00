"""PLY reader: ascii and binary (both byte orders), extra properties and elements, bad files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from point_gn_ros.datasets import read_ply, read_points
from point_gn_ros.errors import DatasetError

XYZ = np.array([[0.5, -1.0, 2.0], [1.25, 3.5, -0.75], [-2.0, 0.0, 1e-3]], dtype=np.float32)


def ply_header(fmt: str, vertex_props: list[str], n: int, before: str = '',
               after: str = '') -> bytes:
    props = ''.join(f'property {p}\n' for p in vertex_props)
    return (f'ply\nformat {fmt} 1.0\ncomment made by a test\n{before}element vertex {n}\n'
            f'{props}{after}end_header\n').encode()


def test_ascii_with_extra_properties_and_faces(tmp_path: Path) -> None:
    head = ply_header('ascii', ['float x', 'float y', 'float z', 'uchar red', 'float nx'], 3,
                      after='element face 1\nproperty list uchar int vertex_indices\n')
    rows = ''.join(f'{x} {y} {z} {i * 100} 0.5\n' for i, (x, y, z) in enumerate(XYZ.tolist()))
    f = tmp_path / 'a.ply'
    f.write_bytes(head + rows.encode() + b'3 0 1 2\n')
    cloud = read_ply(f)
    np.testing.assert_array_equal(cloud['xyz'], XYZ)
    np.testing.assert_array_equal(cloud['red'], [0, 100, 200])
    assert cloud['red'].dtype == np.uint8 and cloud['nx'].shape == (3,)


@pytest.mark.parametrize('order', ['<', '>'])
def test_binary_both_byte_orders_with_doubles_and_colours(tmp_path: Path, order: str) -> None:
    fmt = 'binary_little_endian' if order == '<' else 'binary_big_endian'
    rec = np.zeros(3, dtype=[('red', 'u1'), ('x', order + 'f8'), ('y', order + 'f8'),
                             ('z', order + 'f8'), ('quality', order + 'i4')])
    rec['x'], rec['y'], rec['z'] = XYZ.T
    rec['quality'] = [-1, 7, 1 << 20]
    head = ply_header(fmt, ['uchar red', 'double x', 'double y', 'double z', 'int quality'], 3,
                      after='element face 1\nproperty list uchar int vertex_indices\n')
    f = tmp_path / f'{fmt}.ply'
    f.write_bytes(head + rec.tobytes() + b'\x03' + np.array([0, 1, 2], order + 'i4').tobytes())
    cloud = read_ply(f)
    np.testing.assert_array_equal(cloud['xyz'], XYZ)
    np.testing.assert_array_equal(cloud['quality'], [-1, 7, 1 << 20])
    np.testing.assert_array_equal(read_points(f), XYZ)


def test_binary_element_with_lists_before_vertex_is_skipped(tmp_path: Path) -> None:
    before = 'element face 2\nproperty list uchar int vertex_indices\nproperty uchar flag\n'
    faces = (b'\x03' + np.array([0, 1, 2], '<i4').tobytes() + b'\x01'
             + b'\x04' + np.array([0, 1, 2, 0], '<i4').tobytes() + b'\x00')
    head = ply_header('binary_little_endian', ['float x', 'float y', 'float z'], 3, before=before)
    f = tmp_path / 'faces_first.ply'
    f.write_bytes(head + faces + XYZ.astype('<f4').tobytes())
    np.testing.assert_array_equal(read_ply(f)['xyz'], XYZ)


def test_nan_vertices_are_dropped_unless_asked(tmp_path: Path) -> None:
    xyz = XYZ.copy()
    xyz[1, 2] = np.inf
    f = tmp_path / 'nan.ply'
    f.write_bytes(ply_header('binary_little_endian', ['float x', 'float y', 'float z'], 3)
                  + xyz.tobytes())
    assert read_ply(f)['xyz'].shape == (2, 3)
    assert read_ply(f, drop_nan=False)['xyz'].shape == (3, 3)


XYZ_PROPS = ['float x', 'float y', 'float z']


@pytest.mark.parametrize(('content', 'words'), [
    (b'plx\nformat ascii 1.0\nend_header\n', 'does not start with "ply"'),
    (ply_header('ascii', XYZ_PROPS, 1).replace(b'end_header', b'end_hdr'), 'no end_header'),
    (ply_header('binary_little_endian', XYZ_PROPS, 3) + XYZ.tobytes()[:-4], 'truncated'),
    (ply_header('ascii', XYZ_PROPS, 3) + b'1 2 3\n4 5 6\n', 'truncated'),
    (ply_header('ascii', XYZ_PROPS, 2) + b'1 2 3\n4 5\n', 'values'),
    (ply_header('ascii', XYZ_PROPS, 1) + b'1 2 abc\n', 'non-numeric'),
    (ply_header('ascii', ['float x', 'float y', 'float w'], 1) + b'1 2 3\n', 'missing z'),
    (ply_header('ascii', ['float x', 'float y', 'quad z'], 1) + b'1 2 3\n', 'quad'),
    (ply_header('binary_middle_endian', XYZ_PROPS, 1), 'binary_middle_endian'),
    (b'ply\nelement vertex 1\nproperty float x\nend_header\n', 'no format'),
    (ply_header('ascii', XYZ_PROPS, 1).replace(b'element vertex', b'element point') + b'1 2 3\n',
     'no vertex element'),
    (ply_header('ascii', XYZ_PROPS + ['list uchar int idx'], 1) + b'1 2 3 0\n', 'list'),
])
def test_malformed_ply_raises_dataset_error_naming_file(tmp_path: Path, content: bytes,
                                                        words: str) -> None:
    f = tmp_path / 'bad.ply'
    f.write_bytes(content)
    with pytest.raises(DatasetError) as err:
        read_ply(f)
    assert str(f) in str(err.value) and words in str(err.value)
