"""Folder trees of point files: <root>/[train|test/]<class>/.../<file>.

Class names are the sorted class-folder names (the union over train/ and test/,
so both splits number classes the same way). Files are read when the dataset is
opened; unreadable ones are left out and listed in `.skipped`.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from point_gn_ros.datasets.base import Dataset
from point_gn_ros.datasets.points import POINT_EXTENSIONS, read_points
from point_gn_ros.datasets.subsample import Subsample, subsample
from point_gn_ros.errors import DatasetError

FORMAT = 'folder'
SPLIT_DIRS = ('train', 'test')
_MAX_LISTED = 5  # reasons quoted per empty class in the error message


def _visible_dirs(path: Path) -> list[Path]:
    return sorted(p for p in path.iterdir() if p.is_dir() and not p.name.startswith('.'))


def _walk_files(top: Path) -> list[Path]:
    """Every non-hidden file under top, in sorted (reproducible) order."""
    out = []
    for dirpath, dirnames, filenames in os.walk(top):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith('.'))
        out.extend(Path(dirpath) / f for f in sorted(filenames) if not f.startswith('.'))
    return out


class FolderDataset(Dataset):
    """Clouds read from a class-per-folder tree; `files[i]` is cloud i's file."""

    format = FORMAT

    def __init__(self, root: Path, split: str = 'train', num_points: int | None = None,
                 subsample: Subsample = 'first') -> None:
        if not root.is_dir():
            raise DatasetError(f'{root}: not a folder')
        class_dirs, effective_split, stray = _class_dirs(root, split)
        names = sorted(class_dirs)
        if not names:
            raise DatasetError(f'{root}: no class folders (expected '
                               '<root>/[train|test/]<class>/<point files>)')
        super().__init__(root, effective_split, np.empty(0, np.int64), names, num_points,
                         subsample)
        self.skipped = [(str(f), 'not inside a class folder') for f in stray]
        clouds: list[np.ndarray] = []
        labels: list[int] = []
        files: list[Path] = []
        empty: dict[str, list[tuple[str, str]]] = {}
        for label, name in enumerate(names):
            found = 0
            before = len(self.skipped)
            for top in class_dirs[name]:
                for f in _walk_files(top):
                    xyz = self._read(f)
                    if xyz is not None:
                        clouds.append(xyz)
                        labels.append(label)
                        files.append(f)
                        found += 1
            if not found:
                reasons = self.skipped[before:]
                where = ', '.join(str(t) for t in class_dirs[name]) or f'{name} (no folder)'
                self.skipped.append((where, 'class has no readable point file'))
                empty[name] = reasons
        if empty:
            raise DatasetError(_empty_message(root, effective_split, empty))
        self.labels = np.asarray(labels, dtype=np.int64)
        self.files = files
        self._clouds = clouds

    def _read(self, f: Path) -> np.ndarray | None:
        """Cloud of one file, or None after recording why it was skipped."""
        if f.suffix.lower() not in POINT_EXTENSIONS:
            self.skipped.append((str(f), f'unsupported extension {f.suffix!r}'))
            return None
        try:
            if f.stat().st_size == 0:    # say so plainly, not as a format's parse error
                self.skipped.append((str(f), 'empty file (0 bytes)'))
                return None
            xyz = read_points(f)
        except OSError as exc:
            self.skipped.append((str(f), f'unreadable ({exc.strerror or exc})'))
            return None
        except DatasetError as exc:
            self.skipped.append((str(f), str(exc).removeprefix(f'{f}: ')))
            return None
        if xyz.shape[0] == 0:
            self.skipped.append((str(f), 'no finite points'))
            return None
        if self.num_points is not None:
            xyz = subsample(xyz, self.num_points, self.subsample)
        return xyz

    def _load(self, i: int) -> np.ndarray:
        return self._clouds[i].copy()

    def item_name(self, i: int) -> str:
        """Cloud i's file relative to the dataset root."""
        return self.files[i].relative_to(self.path).as_posix()


def _class_dirs(root: Path, split: str) -> tuple[dict[str, list[Path]], str, list[Path]]:
    """-> ({class: folders to read for this split}, split actually used, stray files).

    Layouts: root/<split>/<class>/...; root/<class>/<split>/...; root/<class>/...
    (no split folders: every file is used and the split is reported as 'all').
    """
    top_dirs = {p.name for p in _visible_dirs(root)}
    if top_dirs & {*SPLIT_DIRS, split}:
        split_root = root / split
        if not split_root.is_dir():
            found = ', '.join(sorted(top_dirs))
            raise DatasetError(f'{root}: no {split!r} folder (found: {found})')
        names: set[str] = set()
        for s in {*SPLIT_DIRS, split}:
            if (root / s).is_dir():
                names.update(p.name for p in _visible_dirs(root / s))
        stray = [p for p in sorted(split_root.iterdir())
                 if p.is_file() and not p.name.startswith('.')]
        return ({n: [split_root / n] if (split_root / n).is_dir() else [] for n in names},
                split, stray)
    classes = _visible_dirs(root)
    stray = [p for p in sorted(root.iterdir()) if p.is_file() and not p.name.startswith('.')]
    per_class_split = any((c / s).is_dir() for c in classes for s in SPLIT_DIRS)
    if per_class_split:  # e.g. the ModelNet40 mesh release: <class>/train/, <class>/test/
        return ({c.name: [c / split] if (c / split).is_dir() else [] for c in classes},
                split, stray)
    return {c.name: [c] for c in classes}, 'all', stray


def _empty_message(root: Path, split: str, empty: dict[str, list[tuple[str, str]]]) -> str:
    lines = [f'{root}: {len(empty)} class(es) have no readable point file for split '
             f'{split!r}: {", ".join(empty)}']
    for name, reasons in empty.items():
        for file, why in reasons[:_MAX_LISTED]:
            lines.append(f'  {name}: {file}: {why}')
        if len(reasons) > _MAX_LISTED:
            lines.append(f'  {name}: ... {len(reasons) - _MAX_LISTED} more skipped files')
        if not reasons:
            lines.append(f'  {name}: no files')
    return '\n'.join(lines)
