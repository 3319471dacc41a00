"""Rotation handling for sensor-realistic banks, chosen by grouped k-fold CV on train only.

Candidates: yaw canonicalisation (EncoderConfig.yaw_align) and yaw augmentation (no canonical
frame; every bank entry at a random yaw). The bank set is every `--subset`-th ModelNet40 train
object, its complete cloud plus K simulated single-view scans, each at a random yaw
(`ViewsDataset`); folds keep an object and its views together (`groups`). Scores: held-out
single-view scans (the choice) and held-out complete objects, separately. Reads cached features
(`scripts/encode_views.py` writes them); never touches the test split.

    python scripts/single_view_study.py ../shared/datasets/modelnet40_1024 --cache /work/cache
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from point_gn_ros.bank.builder import encode_dataset
from point_gn_ros.bank.selection import select
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.datasets import open_dataset
from point_gn_ros.datasets.views import ViewsDataset
from point_gn_ros.recognizer import make_encoder

CONFIGS = {'yaw_align': True, 'yaw_augment': False}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('dataset')
    p.add_argument('--cache', required=True)
    p.add_argument('--views', type=int, default=4)
    p.add_argument('--subset', type=int, default=3, help='every n-th train object')
    p.add_argument('--folds', type=int, default=5)
    p.add_argument('--full-cached', nargs='*', default=['yaw_align'],
                   help='configs whose features are cached for the whole train split '
                        '(the subset rows are taken from them)')
    args = p.parse_args()
    train = open_dataset(args.dataset, split='train')
    sources = np.arange(0, len(train), args.subset)
    results = {}
    for name, align in CONFIGS.items():
        enc = make_encoder(EncoderConfig(yaw_align=align))
        if name in args.full_cached:
            ds = ViewsDataset(train, args.views, 0, include_full=True, random_yaw=True)
            feats = encode_dataset(ds, enc, cache_dir=Path(args.cache))
            rows = np.isin(ds.groups, sources)
            feats, labels, groups, view = (feats[rows], ds.labels[rows], ds.groups[rows],
                                           ds.view_index[rows])
        else:
            ds = ViewsDataset(train, args.views, 0, include_full=True, random_yaw=True,
                              sources=sources)
            feats = encode_dataset(ds, enc, cache_dir=Path(args.cache))
            labels, groups, view = ds.labels, ds.groups, ds.view_index
        sel = select(feats, labels, len(train.class_names), standardize_options=('standardize',),
                     folds=args.folds, groups=groups)
        ok = sel.heldout_correct
        results[name] = {'entries': int(len(labels)), 'gamma': sel.gamma,
                         'cv_all': float(ok.mean()), 'cv_views': float(ok[view >= 0].mean()),
                         'cv_complete': float(ok[view < 0].mean())}
        print(name, json.dumps(results[name]), flush=True)
    best = max(results, key=lambda n: results[n]['cv_views'])
    print(f'chosen by CV on held-out single-view scans: {best}')


if __name__ == '__main__':
    main()
