"""Labelled clouds stored as HDF5 arrays `data` (M, N, 3) and `label` (M,) or (M, 1)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from point_gn_ros.datasets.base import Dataset
from point_gn_ros.datasets.subsample import Subsample, subsample, subsample_batch
from point_gn_ros.errors import DatasetError


def read_h5_labels(file: Path, data_key: str = 'data',
                   label_key: str = 'label') -> tuple[np.ndarray, tuple[int, int, int]]:
    """Validate one file -> (labels (M,) int64, data shape (M, N, 3)) without reading data."""
    try:
        with h5py.File(file, 'r') as f:
            for key in (data_key, label_key):
                if key not in f or not isinstance(f[key], h5py.Dataset):
                    raise DatasetError(f'{file}: no {key!r} array (keys: {", ".join(f)})')
            shape = f[data_key].shape
            kind = f[data_key].dtype.kind
            labels = np.asarray(f[label_key][()])
    except OSError as exc:
        raise DatasetError(f'{file}: cannot read HDF5 file ({exc})') from exc
    if len(shape) != 3 or shape[2] != 3 or kind not in 'fiu':
        raise DatasetError(f'{file}: {data_key!r} has shape {shape}, expected (M, N, 3) numbers')
    if labels.dtype.kind not in 'iu' or labels.size != shape[0]:
        raise DatasetError(f'{file}: {label_key!r} has shape {labels.shape} {labels.dtype}, '
                           f'expected {shape[0]} integer labels')
    return labels.reshape(-1).astype(np.int64), shape


class H5Dataset(Dataset):
    """Clouds in one or more HDF5 files, read lazily per item or in bulk by load_all.

    Files stay open after the first item read (close() or `with` releases them);
    pickling drops the handles so the dataset can go to worker processes.
    `variant` names the ScanObjectNN variant (None for other datasets).
    """

    variant: str | None = None

    def __init__(self, path: Path, split: str, files: Sequence[Path], class_names: list[str],
                 format: str, num_points: int | None = None, subsample: Subsample = 'first',
                 item_names: list[str] | None = None, data_key: str = 'data',
                 label_key: str = 'label') -> None:
        parts = [read_h5_labels(f, data_key, label_key) for f in files]
        for f, (labels, _) in zip(files, parts, strict=True):
            if labels.size and (labels.min() < 0 or labels.max() >= len(class_names)):
                raise DatasetError(f'{f}: labels range {labels.min()}..{labels.max()} but '
                                   f'there are {len(class_names)} class names')
        labels = np.concatenate([p[0] for p in parts]) if parts else np.empty(0, np.int64)
        self.format = format
        super().__init__(path, split, labels, class_names, num_points, subsample)
        self.files = list(files)
        self.points_per_file = [p[1][1] for p in parts]
        self.item_names = item_names
        self._offsets = np.cumsum([0] + [p[1][0] for p in parts])
        self._keys = (data_key, label_key)
        self._handles: dict[int, h5py.File] = {}

    def _locate(self, i: int) -> tuple[int, int]:
        part = int(np.searchsorted(self._offsets, i, side='right')) - 1
        return part, i - int(self._offsets[part])

    def _load(self, i: int) -> np.ndarray:
        part, row = self._locate(i)
        if part not in self._handles:
            self._handles[part] = h5py.File(self.files[part], 'r')
        xyz = np.asarray(self._handles[part][self._keys[0]][row], dtype=np.float32)
        if self.num_points is not None:
            xyz = subsample(xyz, self.num_points, self.subsample)
        return xyz

    def item_name(self, i: int) -> str | None:
        """Source name of cloud i (e.g. 'chair/chair_0001.npy') when the dataset has one."""
        return self.item_names[i] if self.item_names is not None else None

    def load_all(self) -> tuple[np.ndarray, np.ndarray]:
        """-> (xyz (M, N, 3) float32, labels (M,) int64), each file read in one call.

        N = num_points if set, else the files' common point count (DatasetError if
        they differ). 'fps' runs vectorised over the clouds of a file.
        """
        n = self.num_points
        if n is None:
            if len(set(self.points_per_file)) > 1:
                raise DatasetError(f'{self.path}: files have different point counts '
                                   f'{sorted(set(self.points_per_file))}; pass num_points')
            n = self.points_per_file[0] if self.files else 0
        out = np.empty((len(self), n, 3), dtype=np.float32)
        for part, file in enumerate(self.files):
            with h5py.File(file, 'r') as f:
                data = np.asarray(f[self._keys[0]][()], dtype=np.float32)
            lo, hi = int(self._offsets[part]), int(self._offsets[part + 1])
            out[lo:hi] = subsample_batch(data, n, self.subsample)
        return out, self.labels.copy()

    def close(self) -> None:
        """Close the HDF5 files opened by item reads."""
        for handle in self._handles.values():
            handle.close()
        self._handles.clear()

    def __enter__(self) -> H5Dataset:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown: h5py may already be torn down
            pass

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state['_handles'] = {}
        return state
