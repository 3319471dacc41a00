"""Encode (and cache) the feature sets of the single-view study: train + K views, test both ways.

Every set is cached in --cache by `encode_dataset` (key: data, split incl. the view spec,
encoder version and configuration), so `point_gn bank build --views K --cache DIR` and
`point_gn eval --single-view --cache DIR` reuse them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from point_gn_ros.bank.builder import encode_dataset
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.datasets import open_dataset
from point_gn_ros.datasets.views import ViewsDataset
from point_gn_ros.recognizer import make_encoder


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument('dataset')
    p.add_argument('--cache', required=True)
    p.add_argument('--views', type=int, default=4)
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--test-seed', type=int, default=0)
    p.add_argument('--subset', type=int, default=1, help='every n-th train object only')
    p.add_argument('--configs', nargs='+', default=['aligned', 'plain'])
    p.add_argument('--sets', nargs='+', default=['train', 'test'])
    args = p.parse_args()
    cache = Path(args.cache)
    encs = {name: make_encoder(EncoderConfig(yaw_align=name == 'aligned'))
            for name in args.configs}
    sets = []
    if 'test' in args.sets:
        test = open_dataset(args.dataset, split='test')
        sets.append(ViewsDataset(test, 1, args.test_seed, include_full=False, random_yaw=True,
                                 memoize=True))
        sets.append(ViewsDataset(test, 0, args.test_seed, include_full=True, random_yaw=True))
    if 'train' in args.sets:
        train = open_dataset(args.dataset, split='train')
        sources = None if args.subset == 1 else np.arange(0, len(train), args.subset)
        sets.append(ViewsDataset(train, args.views, args.seed, include_full=True,
                                 random_yaw=True, memoize=True, sources=sources))
    for ds in sets:
        for name, enc in encs.items():
            feats = encode_dataset(ds, enc, cache_dir=cache)
            print(f'{name} {ds.split}: {tuple(feats.shape)}', flush=True)


if __name__ == '__main__':
    main()
