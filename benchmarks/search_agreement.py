#!/usr/bin/env python3
"""Two-stage bank search (bank/search.py) against the exact search: labels and cost.

usage: benchmarks/search_agreement.py [--bank BANK] [--data DIR] [--split test]
       [--cache DIR] [--random-yaw SEED | --single-view --seed S]
       [--candidates 256 512 1024] [--coarse-dims 128 256] [--replicate R --jitter S]
       [--section complete|views] [--code-bits 4 8]

Encodes the split as `point_gn eval` does (complete objects, --random-yaw, or one
--single-view scan per object; cached with --cache), then classifies it through the
bank's Classifier (transform, head whitening, LDA fusion, temperature) twice: with the
exact search (every entry votes) and with IndexedSearch at each (coarse dims, candidates).
Reports labels differing, accuracies, the largest probability and novelty differences,
the index build time (process CPU) and the thread CPU time of a lone query (median over
--lone queries, each classified alone: Classifier.classify on one raw feature row, torch
on one thread).
--section views indexes a two-section bank's scan section instead of its complete section
(the classifier then mixes both by the gate, as the node does).
--code-bits: the coarse codes' widths to try (default: COARSE_BITS).
--replicate R stands in for a large real bank: R copies of every entry, each copy but the
first with Gaussian noise of std S per coordinate, renormalised (R = 10: 98,430 entries).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
import time

import numpy as np
import torch

from point_gn_ros.bank.builder import encode_dataset
from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.bank.index import CANDIDATES, COARSE_BITS, IndexedSearch
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.bank.vote import CompiledHead
from point_gn_ros.core.views import VIEW_PROTOCOLS
from point_gn_ros.datasets import open_dataset
from point_gn_ros.datasets.views import ViewsDataset
from point_gn_ros.recognizer import make_encoder


def lone_query_ms(clf: Classifier, feats: torch.Tensor, count: int) -> float:
    """Median thread CPU ms of clf.classify on one raw row, over `count` rows."""
    clf.classify(feats[:1])                                   # warm-up
    times = []
    for i in range(min(count, len(feats))):
        t0 = time.thread_time()
        clf.classify(feats[i:i + 1])
        times.append(time.thread_time() - t0)
    return 1e3 * float(np.median(times))


def replicated(bank: FeatureBank, copies: int, jitter: float) -> FeatureBank:
    """The bank with `copies` noisy copies of every vote-space row (the first exact)."""
    if copies <= 1:
        return bank
    gen = torch.Generator().manual_seed(0)
    feats = bank.features.float()
    noisy = [feats] + [feats + jitter * torch.randn(feats.shape, generator=gen)
                       for _ in range(copies - 1)]
    return replace(bank, features=torch.nn.functional.normalize(torch.cat(noisy), dim=1),
                   labels=bank.labels.repeat(copies))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--bank', default=None, help='bank (default: the shipped one)')
    ap.add_argument('--data', default=str(Path(__file__).resolve().parents[2] / 'shared' /
                                          'datasets' / 'modelnet40_1024'))
    ap.add_argument('--split', default='test')
    ap.add_argument('--cache', default=None, help='encoded-feature cache directory')
    ap.add_argument('--random-yaw', type=int, default=None, metavar='SEED')
    ap.add_argument('--single-view', action='store_true')
    ap.add_argument('--seed', type=int, default=0, help='seed of the --single-view scans')
    ap.add_argument('--candidates', type=int, nargs='+', default=[CANDIDATES])
    ap.add_argument('--coarse-dims', type=int, nargs='+', default=[0],
                    help='coarse widths to try; 0 = the default (COARSE_ENERGY rule)')
    ap.add_argument('--replicate', type=int, default=1)
    ap.add_argument('--jitter', type=float, default=0.02)
    ap.add_argument('--lone', type=int, default=200, help='lone queries timed')
    ap.add_argument('--section', choices=('complete', 'views'), default='complete',
                    help="the section searched by the index (a two-section bank's 'views')")
    ap.add_argument('--code-bits', type=int, nargs='+', choices=(4, 8), default=[COARSE_BITS])
    args = ap.parse_args()
    torch.set_num_threads(1)

    bank = FeatureBank.load(args.bank)
    ds = open_dataset(args.data, split=args.split)
    source, what = ds, 'complete objects'
    if args.single_view:
        source = ViewsDataset(ds, 1, args.seed, VIEW_PROTOCOLS['hpr'][0], include_full=False,
                              random_yaw=True)
        what = f'single-view scans (seed {args.seed})'
    elif args.random_yaw is not None:
        source = ViewsDataset(ds, 0, args.random_yaw, include_full=True, random_yaw=True)
        what = f'complete objects, random yaw {args.random_yaw}'
    feats = encode_dataset(source, make_encoder(bank.config), cache_dir=args.cache)
    bank = replicated(bank, args.replicate, args.jitter)
    true = np.asarray(ds.labels)
    exact = Classifier(bank, search='exact')
    if args.section == 'views' and exact.views is None:
        raise SystemExit('--section views needs a two-section bank')
    if args.replicate > 1 and exact.head.has_ridge:
        raise SystemExit('--replicate: the complete section has a kernel ridge term (a '
                         'coefficient per entry), which copies of the entries cannot share')
    p_ex, nov_ex = exact.evaluate(feats)
    lab_ex = p_ex.argmax(1).numpy()
    print(f'{len(feats)} {args.split} {what} against {Path(bank.path).name} '
          f'({len(bank.labels)} x {bank.features.shape[1]}, gamma {bank.gamma:g}); exact '
          f'search: accuracy {100 * (lab_ex == true).mean():.2f} %, lone query '
          f'{lone_query_ms(exact, feats, args.lone):.2f} ms CPU')
    print('| coarse dims | bits | candidates | coarse energy | build s CPU | labels differing | '
          'accuracy | max prob. diff (p99 of queries) | max novelty diff | '
          'lone query ms CPU |\n|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|')
    for dims, bits, m in ((d, b, m) for d in args.coarse_dims for b in args.code_bits
                          for m in args.candidates):
        clf = Classifier(bank, search='exact')
        sec = clf.views if args.section == 'views' else clf
        t0 = time.process_time()      # numpy's BLAS may use more than this thread
        sec.search = IndexedSearch(sec.features, sec.labels, sec.bank.num_classes,
                                   coarse_dims=dims or None, candidates=m,
                                   code_bits=bits)
        build = time.process_time() - t0
        sec.compiled_head = CompiledHead.build(sec.transform, sec.head, sec.bank.num_classes,
                                               sec.search)   # it reads the search
        p, nov = clf.evaluate(feats)
        lab = p.argmax(1).numpy()
        index = sec.search.index
        print(f'| {index.coarse_dims} | {bits} | {m} | {index.coarse_energy:.2f} | {build:.2f} | '
              f'{int((lab != lab_ex).sum())} of {len(lab)} | '
              f'{100 * (lab == true).mean():.2f} % | {float((p - p_ex).abs().max()):.2g} '
              f'({float(np.percentile((p - p_ex).abs().amax(1).numpy(), 99)):.2g}) | '
              f'{float((nov - nov_ex).abs().max()):.2g} | '
              f'{lone_query_ms(clf, feats, args.lone):.2f} |', flush=True)


if __name__ == '__main__':
    main()
