"""The Dataset interface every reader returns (see docs/TEAM_NOTES.md, Datasets)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from point_gn_ros.datasets.subsample import SUBSAMPLE_METHODS, Subsample
from point_gn_ros.errors import DatasetError

SPLITS = ('train', 'test')


class Dataset:
    """A labelled list of point clouds.

    Attributes: `labels` (len,) int64; `class_names` list[str] (label i names
    class_names[i]); `format` str; `path` Path; `split` str; `skipped` list of
    (file, reason) for inputs that were left out; `num_points`/`subsample` as
    passed to open_dataset (None = clouds keep their stored point count).
    Subclasses implement `_load(i)` and may override `load_all`.
    """

    format: str = ''

    def __init__(self, path: Path, split: str, labels: np.ndarray, class_names: list[str],
                 num_points: int | None = None, subsample: Subsample = 'first') -> None:
        if subsample not in SUBSAMPLE_METHODS:
            raise DatasetError(f'subsample must be one of {SUBSAMPLE_METHODS}, got {subsample!r}')
        if num_points is not None and num_points < 1:
            raise DatasetError(f'num_points must be >= 1, got {num_points}')
        self.path = Path(path)
        self.split = split
        self.labels = np.asarray(labels, dtype=np.int64)
        self.class_names = list(class_names)
        self.num_points = num_points
        self.subsample = subsample
        self.skipped: list[tuple[str, str]] = []
        self._check_labels()

    def _check_labels(self) -> None:
        """Raise DatasetError if any label does not index class_names."""
        if self.labels.size and (self.labels.min() < 0
                                 or self.labels.max() >= len(self.class_names)):
            raise DatasetError(f'{self.path}: labels range {self.labels.min()}..'
                               f'{self.labels.max()} but there are {len(self.class_names)} '
                               'class names')

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    def __getitem__(self, i: int) -> tuple[np.ndarray, int]:
        """-> (xyz (N, 3) float32, label int). Negative indices count from the end."""
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f'index {i} out of range for {n} clouds')
        i = int(i) % n
        return self._load(i), int(self.labels[i])

    def __iter__(self) -> Iterator[tuple[np.ndarray, int]]:
        for i in range(len(self)):
            yield self[i]

    def _load(self, i: int) -> np.ndarray:
        raise NotImplementedError

    def load_all(self) -> tuple[np.ndarray, np.ndarray]:
        """-> (xyz (M, N, 3) float32, labels (M,) int64), all clouds stacked.

        Needs one point count N for every cloud (pass num_points otherwise);
        raises DatasetError if counts differ.
        """
        clouds = [self._load(i) for i in range(len(self))]
        counts = {c.shape[0] for c in clouds}
        if len(counts) > 1:
            raise DatasetError(f'{self.path}: clouds have different point counts '
                               f'({min(counts)}..{max(counts)}); pass num_points to stack them')
        if not clouds:
            return np.empty((0, self.num_points or 0, 3), np.float32), self.labels.copy()
        return np.stack(clouds), self.labels.copy()

    def class_counts(self) -> dict[str, int]:
        """Class name -> number of clouds with that label."""
        counts = np.bincount(self.labels, minlength=len(self.class_names))
        return {name: int(c) for name, c in zip(self.class_names, counts, strict=True)}

    def __repr__(self) -> str:
        return (f'{type(self).__name__}(format={self.format!r}, path={str(self.path)!r}, '
                f'split={self.split!r}, clouds={len(self)}, classes={len(self.class_names)}, '
                f'skipped={len(self.skipped)})')
