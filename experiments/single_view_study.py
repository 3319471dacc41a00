"""Rotation handling for sensor-realistic banks, chosen by grouped k-fold CV on train only.

Candidates: yaw canonicalisation (EncoderConfig.yaw_align) and yaw augmentation (no canonical
frame; every bank entry at a random yaw). The bank set is every `--subset`-th ModelNet40 train
object, its complete cloud plus K simulated single-view scans, each at a random yaw
(`ViewsDataset`); folds keep an object and its views together (`groups`). Scores: held-out
single-view scans (the choice) and held-out complete objects, separately. Encodes the features
(cached in --cache, keyed by data, view spec and encoder); never touches the test split.

    python experiments/single_view_study.py ../shared/datasets/modelnet40_1024 --cache DIR
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
    p.add_argument('--cached-subset', nargs=2, action='append', metavar=('CONFIG', 'N'),
                   default=[], help='features of CONFIG are cached for every N-th object '
                                    '(default 1: all); the study takes its rows from them')
    p.add_argument('--configs', nargs='+', default=list(CONFIGS), choices=list(CONFIGS))
    p.add_argument('--dims', type=int, default=224, help="PCA width (the shipped bank's)")
    p.add_argument('--alphas', type=float, nargs='*', default=[0.1],
                   help='whitening / LDA shrinkages (none: plain kernel vote)')
    p.add_argument('--weights', type=float, nargs='*', default=[0.1, 0.3],
                   help='LDA fusion weights')
    args = p.parse_args()
    train = open_dataset(args.dataset, split='train')
    sources = np.arange(0, len(train), args.subset)
    results = {}
    for name in args.configs:
        align = CONFIGS[name]
        enc = make_encoder(EncoderConfig(yaw_align=align))
        every = int(dict(args.cached_subset).get(name, 1))
        # Views depend only on (seed, source object): a subset's rows equal the full set's.
        ds = ViewsDataset(train, args.views, 0, include_full=True, random_yaw=True,
                          sources=None if every == 1 else np.arange(0, len(train), every))
        feats = encode_dataset(ds, enc, cache_dir=Path(args.cache))
        rows = np.isin(ds.groups, sources)
        feats, labels, groups, view = (feats[rows], ds.labels[rows], ds.groups[rows],
                                       ds.view_index[rows])
        sel = select(feats, labels, len(train.class_names), standardize_options=('standardize',),
                     dims_options=(args.dims,), folds=args.folds, groups=groups,
                     alphas=tuple(args.alphas), weights=tuple(args.weights),
                     whiten_options=(True,) if args.alphas else (False,))
        ok = sel.heldout_correct
        results[name] = {'entries': int(len(labels)), 'gamma': sel.gamma,
                         'whiten_alpha': sel.alpha, 'lda_alpha': sel.lda_alpha,
                         'weight': sel.fusion_weight,
                         'cv_all': float(ok.mean()), 'cv_views': float(ok[view >= 0].mean()),
                         'cv_complete': float(ok[view < 0].mean())}
        print(name, json.dumps(results[name]), flush=True)
    best = max(results, key=lambda n: results[n]['cv_views'])
    print(f'chosen by CV on held-out single-view scans: {best}')


if __name__ == '__main__':
    main()
