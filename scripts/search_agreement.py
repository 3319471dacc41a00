#!/usr/bin/env python3
"""Two-stage bank search (bank/search.py) against the full float32 search: labels.

usage: scripts/search_agreement.py [--bank BANK] [--data DIR] [--split test]
       [--cache DIR] [--candidates 128 256 512] [--coarse-dims 64 128]
       [--replicate R --jitter S]

Encodes the split with the bank's encoder configuration (cached with --cache), then
counts the queries whose label differs between BankIndex.scores and the classifier's
full search (bank.classifier.class_scores), and the largest vote-share difference.
--replicate R stands in for a large real bank: R copies of every entry, each copy but the
first with Gaussian noise of std S per coordinate, renormalised (R = 10: 98,430 entries).
"""

from __future__ import annotations

import argparse
from pathlib import Path
import time

import numpy as np
import torch

from point_gn_ros.bank.builder import encode_dataset
from point_gn_ros.bank.classifier import class_scores
from point_gn_ros.bank.search import BankIndex
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.datasets import open_dataset
from point_gn_ros.recognizer import make_encoder


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--bank', default=None, help='bank (default: the shipped one)')
    ap.add_argument('--data', default=str(Path(__file__).resolve().parents[2] / 'shared' /
                                          'datasets' / 'modelnet40_1024'))
    ap.add_argument('--split', default='test')
    ap.add_argument('--cache', default=None, help='encoded-feature cache directory')
    ap.add_argument('--candidates', type=int, nargs='+', default=[128, 256, 512])
    ap.add_argument('--coarse-dims', type=int, nargs='+', default=[64, 128])
    ap.add_argument('--replicate', type=int, default=1)
    ap.add_argument('--jitter', type=float, default=0.02)
    args = ap.parse_args()

    bank = FeatureBank.load(args.bank)
    ds = open_dataset(args.data, split=args.split)
    feats = encode_dataset(ds, make_encoder(bank.config), cache_dir=args.cache)
    query = bank.transform(feats)
    bank_feats, bank_labels = bank.features.float(), bank.labels
    if args.replicate > 1:
        gen = torch.Generator().manual_seed(0)
        noisy = [bank_feats] + [bank_feats + args.jitter * torch.randn(
            bank_feats.shape, generator=gen) for _ in range(args.replicate - 1)]
        bank_feats = torch.nn.functional.normalize(torch.cat(noisy), dim=1)
        bank_labels = bank_labels.repeat(args.replicate)
    full = class_scores(query, bank_feats, bank_labels, bank.num_classes, bank.gamma).numpy()
    true = np.asarray(ds.labels)
    q = query.numpy()
    print(f'{len(q)} {args.split} queries against {bank.path.name} ({len(bank_labels)} x '
          f'{bank_feats.shape[1]}, gamma {bank.gamma:g}); full search accuracy '
          f'{100 * (full.argmax(1) == true).mean():.2f} %')
    for dims in args.coarse_dims:
        for m in args.candidates:
            index = BankIndex(bank_feats.numpy(), bank_labels.numpy(), bank.num_classes,
                              coarse_dims=dims, candidates=m)
            t0 = time.thread_time()
            got = index.scores(q, bank.gamma)
            dt = (time.thread_time() - t0) / len(q)
            differ = int((got.argmax(1) != full.argmax(1)).sum())
            print(f'coarse {index.coarse_dims} dims, {m} candidates: labels differing '
                  f'{differ} of {len(q)}, max vote-share diff {np.abs(got - full).max():.2e}, '
                  f'accuracy {100 * (got.argmax(1) == true).mean():.2f} %, '
                  f'{dt * 1e3:.3f} ms CPU/query')


if __name__ == '__main__':
    main()
