"""Classifier cost of banks: file size, load time, bytes in memory, a lone query and a batch.

What a bigger (sensor-realistic) bank costs the node per object, without the node: the
classifier's time per query at batch 1 (a lone query reads the whole bank) and at batch 16
(the node's micro-batches), median over repeats, random unit features as queries.

    python scripts/bank_query_time.py point_gn_ros/data/modelnet40_default.npz other.npz
"""

from __future__ import annotations

import argparse
from pathlib import Path
import time

import numpy as np
import torch

from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.bank.store import FeatureBank


def _median_ms(fn, repeats: int) -> float:
    fn()                                    # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('banks', nargs='+')
    p.add_argument('--repeats', type=int, default=30)
    args = p.parse_args()
    print('| bank | entries x dims | file MB | load s | features in memory MB | '
          'lone query ms | per query at batch 16 ms |\n|---|---|---:|---:|---:|---:|---:|')
    for path in args.banks:
        t0 = time.perf_counter()
        bank = FeatureBank.load(path)
        load_s = time.perf_counter() - t0
        clf = Classifier(bank)
        dim = bank.config.feature_dim
        q = torch.from_numpy(np.random.default_rng(0).normal(size=(16, dim)).astype(np.float32))
        one = _median_ms(lambda q=q, clf=clf: clf.classify(q[:1]), args.repeats)
        batch = _median_ms(lambda q=q, clf=clf: clf.classify(q), args.repeats) / 16
        mem = bank.features.element_size() * bank.features.numel() / 1e6
        print(f'| {Path(path).name} | {len(bank)} x {bank.features.shape[1]} | '
              f'{Path(path).stat().st_size / 1e6:.1f} | {load_s:.2f} | {mem:.0f} | {one:.2f} | '
              f'{batch:.2f} |', flush=True)


if __name__ == '__main__':
    main()
