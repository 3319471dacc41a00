"""ScanObjectNN HDF5 files (h5_files/ of the release) and its three standard variants.

OBJ_BG:    main_split/{training,test}_objectdataset.h5
OBJ_ONLY:  main_split_nobg/{training,test}_objectdataset.h5
PB_T50_RS: main_split/{training,test}_objectdataset_augmentedrot_scale75.h5
Each holds `data` (M, 2048, 3) float32, `label` (M,) and optionally `mask` (M, 2048).
"""

from __future__ import annotations

import re
from pathlib import Path

from point_gn_ros.datasets.h5 import H5Dataset
from point_gn_ros.datasets.subsample import Subsample
from point_gn_ros.errors import DatasetError

FORMAT = 'scanobjectnn_h5'
SCANOBJECTNN_CLASSES = ('bag', 'bin', 'box', 'cabinet', 'chair', 'desk', 'display', 'door',
                        'shelf', 'table', 'bed', 'pillow', 'sink', 'sofa', 'toilet')
# variant -> (sub-folder of h5_files, file-name suffix)
VARIANTS = {'PB_T50_RS': ('main_split', '_augmentedrot_scale75'),
            'OBJ_BG': ('main_split', ''),
            'OBJ_ONLY': ('main_split_nobg', '')}
_ALIASES = {'hardest': 'PB_T50_RS', 'pb_t50_rs': 'PB_T50_RS', 'obj_bg': 'OBJ_BG',
            'obj_only': 'OBJ_ONLY', 'objectdataset_augmentedrot_scale75': 'PB_T50_RS'}
_FILE_RE = re.compile(r'^(training|test)_objectdataset(.*)\.h5$')


def normalize_variant(variant: str) -> str:
    """'obj-bg', 'OBJ_BG', 'hardest', ... -> a key of VARIANTS, or DatasetError."""
    key = _ALIASES.get(variant.strip().lower().replace('-', '_'))
    if key is None:
        raise DatasetError(f'unknown ScanObjectNN variant {variant!r} '
                           f'(one of {", ".join(VARIANTS)})')
    return key


def _file_name(split: str, variant: str) -> str:
    stem = 'training' if split == 'train' else 'test'
    return f'{stem}_objectdataset{VARIANTS[variant][1]}.h5'


def _candidates(root: Path, split: str, variant: str) -> list[Path]:
    """Where the variant's file may be: under h5_files/<sub>/, <sub>/, or root itself."""
    sub, _ = VARIANTS[variant]
    name = _file_name(split, variant)
    out = [root / 'h5_files' / sub / name, root / sub / name]
    # A folder that *is* main_split or main_split_nobg holds the files directly.
    if ('nobg' in root.name) == (variant == 'OBJ_ONLY'):
        out.append(root / name)
    return out


def looks_like_scanobjectnn(path: Path) -> bool:
    """True for a *_objectdataset*.h5 file or a folder laid out like h5_files/."""
    if path.is_file():
        return bool(_FILE_RE.match(path.name))
    for pattern in ('*objectdataset*.h5', 'main_split*/*objectdataset*.h5',
                    'h5_files/main_split*/*objectdataset*.h5'):
        if any(_FILE_RE.match(p.name) for p in path.glob(pattern)):
            return True
    return False


def _variant_of_file(path: Path, suffix: str) -> str:
    if suffix == '':
        return 'OBJ_ONLY' if 'nobg' in path.parent.name else 'OBJ_BG'
    if suffix == VARIANTS['PB_T50_RS'][1] and 'nobg' not in path.parent.name:
        return 'PB_T50_RS'
    return suffix.lstrip('_')  # other augmented copies of the release: name them by suffix


def _class_names(root: Path) -> list[str]:
    names_file = root / 'shape_names.txt'
    if names_file.is_file():
        return [s.strip() for s in names_file.read_text().splitlines() if s.strip()]
    return list(SCANOBJECTNN_CLASSES)


def open_scanobjectnn(path: Path, split: str = 'train', variant: str | None = None,
                      num_points: int | None = None, subsample: Subsample = 'first'
                      ) -> H5Dataset:
    """ScanObjectNN folder or file -> H5Dataset with a `.variant` attribute.

    A folder: the variant's file for `split`; with variant None the first present
    of PB_T50_RS, OBJ_BG, OBJ_ONLY. A file: that file; its name sets split and variant.
    """
    if path.is_file():
        m = _FILE_RE.match(path.name)
        # A file named like the release sets split and variant; other names keep `split`.
        if m:
            split = 'train' if m.group(1) == 'training' else 'test'
        chosen, file = (_variant_of_file(path, m.group(2)) if m else None), path
    else:
        if split not in ('train', 'test'):
            raise DatasetError(f"{path}: split must be 'train' or 'test', got {split!r}")
        order = [normalize_variant(variant)] if variant is not None else list(VARIANTS)
        found = [(v, c) for v in order for c in _candidates(path, split, v) if c.is_file()]
        if not found:
            looked = [str(c) for v in order for c in _candidates(path, split, v)]
            raise DatasetError(f'{path}: no ScanObjectNN {split} file for variant '
                               f'{variant or "any"}; looked for {", ".join(looked)}')
        chosen, file = found[0]
    ds = H5Dataset(path, split, [file], _class_names(file.parent), FORMAT, num_points,
                   subsample)
    ds.variant = chosen
    return ds
