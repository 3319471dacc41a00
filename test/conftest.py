"""Shared fixtures: the ../shared data (skipped with a reason when absent, mandatory in CI)."""

from __future__ import annotations

import ctypes
from functools import lru_cache
import os
from pathlib import Path
import subprocess

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / 'shared'
MODELNET = SHARED / 'datasets' / 'modelnet40_1024'


def require_shared(path: Path = SHARED) -> Path:
    """Return path, or skip when it is absent (a user's clone); CI sets the switch that fails."""
    if path.exists():
        return path
    reason = f'{path} is absent: shared data sits beside the repository on dev/CI machines only'
    if os.environ.get('POINT_GN_REQUIRE_SHARED') == '1':
        pytest.fail(reason + ' (POINT_GN_REQUIRE_SHARED=1)')
    pytest.skip(reason)


@pytest.fixture(scope='session')
def shared_dir() -> Path:
    return require_shared(SHARED)


@pytest.fixture(scope='session')
def modelnet_dir() -> Path:
    return require_shared(MODELNET)


@lru_cache(maxsize=2)
def load_modelnet_split(split: str) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """A whole ModelNet40 split, read once per session.

    -> xyz (M, 1024, 3) float32, labels (M,) int64, the 40 class names. Read with h5py
    directly so core tests do not depend on the dataset readers.
    """
    import h5py

    root = require_shared(MODELNET)
    xyz, labels = [], []
    for path in sorted(root.glob(f'ply_data_{split}*.h5')):
        with h5py.File(path, 'r') as f:
            xyz.append(f['data'][:].astype(np.float32))
            labels.append(f['label'][:].reshape(-1).astype(np.int64))
    names = tuple((root / 'shape_names.txt').read_text().split())
    return np.concatenate(xyz), np.concatenate(labels), names


def load_modelnet_subset(split: str, per_class: int, offset: int = 0
                         ) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """First `per_class` objects of each class (after `offset`) of a ModelNet40 split.

    -> xyz (M, 1024, 3) float32, labels (M,) int64, class names.
    """
    xyz, labels, names = load_modelnet_split(split)
    pick = np.concatenate([np.flatnonzero(labels == c)[offset:offset + per_class]
                           for c in range(len(names))])
    return xyz[pick], labels[pick], list(names)


def agreement_rows(count: int, step: int) -> np.ndarray:
    """Rows of a split that a real-data agreement test checks: (M,) int64.

    Every `step`-th of `count` (a subsample that keeps a slow test under a minute on a
    2-core machine), or all of them with POINT_GN_FULL_AGREEMENT=1 (the full-set figures).
    """
    if os.environ.get('POINT_GN_FULL_AGREEMENT') == '1':
        step = 1
    return np.arange(0, count, step, dtype=np.int64)


def write_npy_tree(root: Path, classes: tuple[str, ...], per_class: dict[str, int],
                   scale: float = 1.0, offset: float = 0.0) -> Path:
    """A folder-tree dataset `root/<split>/<class>/<class>_<i>.npy` of real ModelNet40 objects.

    per_class: split -> objects per class; each cloud is written as xyz * scale + offset.
    """
    for split, n in per_class.items():
        xyz, labels, names = load_modelnet_subset(split, n)
        for name in classes:
            folder = root / split / name
            folder.mkdir(parents=True)
            for i, cloud in enumerate(xyz[labels == names.index(name)]):
                np.save(folder / f'{name}_{i}.npy', cloud * scale + offset)
    return root


TREE_CLASSES = ('chair', 'lamp', 'airplane')


@pytest.fixture(scope='module')
def three_class_tree(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder tree of real ModelNet40 objects: train/test x 3 classes (TREE_CLASSES), .npy."""
    return write_npy_tree(tmp_path_factory.mktemp('tree'), TREE_CLASSES, {'train': 6, 'test': 4})


class ArrayDataset:
    """In-memory dataset with the Dataset contract (for tests and tiny banks)."""

    def __init__(self, xyz: np.ndarray, labels: np.ndarray, class_names: list[str],
                 path: str = 'memory', split: str = 'train', format: str = 'array') -> None:
        self.xyz, self.labels, self.class_names = xyz, np.asarray(labels), list(class_names)
        self.path, self.split, self.format = path, split, format

    def __len__(self) -> int:
        return len(self.xyz)

    def __getitem__(self, i: int) -> tuple[np.ndarray, int]:
        return self.xyz[i], int(self.labels[i])


@pytest.fixture(scope='session')
def small_bank_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A bank of 4 ModelNet40 train objects per class (160 entries), built once per session."""
    from point_gn_ros.bank.builder import build_bank

    xyz, labels, names = load_modelnet_subset('train', 4)
    bank = build_bank(ArrayDataset(xyz, labels, names, str(MODELNET)), folds=2, progress=False)
    return bank.save(tmp_path_factory.mktemp('bank') / 'small_bank.npz')


# SIMD builds of a kernel file: compile flags -> the CPU flags needed to run the build.
# CI machines differ in which path -march=native takes; tests build each one they can run.
KERNEL_BUILDS = {'portable': ([], set()),
                 'avx2': (['-mavx2', '-mfma'], {'avx2', 'fma'}),
                 'avx512bw, no vnni': (['-mavx512f', '-mavx512bw', '-mavx512vl',
                                        '-mno-avx512vnni'], {'avx512f', 'avx512bw', 'avx512vl'}),
                 'avx512 vnni': (['-mavx512f', '-mavx512bw', '-mavx512vl', '-mavx512vnni'],
                                 {'avx512f', 'avx512bw', 'avx512vl', 'avx512_vnni'}),
                 # pgn_knn16.c's 16-bit codes (Ice Lake, Zen 4 and later)
                 'avx512 vbmi2': (['-mavx512f', '-mavx512bw', '-mavx512vl', '-mavx512vbmi2'],
                                  {'avx512f', 'avx512bw', 'avx512vl', 'avx512_vbmi2'})}


def kernel_build(source: str | tuple[str, ...], build: str, out_dir: Path,
                 extra: tuple[str, ...] = ()) -> ctypes.CDLL:
    """core/kernels/SOURCE built alone as KERNEL_BUILDS[build]; skips where it cannot run.

    source: one file, or a few linked into one library.
    """
    from point_gn_ros.core import kernels

    flags, needs = KERNEL_BUILDS[build]
    cc = kernels._compiler()
    if cc is None:
        pytest.skip('no C compiler: the kernels are not built on this machine')
    cpu = {flag for line in kernels._cpu_id().splitlines()
           if line.startswith(('flags', 'Features')) for flag in line.split(':', 1)[1].split()}
    if needs - cpu:
        pytest.skip(f'this CPU cannot run the {build} build (lacks {sorted(needs - cpu)})')
    sources = (source,) if isinstance(source, str) else source
    src_dir = Path(kernels.__file__).resolve().parent
    so = out_dir / f'{Path(sources[0]).stem}.so'
    subprocess.run([cc, '-O3', '-fPIC', '-shared', '-std=gnu11', *extra, *flags,
                    *(str(src_dir / s) for s in sources), '-o', str(so)],
                   check=True, capture_output=True)
    return ctypes.CDLL(str(so))
