"""ModelNet40 in the PointNet HDF5 layout (modelnet40_ply_hdf5_2048 and its 1024 cut).

Folder: ply_data_{train,test}<k>.h5 (`data` (M, N, 3), `label` (M, 1)), shape_names.txt,
optional {train,test}_files.txt and ply_data_{split}_<k>_id2file.json (source names).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from point_gn_ros.datasets.h5 import H5Dataset
from point_gn_ros.datasets.subsample import Subsample
from point_gn_ros.errors import DatasetError

FORMAT = 'modelnet40_h5'
MODELNET40_CLASSES = (
    'airplane bathtub bed bench bookshelf bottle bowl car chair cone cup curtain desk door '
    'dresser flower_pot glass_box guitar keyboard lamp laptop mantel monitor night_stand '
    'person piano plant radio range_hood sink sofa stairs stool table tent toilet tv_stand '
    'vase wardrobe xbox').split()
_FILE_RE = re.compile(r'^ply_data_(train|test)(\d*)\.h5$')


def looks_like_modelnet40(path: Path) -> bool:
    """True for a ply_data_*.h5 file or a folder holding one."""
    if path.is_file():
        return bool(_FILE_RE.match(path.name))
    return any(_FILE_RE.match(p.name) for p in path.glob('ply_data_*.h5'))


def _split_files(root: Path, split: str) -> list[Path]:
    """The split's h5 files: from {split}_files.txt if present, else by name, in order."""
    listing = root / f'{split}_files.txt'
    if listing.is_file():
        # Entries are paths from the original archive (data/modelnet40.../x.h5): use the name.
        names = [Path(s.strip()).name for s in listing.read_text().splitlines() if s.strip()]
        files = [root / n for n in names]
        missing = [str(f) for f in files if not f.is_file()]
        if missing:
            raise DatasetError(f'{listing}: lists missing file(s) {", ".join(missing)}')
        return files
    found = [(m, p) for p in root.glob(f'ply_data_{split}*.h5') if (m := _FILE_RE.match(p.name))]
    found.sort(key=lambda mp: (int(mp[0].group(2) or 0), mp[1].name))
    return [p for _, p in found]


def _class_names(root: Path) -> list[str]:
    names_file = root / 'shape_names.txt'
    if names_file.is_file():
        names = [s.strip() for s in names_file.read_text().splitlines() if s.strip()]
        if not names:
            raise DatasetError(f'{names_file}: no class names')
        return names
    return list(MODELNET40_CLASSES)


def _item_names(files: list[Path]) -> list[str] | None:
    """Concatenated id2file lists, or None unless every file has a readable one."""
    names: list[str] = []
    for f in files:
        m = _FILE_RE.match(f.name)
        side = f.with_name(f'ply_data_{m.group(1)}_{m.group(2) or 0}_id2file.json') if m else f
        try:
            entries = json.loads(side.read_text())
        except (OSError, ValueError):
            return None
        if not isinstance(entries, list):
            return None
        names.extend(str(e) for e in entries)
    return names


def open_modelnet40(path: Path, split: str = 'train', num_points: int | None = None,
                    subsample: Subsample = 'first') -> H5Dataset:
    """ModelNet40 folder (or one ply_data_*.h5 file, whose own split wins) -> H5Dataset."""
    if path.is_file():
        m = _FILE_RE.match(path.name)
        # A file named like the release sets the split; any other name keeps `split`.
        root, split, files = path.parent, (m.group(1) if m else split), [path]
    else:
        if split not in ('train', 'test'):
            raise DatasetError(f"{path}: split must be 'train' or 'test', got {split!r}")
        root, files = path, _split_files(path, split)
        if not files:
            raise DatasetError(f'{path}: no ply_data_{split}*.h5 files')
    ds = H5Dataset(path, split, files, _class_names(root), FORMAT, num_points, subsample)
    names = _item_names(files)
    ds.item_names = names if names is not None and len(names) == len(ds) else None
    return ds
