"""Folder-tree datasets: layouts, mixed formats, skipped files, empty classes, detection."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from point_gn_ros.datasets import detect_format, open_dataset, write_pcd
from point_gn_ros.errors import DatasetError


def cloud(seed: int, n: int) -> np.ndarray:
    return np.random.default_rng(seed).standard_normal((n, 3)).astype(np.float32)


def put(path: Path, xyz: np.ndarray) -> Path:
    """Write xyz in the format the extension names (PLY as binary little endian)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    ext = path.suffix
    if ext == '.npy':
        np.save(path, xyz)
    elif ext == '.pcd':
        write_pcd(path, {'xyz': xyz}, data='ascii')
    elif ext == '.ply':
        head = (f'ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz)}\n'
                'property float x\nproperty float y\nproperty float z\nend_header\n')
        path.write_bytes(head.encode() + xyz.astype('<f4').tobytes())
    else:
        path.write_text(''.join(f'{x!r}, {y!r}, {z!r}\n' for x, y, z in xyz.tolist()))
    return path


@pytest.fixture
def tree(tmp_path: Path) -> Path:
    """train/ and test/ with classes bird, car, tree in every supported format."""
    root = tmp_path / 'objects'
    put(root / 'train' / 'car' / 'a.pcd', cloud(0, 30))
    put(root / 'train' / 'car' / 'nested' / 'deeper' / 'b.ply', cloud(1, 20))
    put(root / 'train' / 'bird' / 'c.npy', cloud(2, 25))
    put(root / 'train' / 'bird' / 'd.txt', cloud(3, 12))
    put(root / 'train' / 'tree' / 'e.xyz', cloud(4, 40))
    put(root / 'test' / 'car' / 'f.npy', cloud(5, 30))
    put(root / 'test' / 'bird' / 'g.pcd', cloud(6, 30))
    put(root / 'test' / 'tree' / 'h.ply', cloud(7, 30))
    (root / 'train' / 'car' / '.hidden.npy').write_bytes(b'junk')  # dotfiles are ignored
    return root


def test_train_split_reads_every_format(tree: Path) -> None:
    assert detect_format(tree) == 'folder'
    ds = open_dataset(tree)
    assert (ds.format, ds.split, ds.class_names) == ('folder', 'train', ['bird', 'car', 'tree'])
    assert ds.labels.tolist() == [0, 0, 1, 1, 2] and ds.labels.dtype == np.int64
    assert [ds.item_name(i) for i in range(len(ds))] == [
        'train/bird/c.npy', 'train/bird/d.txt', 'train/car/a.pcd',
        'train/car/nested/deeper/b.ply', 'train/tree/e.xyz']
    for i, seed in enumerate([2, 3, 0, 1, 4]):
        xyz, label = ds[i]
        assert xyz.dtype == np.float32
        np.testing.assert_array_equal(xyz, cloud(seed, len(xyz)))
    ds[0][0][:] = 0  # callers get copies
    assert ds[0][0].any() and ds.skipped == []
    with pytest.raises(DatasetError, match='different point counts'):
        ds.load_all()


def test_num_points_allows_bulk_load_and_test_split_shares_class_ids(tree: Path) -> None:
    train = open_dataset(tree, num_points=16, subsample='fps')
    xyz, labels = train.load_all()
    assert xyz.shape == (5, 16, 3) and labels.tolist() == train.labels.tolist()
    test = open_dataset(tree, split='test', num_points=30)
    assert test.class_names == train.class_names and test.labels.tolist() == [0, 1, 2]
    assert test.load_all()[0].shape == (3, 30, 3)


def test_malformed_and_unsupported_files_are_skipped_and_reported(tree: Path) -> None:
    bad = tree / 'train' / 'car' / 'broken.pcd'
    bad.write_bytes(b'VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 9\nHEIGHT 1\n'
                    b'POINTS 9\nDATA binary\n\x00\x00')
    (tree / 'train' / 'car' / 'mesh.off').write_text('OFF\n')
    put(tree / 'train' / 'car' / 'allnan.npy', np.full((4, 3), np.nan, np.float32))
    (tree / 'train' / 'README.md').write_text('stray')
    ds = open_dataset(tree)
    assert len(ds) == 5
    reasons = dict(ds.skipped)
    assert 'truncated' in reasons[str(bad)]
    assert reasons[str(tree / 'train' / 'car' / 'mesh.off')] == "unsupported extension '.off'"
    assert reasons[str(tree / 'train' / 'car' / 'allnan.npy')] == 'no finite points'
    assert reasons[str(tree / 'train' / 'README.md')] == 'not inside a class folder'


def test_class_with_no_readable_file_raises_naming_it(tree: Path) -> None:
    for f in (tree / 'train' / 'tree').iterdir():
        f.unlink()
    (tree / 'train' / 'tree' / 'bad.txt').write_text('not numbers at all\n')
    with pytest.raises(DatasetError) as err:
        open_dataset(tree)
    msg = str(err.value)
    assert "1 class(es) have no readable point file for split 'train': tree" in msg
    assert 'bad.txt' in msg


def test_class_missing_from_one_split_is_an_error_not_a_renumbering(tree: Path) -> None:
    put(tree / 'train' / 'zebra' / 'z.npy', cloud(9, 10))
    assert open_dataset(tree).class_names == ['bird', 'car', 'tree', 'zebra']
    with pytest.raises(DatasetError, match='zebra'):
        open_dataset(tree, split='test')


def test_flat_and_per_class_split_layouts(tmp_path: Path) -> None:
    flat = tmp_path / 'flat'
    put(flat / 'mug' / 'a.npy', cloud(0, 8))
    put(flat / 'can' / 'b.npy', cloud(1, 8))
    ds = open_dataset(flat, split='test')
    assert (ds.split, ds.class_names, len(ds)) == ('all', ['can', 'mug'], 2)
    nested = tmp_path / 'nested'  # the ModelNet40 mesh release's <class>/<split>/ layout
    put(nested / 'mug' / 'train' / 'a.npy', cloud(0, 8))
    put(nested / 'mug' / 'test' / 'b.npy', cloud(1, 8))
    put(nested / 'can' / 'train' / 'c.npy', cloud(2, 8))
    put(nested / 'can' / 'test' / 'd.npy', cloud(3, 8))
    ds = open_dataset(nested, split='test')
    assert ds.split == 'test' and [ds.item_name(i) for i in range(2)] == [
        'can/test/d.npy', 'mug/test/b.npy']


def test_folder_errors(tmp_path: Path, tree: Path) -> None:
    with pytest.raises(DatasetError, match="no 'val' folder"):
        open_dataset(tree, split='val')
    empty = tmp_path / 'empty'
    empty.mkdir()
    with pytest.raises(DatasetError, match='no class folders'):
        open_dataset(empty)
    with pytest.raises(DatasetError, match='no such file or folder'):
        open_dataset(tmp_path / 'missing')
    single = put(tmp_path / 'one.pcd', cloud(0, 5))
    with pytest.raises(DatasetError, match='a single point cloud, not a dataset'):
        open_dataset(single)
    with pytest.raises(DatasetError, match='not a folder'):
        open_dataset(single, format='folder')
    with pytest.raises(DatasetError, match='subsample must be one of'):
        open_dataset(tree, num_points=8, subsample='random')
