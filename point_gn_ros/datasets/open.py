"""open_dataset: one entry point that recognises the dataset layout at a path."""

from __future__ import annotations

from pathlib import Path

from point_gn_ros.datasets.base import Dataset
from point_gn_ros.datasets.folder import FolderDataset
from point_gn_ros.datasets.modelnet40 import looks_like_modelnet40, open_modelnet40
from point_gn_ros.datasets.points import POINT_EXTENSIONS
from point_gn_ros.datasets.scanobjectnn import looks_like_scanobjectnn, open_scanobjectnn
from point_gn_ros.datasets.subsample import Subsample
from point_gn_ros.errors import DatasetError

FORMATS = ('modelnet40_h5', 'scanobjectnn_h5', 'folder')


def detect_format(path: str | Path) -> str:
    """The dataset kind at path: one of FORMATS, or DatasetError saying why not."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(f'{path}: no such file or folder')
    if path.is_file():
        if looks_like_modelnet40(path):
            return 'modelnet40_h5'
        if looks_like_scanobjectnn(path):
            return 'scanobjectnn_h5'
        if path.suffix.lower() in POINT_EXTENSIONS:
            raise DatasetError(f'{path}: a single point cloud, not a dataset '
                               '(read it with read_points)')
        raise DatasetError(f'{path}: not a recognised dataset file; pass format= one of '
                           f'{", ".join(FORMATS)}')
    if looks_like_modelnet40(path):
        return 'modelnet40_h5'
    if looks_like_scanobjectnn(path):
        return 'scanobjectnn_h5'
    return 'folder'


def open_dataset(path: str | Path, split: str = 'train', format: str | None = None,
                 num_points: int | None = None, subsample: Subsample = 'first',
                 variant: str | None = None) -> Dataset:
    """Open a labelled point-cloud dataset.

    path: a ModelNet40 h5 folder or file, a ScanObjectNN h5 folder or file, or a
    class-per-folder tree. format: force one of FORMATS instead of detecting.
    num_points: give every cloud exactly this many points ('first' N or 'fps';
    smaller clouds repeat their points). variant: ScanObjectNN OBJ_BG, OBJ_ONLY or
    PB_T50_RS. Every error is a DatasetError naming the path.
    """
    path = Path(path)
    if not path.exists():
        raise DatasetError(f'{path}: no such file or folder')
    kind = detect_format(path) if format is None else format
    if kind not in FORMATS:
        raise DatasetError(f'unknown dataset format {kind!r} (one of {", ".join(FORMATS)})')
    if variant is not None and kind != 'scanobjectnn_h5':
        raise DatasetError(f'{path}: variant={variant!r} applies to ScanObjectNN only, '
                           f'this is {kind}')
    if kind == 'modelnet40_h5':
        return open_modelnet40(path, split, num_points, subsample)
    if kind == 'scanobjectnn_h5':
        return open_scanobjectnn(path, split, variant, num_points, subsample)
    return FolderDataset(path, split, num_points, subsample)
