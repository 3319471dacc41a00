"""Classifier cost of banks: file size, load time, bytes in memory, a lone query and a batch.

What a bigger (sensor-realistic) bank costs the node per object, without the node: for each
bank search (exact: every entry; indexed: bank/index.py's two-stage search, built when the
Classifier is made) the build time (process CPU), the classifier's time per query at batch 1
(a lone query: the exact search reads the whole bank) and at batch 16 (the node's
micro-batches), median thread CPU time over repeats with one torch thread (so a loaded
machine's waiting is not counted), random features as queries.

    python benchmarks/bank_query_time.py point_gn_ros/data/modelnet40_default.npz other.npz
    python benchmarks/bank_query_time.py --replicate 10 point_gn_ros/data/modelnet40_default.npz
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
import time

import numpy as np
import torch

from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.bank.store import FeatureBank


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


def _median_ms(fn, repeats: int) -> float:
    """Median thread CPU time of fn (on a loaded machine, waiting is not counted)."""
    fn()                                    # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.thread_time()
        fn()
        times.append(time.thread_time() - t0)
    return 1e3 * float(np.median(times))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('banks', nargs='+')
    p.add_argument('--repeats', type=int, default=30)
    p.add_argument('--replicate', type=int, default=1,
                   help='R noisy copies of every entry, each but the first with Gaussian noise '
                        'of std --jitter, renormalised (a stand-in for a large real bank)')
    p.add_argument('--jitter', type=float, default=0.02)
    p.add_argument('--search', nargs='+', default=['exact', 'indexed'],
                   choices=('auto', 'exact', 'indexed'))
    args = p.parse_args()
    torch.set_num_threads(1)
    print('| bank | entries x dims | file MB | load s | features in memory MB | search | '
          'build s CPU | lone query CPU ms | per query at batch 16 CPU ms |\n'
          '|---|---|---:|---:|---:|---|---:|---:|---:|')
    for path in args.banks:
        t0 = time.perf_counter()
        bank = replicated(FeatureBank.load(path), args.replicate, args.jitter)
        load_s = time.perf_counter() - t0
        dim = bank.config.feature_dim
        q = torch.from_numpy(np.random.default_rng(0).normal(size=(16, dim)).astype(np.float32))
        mem = bank.features.element_size() * bank.features.numel() / 1e6
        for search in args.search:
            t0 = time.process_time()         # numpy's BLAS may use more than this thread
            clf = Classifier(bank, search=search)
            build = time.process_time() - t0
            one = _median_ms(lambda q=q, clf=clf: clf.classify(q[:1]), args.repeats)
            batch = _median_ms(lambda q=q, clf=clf: clf.classify(q), args.repeats) / 16
            print(f'| {Path(path).name} | {len(bank.labels)} x {bank.features.shape[1]} | '
                  f'{Path(path).stat().st_size / 1e6:.1f} | {load_s:.2f} | {mem:.0f} | '
                  f'{clf.search_kind} | {build:.2f} | {one:.2f} | {batch:.2f} |', flush=True)


if __name__ == '__main__':
    main()
