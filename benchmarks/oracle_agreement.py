#!/usr/bin/env python3
"""Fast encoder vs the naive oracle on a whole dataset split: features and labels.

usage: benchmarks/oracle_agreement.py [--bank BANK] [--data DIR] [--split test] [--limit N]
       [--torch-threads T] [--save-oracle FILE | --oracle-features FILE]

Encodes every cloud with both encoders (configured from the bank), reports the largest
per-cloud relative feature difference and how many labels differ. The oracle takes minutes
(hours on a busy machine): --save-oracle keeps its features (.npy) so that a later fast
encoder can be checked against them with --oracle-features in seconds.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import time

import numpy as np
import torch

from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.datasets import open_dataset
from point_gn_ros.recognizer import encode_clouds, make_encoder


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--bank', default=None, help='bank (default: the shipped one)')
    ap.add_argument('--data', default=str(Path(__file__).resolve().parents[2] / 'shared' /
                                          'datasets' / 'modelnet40_1024'))
    ap.add_argument('--split', default='test')
    ap.add_argument('--limit', type=int, default=0, help='first N clouds only (0 = all)')
    ap.add_argument('--torch-threads', type=int, default=1,
                    help='torch threads for the oracle (default 1: on a shared machine more '
                         'threads spin in OpenMP and run slower)')
    ap.add_argument('--save-oracle', default=None, help='write the oracle features (.npy)')
    ap.add_argument('--oracle-features', default=None,
                    help='oracle features saved by --save-oracle for the same bank, data, '
                         'split and limit (skips the oracle)')
    args = ap.parse_args()

    bank = FeatureBank.load(args.bank)
    ds = open_dataset(args.data, split=args.split)
    n = len(ds) if args.limit <= 0 else min(args.limit, len(ds))
    clouds = [ds[i][0] for i in range(n)]
    torch.set_num_threads(args.torch_threads)
    times, feats = {}, {}
    for name, naive in (('fast', False), ('oracle', True)):
        if naive and args.oracle_features:
            feats[name] = torch.from_numpy(np.load(args.oracle_features, allow_pickle=False))
            if feats[name].shape != feats['fast'].shape:
                raise SystemExit(f'{args.oracle_features}: shape {tuple(feats[name].shape)}, '
                                 f'expected {tuple(feats["fast"].shape)}')
            times[name] = float('nan')
            continue
        enc = make_encoder(bank.config, naive=naive)
        t0 = time.perf_counter()
        feats[name] = encode_clouds(clouds, enc, batch_size=64,
                                    progress=f'{name} encoder')
        times[name] = time.perf_counter() - t0
    if args.save_oracle and not args.oracle_features:
        tmp = Path(args.save_oracle).with_suffix('.tmp.npy')
        np.save(tmp, feats['oracle'].numpy())
        os.replace(tmp, args.save_oracle)  # atomic
    rel = ((feats['fast'] - feats['oracle']).abs().amax(1) /
           feats['oracle'].abs().amax(1)).numpy()
    clf = Classifier(bank)
    fast_lab = clf.classify(feats['fast'], top_k=1).labels
    oracle_lab = clf.classify(feats['oracle'], top_k=1).labels
    true = np.asarray(ds.labels[:n])
    print(f'{n} clouds of {args.split} against {bank.path.name}')
    print(f'max relative feature difference {rel.max():.2e} (median {np.median(rel):.2e}); '
          f'limit 1e-4')
    print(f'labels differing: {int((fast_lab != oracle_lab).sum())} of {n}; accuracy fast '
          f'{100 * (fast_lab == true).mean():.2f} %, '
          f'oracle {100 * (oracle_lab == true).mean():.2f} %')
    if args.oracle_features:
        print(f'time: fast {times["fast"]:.1f} s; oracle features from {args.oracle_features}')
    else:
        print(f'time: fast {times["fast"]:.1f} s, oracle {times["oracle"]:.1f} s '
              f'({times["oracle"] / times["fast"]:.0f}x)')


if __name__ == '__main__':
    main()
