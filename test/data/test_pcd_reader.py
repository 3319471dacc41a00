"""PCD reader: every encoding and header version, NaN handling, malformed files, real PCL files."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from conftest import require_shared

from point_gn_ros.datasets import read_pcd, read_pcd_header, read_points, write_pcd
from point_gn_ros.datasets.lzf import compress
from point_gn_ros.errors import DatasetError


def header(fields: str, sizes: str, types: str, counts: str | None, width: int, height: int,
           data: str, points: int | None = None, version: str = '0.7') -> bytes:
    """A PCD header as PCL writes it; counts=None leaves the (optional) COUNT line out."""
    lines = [f'# .PCD v{version} - Point Cloud Data file format', f'VERSION {version}',
             f'FIELDS {fields}', f'SIZE {sizes}', f'TYPE {types}']
    if counts is not None:
        lines.append(f'COUNT {counts}')
    lines += [f'WIDTH {width}', f'HEIGHT {height}']
    if version != '.5':
        lines.append('VIEWPOINT 0 0 0 1 0 0 0')
    lines += [f'POINTS {width * height if points is None else points}', f'DATA {data}']
    return ('\n'.join(lines) + '\n').encode()


def write(path: Path, head: bytes, body: bytes) -> Path:
    path.write_bytes(head + body)
    return path


XYZ = np.array([[0.5, -1.0, 2.0], [1.25, 3.5, -0.75], [np.nan, np.nan, np.nan],
                [-2.0, 0.0, 1e-3]], dtype=np.float32)
FINITE = np.isfinite(XYZ).all(axis=1)


def test_ascii_v07_with_extra_fields_drops_nan_points(tmp_path: Path) -> None:
    rgb = np.array([0xFF0000, 0x00FF00, 0x0000FF, 0x123456], dtype=np.uint32)
    body = ''.join(f'{x} {y} {z} {c}\n' for (x, y, z), c in zip(XYZ.tolist(), rgb, strict=True))
    f = write(tmp_path / 'a.pcd', header('x y z rgb', '4 4 4 4', 'F F F U', '1 1 1 1', 4, 1,
                                         'ascii'), body.encode())
    cloud = read_pcd(f)
    np.testing.assert_array_equal(cloud['xyz'], XYZ[FINITE])
    np.testing.assert_array_equal(cloud['rgb'], rgb[FINITE])
    assert cloud['rgb'].dtype == np.uint32 and cloud['xyz'].dtype == np.float32
    raw = read_pcd(f, drop_nan=False)
    assert raw['xyz'].shape == (4, 3) and np.isnan(raw['xyz'][2]).all()


def test_ascii_v05_header_without_count_or_viewpoint(tmp_path: Path) -> None:
    body = b'1 2 3\n4 5 6\n'
    f = write(tmp_path / 'old.pcd', header('x y z', '4 4 4', 'F F F', None, 2, 1, 'ascii',
                                           version='.5'), body)
    np.testing.assert_array_equal(read_pcd(f)['xyz'], [[1, 2, 3], [4, 5, 6]])
    assert read_pcd_header(f).version == '.5'


def test_binary_mixed_types_padding_and_multi_count_fields(tmp_path: Path) -> None:
    n = 4
    rec = np.zeros(n, dtype=[('x', '<f8'), ('y', '<f8'), ('z', '<f8'), ('pad', 'u1', (3,)),
                             ('intensity', '<u2'), ('normal', '<f4', (3,))])
    rec['x'], rec['y'], rec['z'] = XYZ.T
    rec['intensity'] = [10, 20, 30, 40]
    rec['normal'] = np.arange(12, dtype=np.float32).reshape(4, 3)
    head = header('x y z _ intensity normal', '8 8 8 1 2 4', 'F F F U U F', '1 1 1 3 1 3',
                  n, 1, 'binary')
    cloud = read_pcd(write(tmp_path / 'b.pcd', head, rec.tobytes()))
    assert '_' not in cloud and set(cloud) == {'x', 'y', 'z', 'intensity', 'normal', 'xyz'}
    np.testing.assert_array_equal(cloud['xyz'], XYZ[FINITE])
    np.testing.assert_array_equal(cloud['intensity'], [10, 20, 40])
    assert cloud['normal'].shape == (3, 3)
    np.testing.assert_array_equal(cloud['normal'], rec['normal'][FINITE])


def test_binary_organized_cloud_is_flattened_row_major(tmp_path: Path) -> None:
    grid = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)
    grid[1, 1] = np.nan  # an invalid pixel, as depth cameras write them
    f = write(tmp_path / 'org.pcd', header('x y z', '4 4 4', 'F F F', '1 1 1', 3, 2, 'binary'),
              grid.tobytes())
    assert read_pcd(f, drop_nan=False)['xyz'].shape == (6, 3)
    flat = grid.reshape(-1, 3)
    np.testing.assert_array_equal(read_pcd(f)['xyz'], flat[[0, 1, 2, 3, 5]])
    hdr = read_pcd_header(f)
    assert (hdr.width, hdr.height, hdr.points) == (3, 2, 6)


def compressed_body(columns: list[np.ndarray]) -> bytes:
    """PCL's binary_compressed payload: size words, then LZF of the field-major bytes."""
    plain = b''.join(np.ascontiguousarray(c).tobytes() for c in columns)
    packed = compress(plain)
    return struct.pack('<II', len(packed), len(plain)) + packed


def test_binary_compressed_field_major_layout(tmp_path: Path) -> None:
    rgba = np.array([1, 2, 3, 4], dtype='<u4')
    head = header('x y z rgba', '4 4 4 4', 'F F F U', '1 1 1 1', 4, 1, 'binary_compressed')
    f = write(tmp_path / 'c.pcd', head, compressed_body([XYZ[:, 0], XYZ[:, 1], XYZ[:, 2], rgba]))
    cloud = read_pcd(f)
    np.testing.assert_array_equal(cloud['xyz'], XYZ[FINITE])
    np.testing.assert_array_equal(cloud['rgba'], rgba[FINITE])


@pytest.mark.parametrize('data', ['ascii', 'binary', 'binary_compressed'])
def test_write_pcd_round_trip(tmp_path: Path, data: str) -> None:
    rng = np.random.default_rng(1)
    xyz = rng.standard_normal((50, 3)).astype(np.float32)
    xyz[::7] = 0.0  # repeats, so the compressor emits back-references
    normals = rng.standard_normal((50, 3)).astype(np.float32)
    label = np.arange(50, dtype=np.int16)
    f = tmp_path / f'{data}.pcd'
    write_pcd(f, {'xyz': xyz, 'normal': normals, 'label': label}, data=data, width=10, height=5)
    cloud = read_pcd(f)
    np.testing.assert_array_equal(cloud['xyz'], xyz)
    np.testing.assert_array_equal(cloud['normal'], normals)
    np.testing.assert_array_equal(cloud['label'], label)
    assert read_pcd_header(f).height == 5
    np.testing.assert_array_equal(read_points(f), xyz)


GOOD_HEAD = header('x y z', '4 4 4', 'F F F', '1 1 1', 2, 1, 'binary')
GOOD_BODY = np.ones((2, 3), np.float32).tobytes()


@pytest.mark.parametrize(('name', 'content', 'words'), [
    ('truncated.pcd', GOOD_HEAD + GOOD_BODY[:-5], 'truncated'),
    ('nodata.pcd', GOOD_HEAD.replace(b'DATA binary\n', b''), 'no DATA line'),
    ('unknownline.pcd', GOOD_HEAD.replace(b'VERSION', b'FOO 1\nVERSION') + GOOD_BODY, 'unknown'),
    ('badwidth.pcd', GOOD_HEAD.replace(b'WIDTH 2', b'WIDTH two') + GOOD_BODY, 'WIDTH two'),
    ('lengths.pcd', GOOD_HEAD.replace(b'SIZE 4 4 4', b'SIZE 4 4') + GOOD_BODY, 'lengths'),
    ('badtype.pcd', GOOD_HEAD.replace(b'TYPE F F F', b'TYPE F F I') .replace(b'SIZE 4 4 4',
                                                                             b'SIZE 4 4 3'),
     'TYPE I SIZE 3'),
    ('encoding.pcd', GOOD_HEAD.replace(b'DATA binary', b'DATA zip') + GOOD_BODY, 'zip'),
    ('count.pcd', GOOD_HEAD.replace(b'POINTS 2', b'POINTS 3') + GOOD_BODY, 'POINTS 3'),
    ('nofields.pcd', GOOD_HEAD.replace(b'FIELDS x y z\n', b''), 'no FIELDS'),
    ('binaryhead.pcd', b'\x89PNG\r\n\x1a\n\xff\xfe\n' + GOOD_BODY, 'not a PCD file'),
    ('asciicount.pcd', header('x y z', '4 4 4', 'F F F', '1 1 1', 2, 1, 'ascii') + b'1 2 3\n',
     '3 values'),
    ('asciitext.pcd', header('x y z', '4 4 4', 'F F F', '1 1 1', 1, 1, 'ascii') + b'1 2 zz\n',
     'non-numeric'),
    ('noz.pcd', header('x y w', '4 4 4', 'F F F', '1 1 1', 2, 1, 'binary') + GOOD_BODY,
     'missing z'),
    ('normal_only.pcd', header('normal_x normal_y normal_z', '4 4 4', 'F F F', '1 1 1', 2, 1,
                               'binary') + GOOD_BODY, 'missing x/y/z'),
    ('xcount.pcd', header('x y z', '4 4 4', 'F F F', '2 1 1', 2, 1, 'binary') + GOOD_BODY * 2,
     "field 'x'"),
])
def test_malformed_pcd_raises_dataset_error_naming_file(tmp_path: Path, name: str,
                                                        content: bytes, words: str) -> None:
    f = tmp_path / name
    f.write_bytes(content)
    with pytest.raises(DatasetError) as err:
        read_pcd(f)
    assert str(f) in str(err.value) and words in str(err.value)


def compressed_file(tmp_path: Path, body: bytes) -> Path:
    head = header('x y z', '4 4 4', 'F F F', '1 1 1', 2, 1, 'binary_compressed')
    return write(tmp_path / 'bad_compressed.pcd', head, body)


def test_compressed_size_mismatch_truncation_and_corruption(tmp_path: Path) -> None:
    cols = [np.ones(2, np.float32)] * 3
    good = compressed_body(cols)
    comp, plain = struct.unpack('<II', good[:8])
    cases = {
        'size mismatch': struct.pack('<II', comp, plain + 4) + good[8:],
        'truncated': good[:-3],
        'no size words': good[:5],
        'corrupt': struct.pack('<II', 2, plain) + b'\xe0\xff',  # back-reference before start
        'expected 24': struct.pack('<II', 3, plain) + b'\x01ab',  # decodes to too few bytes
    }
    for words, body in cases.items():
        f = compressed_file(tmp_path, body)
        with pytest.raises(DatasetError, match=words) as err:
            read_pcd(f)
        assert str(f) in str(err.value)


def test_missing_file_is_a_dataset_error(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match='nothere.pcd'):
        read_pcd(tmp_path / 'nothere.pcd')


@pytest.fixture(scope='module')
def pcd_samples(shared_dir: Path) -> Path:
    return require_shared(shared_dir / 'samples' / 'pcd')


def test_real_ascii_v05_bunny(pcd_samples: Path) -> None:
    cloud = read_pcd(pcd_samples / 'bunny.pcd')
    assert cloud['xyz'].shape == (397, 3)
    np.testing.assert_allclose(cloud['xyz'][0], [0.0054216, 0.11349, 0.040749])


def test_real_binary_with_rgb_and_normals(pcd_samples: Path) -> None:
    cloud = read_pcd(pcd_samples / 'colored_cloud.pcd')
    assert cloud['xyz'].shape == (1000, 3)
    assert cloud['rgb'].dtype == np.uint32 and cloud['curvature'].shape == (1000,)
    normals = np.stack([cloud[f'normal_{c}'] for c in 'xyz'], axis=1)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-3)


def test_real_binary_compressed(pcd_samples: Path) -> None:
    cloud = read_pcd(pcd_samples / 'milk_color.pcd')
    assert cloud['xyz'].shape == (13704, 3) and cloud['rgba'].shape == (13704,)
    assert np.isfinite(cloud['xyz']).all()
    assert 0.3 < float(np.median(cloud['xyz'][:, 2])) < 3.0  # a table-top RGB-D scan, metres


def test_real_organized_compressed_with_nans(pcd_samples: Path) -> None:
    f = pcd_samples / 'table_scene_mug_stereo_textured.pcd'
    hdr = read_pcd_header(f)
    assert (hdr.width, hdr.height, hdr.data) == (640, 480, 'binary_compressed')
    raw = read_pcd(f, drop_nan=False)['xyz']
    assert raw.shape == (307200, 3)
    valid = np.isfinite(raw).all(axis=1)
    assert 0 < valid.sum() < 307200
    assert np.isnan(raw[~valid]).all()  # invalid pixels are NaN in x, y and z alike
    xyz = read_points(f)
    assert xyz.shape == (int(valid.sum()), 3) and np.isfinite(xyz).all()
    np.testing.assert_array_equal(xyz, raw[valid])
