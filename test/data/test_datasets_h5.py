"""ModelNet40 and ScanObjectNN HDF5 datasets: layouts, variants, subsampling, bulk loads."""

from __future__ import annotations

import json
import copy
import re
from pathlib import Path

import h5py
import numpy as np
import pytest

from point_gn_ros.datasets import SCANOBJECTNN_CLASSES, detect_format, open_dataset
from point_gn_ros.errors import DatasetError
from point_gn_ros.core.sampling import fps_indices

NAMES = ['cup', 'lamp', 'plant', 'vase']


def write_h5(path: Path, data: np.ndarray, label: np.ndarray, **extra: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, 'w') as f:
        f['data'] = data
        f['label'] = label
        for key, arr in extra.items():
            f[key] = arr
    return path


def clouds(seed: int, m: int, n: int) -> np.ndarray:
    return np.random.default_rng(seed).standard_normal((m, n, 3)).astype(np.float32)


@pytest.fixture
def modelnet(tmp_path: Path) -> Path:
    """Two train files (5 + 3 clouds) and one test file, 32 points, PointNet naming."""
    root = tmp_path / 'mn'
    for name, seed, m in [('ply_data_train0.h5', 0, 5), ('ply_data_train1.h5', 1, 3),
                          ('ply_data_test0.h5', 2, 4)]:
        label = (np.arange(m) % 4).astype(np.uint8).reshape(m, 1)
        write_h5(root / name, clouds(seed, m, 32), label)
    (root / 'shape_names.txt').write_text('\n'.join(NAMES) + '\n')
    # The release lists files by their archive path; only the name should matter.
    (root / 'train_files.txt').write_text(
        'data/modelnet40_ply_hdf5_2048/ply_data_train0.h5\n'
        'data/modelnet40_ply_hdf5_2048/ply_data_train1.h5\n')
    for k, m in [(0, 5), (1, 3)]:
        (root / f'ply_data_train_{k}_id2file.json').write_text(
            json.dumps([f'{NAMES[i % 4]}/{NAMES[i % 4]}_{k}{i}.ply' for i in range(m)]))
    return root


def test_modelnet_layout_items_and_bulk_load(modelnet: Path) -> None:
    assert detect_format(modelnet) == 'modelnet40_h5'
    ds = open_dataset(modelnet)
    assert (ds.format, ds.split, len(ds), ds.class_names) == ('modelnet40_h5', 'train', 8, NAMES)
    assert ds.labels.dtype == np.int64 and ds.labels.tolist() == [0, 1, 2, 3, 0, 0, 1, 2]
    want = np.concatenate([clouds(0, 5, 32), clouds(1, 3, 32)])
    xyz, label = ds[6]
    assert xyz.dtype == np.float32 and xyz.shape == (32, 3) and label == 1
    np.testing.assert_array_equal(xyz, want[6])
    np.testing.assert_array_equal(ds[-1][0], want[7])
    with pytest.raises(IndexError):
        ds[8]
    all_xyz, labels = ds.load_all()
    np.testing.assert_array_equal(all_xyz, want)
    np.testing.assert_array_equal(labels, ds.labels)
    assert ds.item_name(5) == 'cup/cup_10.ply' and ds.skipped == []
    assert [x.shape for x, _ in ds] == [(32, 3)] * 8
    ds.close()


def test_modelnet_test_split_without_listing_or_id2file(modelnet: Path) -> None:
    ds = open_dataset(modelnet, split='test')
    assert len(ds) == 4 and ds.item_name(0) is None
    np.testing.assert_array_equal(ds.load_all()[0], clouds(2, 4, 32))


@pytest.mark.parametrize('method', ['first', 'fps'])
def test_modelnet_num_points(modelnet: Path, method: str) -> None:
    ds = open_dataset(modelnet, num_points=10, subsample=method)
    full = open_dataset(modelnet)[3][0]
    want = full[:10] if method == 'first' else full[fps_indices(full, 10)]
    np.testing.assert_array_equal(ds[3][0], want)
    all_xyz, _ = ds.load_all()
    assert all_xyz.shape == (8, 10, 3)
    np.testing.assert_array_equal(all_xyz[3], want)


def test_single_file_sets_split_and_copies_without_handles(modelnet: Path) -> None:
    ds = open_dataset(modelnet / 'ply_data_test0.h5')
    assert (ds.split, len(ds), ds.class_names) == ('test', 4, NAMES)
    first = ds[0][0]
    # deepcopy goes through the pickle protocol (__getstate__), as a DataLoader worker would
    clone = copy.deepcopy(ds)
    np.testing.assert_array_equal(clone[0][0], first)
    clone.close()
    ds.close()


def test_files_with_different_point_counts_need_num_points(tmp_path: Path) -> None:
    write_h5(tmp_path / 'ply_data_train0.h5', clouds(0, 2, 16), np.zeros((2, 1), np.uint8))
    write_h5(tmp_path / 'ply_data_train1.h5', clouds(1, 2, 8), np.zeros((2, 1), np.uint8))
    ds = open_dataset(tmp_path)
    assert ds.class_names[0] == 'airplane'  # no shape_names.txt: the ModelNet40 list
    with pytest.raises(DatasetError, match='different point counts'):
        ds.load_all()
    xyz, _ = open_dataset(tmp_path, num_points=12).load_all()
    np.testing.assert_array_equal(xyz[3], clouds(1, 2, 8)[1][np.arange(12) % 8])


@pytest.mark.parametrize(('setup', 'words'), [
    ('labels', 'labels range 0..7'),
    ('nodata', "no 'data' array"),
    ('shape', 'expected (M, N, 3)'),
    ('count', 'expected 2 integer labels'),
    ('nothdf5', 'cannot read HDF5'),
    ('listing', 'lists missing file'),
    ('split', "split must be 'train' or 'test'"),
])
def test_bad_modelnet(tmp_path: Path, setup: str, words: str) -> None:
    f = tmp_path / 'ply_data_train0.h5'
    data, label = clouds(0, 2, 8), np.zeros((2, 1), np.uint8)
    if setup == 'labels':
        (tmp_path / 'shape_names.txt').write_text('a\nb\n')
        write_h5(f, data, np.array([[0], [7]], np.uint8))
    elif setup == 'nodata':
        with h5py.File(f, 'w') as h:
            h['points'] = data
            h['label'] = label
    elif setup == 'shape':
        write_h5(f, data[:, :, :2], label)
    elif setup == 'count':
        write_h5(f, data, np.zeros((3, 1), np.uint8))
    elif setup == 'nothdf5':
        f.write_bytes(b'not hdf5 at all')
    elif setup == 'listing':
        write_h5(f, data, label)
        (tmp_path / 'train_files.txt').write_text('ply_data_train0.h5\nply_data_train9.h5\n')
    else:
        write_h5(f, data, label)
    with pytest.raises(DatasetError, match=re.escape(words)) as err:
        open_dataset(tmp_path, split='val' if setup == 'split' else 'train')
    named = 'train_files.txt' if setup == 'listing' else f.name
    assert (tmp_path / named).as_posix() in str(err.value) or setup == 'split'



@pytest.fixture
def scanobjectnn(tmp_path: Path) -> Path:
    """h5_files/ of the release with distinct sizes per variant and split."""
    root = tmp_path / 'h5_files'
    sizes = {('main_split', ''): 6, ('main_split', '_augmentedrot_scale75'): 9,
             ('main_split_nobg', ''): 4}
    for (sub, suffix), m in sizes.items():
        for split, extra in [('training', 0), ('test', 1)]:
            label = (np.arange(m + extra) % 15).astype(np.int64)
            mask = np.zeros((m + extra, 64), np.int32)
            write_h5(root / sub / f'{split}_objectdataset{suffix}.h5',
                     clouds(m + extra, m + extra, 64), label, mask=mask)
    return root


@pytest.mark.parametrize(('variant', 'split', 'size'), [
    (None, 'train', 9), ('PB_T50_RS', 'test', 10), ('obj_bg', 'train', 6), ('OBJ-ONLY', 'test', 5),
    ('hardest', 'train', 9),
])
def test_scanobjectnn_variants(scanobjectnn: Path, variant: str | None, split: str,
                               size: int) -> None:
    assert detect_format(scanobjectnn) == 'scanobjectnn_h5'
    ds = open_dataset(scanobjectnn, split=split, variant=variant)
    assert (ds.format, ds.split, len(ds)) == ('scanobjectnn_h5', split, size)
    assert ds.class_names == list(SCANOBJECTNN_CLASSES) and len(ds.class_names) == 15
    assert ds.variant == {None: 'PB_T50_RS', 'hardest': 'PB_T50_RS'}.get(
        variant, variant and variant.upper().replace('-', '_'))
    np.testing.assert_array_equal(ds.load_all()[0], clouds(size, size, 64))


def test_scanobjectnn_sub_folder_file_and_num_points(scanobjectnn: Path) -> None:
    parent = scanobjectnn.parent
    assert open_dataset(parent, split='test', variant='OBJ_ONLY').variant == 'OBJ_ONLY'
    nobg = open_dataset(scanobjectnn / 'main_split_nobg')
    assert (nobg.variant, len(nobg)) == ('OBJ_ONLY', 4)
    bg = open_dataset(scanobjectnn / 'main_split', variant='OBJ_BG', num_points=16)
    assert bg.load_all()[0].shape == (6, 16, 3) and bg[0][0].shape == (16, 3)
    one = open_dataset(scanobjectnn / 'main_split' / 'test_objectdataset_augmentedrot_scale75.h5')
    assert (one.split, one.variant, len(one)) == ('test', 'PB_T50_RS', 10)
    forced = open_dataset(scanobjectnn / 'main_split' / 'test_objectdataset.h5',
                          format='scanobjectnn_h5')
    assert (forced.variant, forced.split) == ('OBJ_BG', 'test')


def test_scanobjectnn_errors(scanobjectnn: Path) -> None:
    with pytest.raises(DatasetError, match='unknown ScanObjectNN variant'):
        open_dataset(scanobjectnn, variant='OBJ_XL')
    (scanobjectnn / 'main_split_nobg' / 'test_objectdataset.h5').unlink()
    with pytest.raises(DatasetError, match='no ScanObjectNN test file for variant OBJ_ONLY'):
        open_dataset(scanobjectnn, split='test', variant='OBJ_ONLY')
    with pytest.raises(DatasetError, match='applies to ScanObjectNN only'):
        open_dataset(scanobjectnn, format='folder', variant='OBJ_BG')
    with pytest.raises(DatasetError, match="unknown dataset format 'kitti'"):
        open_dataset(scanobjectnn, format='kitti')


def test_real_modelnet40_1024(modelnet_dir: Path) -> None:
    train, test = open_dataset(modelnet_dir), open_dataset(modelnet_dir, split='test')
    assert (len(train), len(test), len(train.class_names)) == (9843, 2468, 40)
    assert train.class_names[0] == 'airplane' and test.class_names[-1] == 'xbox'
    assert set(np.unique(test.labels)) == set(range(40))
    xyz, labels = test.load_all()
    assert xyz.shape == (2468, 1024, 3) and xyz.dtype == np.float32
    for i in (0, 1234, 2467):
        cloud, label = test[i]
        np.testing.assert_array_equal(cloud, xyz[i])
        assert label == labels[i]
        assert test.item_name(i).startswith(test.class_names[label] + '/')
    assert test.class_counts()['airplane'] == 100
    test.close()
