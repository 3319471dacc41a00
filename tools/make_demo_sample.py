#!/usr/bin/env python3
"""Write point_gn_ros/data/demo_objects.npz: held-out ModelNet40 test objects for the demo.

One object per class (the first of each class in the test split, or the --index-th),
1024 points as float16 (a ~250 KB file the package can ship, so `make demo` works on a
machine without ../shared). Arrays (read with allow_pickle=False):
  xyz          (C, 1024, 3) float16  unit-sphere dataset clouds
  labels       (C,) int64            class index of each object
  class_names  (40,) unicode         ModelNet40 class names, index = label
  source       (C,) unicode          dataset file of each object
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import h5py
import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_SRC = REPO.parent / 'shared' / 'datasets' / 'modelnet40_1024'
DEFAULT_OUT = REPO / 'point_gn_ros' / 'data' / 'demo_objects.npz'


def load_test_split(root: Path) -> tuple[np.ndarray, np.ndarray, list[str], list[str]]:
    """ModelNet40 test split: xyz, labels, class names (from the id2file lists), file names."""
    xyz, labels, files = [], [], []
    names: dict[int, str] = {}
    for h5 in sorted(root.glob('ply_data_test*.h5')):
        with h5py.File(h5, 'r') as f:
            xyz.append(f['data'][:])
            lab = f['label'][:].reshape(-1).astype(np.int64)
        ids = json.loads((root / f'{h5.stem[:-1]}_{h5.stem[-1]}_id2file.json').read_text())
        for label, file in zip(lab, ids, strict=True):
            names[int(label)] = file.split('/')[0]
        labels.append(lab)
        files += ids
    if not xyz:
        raise SystemExit(f'no ply_data_test*.h5 under {root}')
    return (np.concatenate(xyz), np.concatenate(labels),
            [names[i] for i in range(len(names))], files)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--src', type=Path, default=DEFAULT_SRC, help='modelnet40_1024 folder')
    parser.add_argument('-o', '--out', type=Path, default=DEFAULT_OUT)
    parser.add_argument('--index', type=int, default=0, help='which object of each class')
    args = parser.parse_args()

    xyz, labels, names, files = load_test_split(args.src)
    pick = [np.flatnonzero(labels == c)[args.index] for c in range(len(names))]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.out, xyz=xyz[pick].astype(np.float16), labels=labels[pick],
                        class_names=np.array(names), source=np.array([files[i] for i in pick]))
    with np.load(args.out, allow_pickle=False) as z:   # what the demo will do
        assert z['xyz'].shape == (len(names), xyz.shape[1], 3)
    print(f'wrote {args.out} ({args.out.stat().st_size / 1024:.0f} KB, {len(pick)} objects)')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
