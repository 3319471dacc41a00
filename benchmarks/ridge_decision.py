"""The kernel ridge term's figures on the shipped bank: accuracy, query time, enrollment latency.

With the term (as shipped) and without it (its weight 0, the head's CV temperature without
the term, `meta head.ridge.temperature_without`): ModelNet40 test accuracy on complete
objects and one single-view scan each (features as benchmarks/answer_dump.py caches them),
the lone query's classifier time (median over --queries features, one torch thread), and
the latency of one enrollment of --examples examples of a new class into the whole bank
(`add_examples` with the node's policy: refit in full of what depends on the rows).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
import statistics
import time

import numpy as np
import torch

DATA = Path(__file__).resolve().parents[1] / '..' / 'shared' / 'datasets' / 'modelnet40_1024'


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--cache', type=Path, default=Path('/tmp/pgn_answer_dump_cache'))
    ap.add_argument('--data', type=Path, default=DATA)
    ap.add_argument('--queries', type=int, default=300)
    ap.add_argument('--examples', type=int, default=10)
    ap.add_argument('--enrollments', type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(1)
    from point_gn_ros.bank.builder import encode_dataset
    from point_gn_ros.bank.classifier import Classifier
    from point_gn_ros.bank.enroll import BankFile, add_examples
    from point_gn_ros.bank.refit import RefitPolicy
    from point_gn_ros.bank.store import FeatureBank
    from point_gn_ros.core.views import VIEW_PROTOCOLS
    from point_gn_ros.datasets import open_dataset
    from point_gn_ros.datasets.views import ViewsDataset
    from point_gn_ros.recognizer import make_encoder

    shipped = FeatureBank.load(None)
    ridge = shipped.meta['head']['ridge']
    plain = replace(shipped, head=replace(shipped.head, ridge_coef=None, ridge_weight=0.0,
                                          temperature=float(ridge['temperature_without'])))
    ds = open_dataset(args.data, split='test')
    true = np.asarray(ds.labels)
    enc = make_encoder(shipped.config, 'cpu')
    feats = {'complete': encode_dataset(ds, enc, 64, progress=False, cache_dir=args.cache),
             'single-view': encode_dataset(
                 ViewsDataset(ds, 1, 0, VIEW_PROTOCOLS['hpr'][0], include_full=False,
                              random_yaw=True), enc, 64, progress=False, cache_dir=args.cache)}
    policy = RefitPolicy(lda_prior='typical', lda_debias=2.0, lda_steal_budget=0.001)
    rng = np.random.default_rng(0)
    for name, bank in (('with the ridge term', shipped), ('without it', plain)):
        clf = Classifier(bank)
        acc = {k: 100 * float((clf.classify(torch.as_tensor(f)).labels == true).mean())
               for k, f in feats.items()}
        f = torch.as_tensor(feats['complete'])[:args.queries]
        times = []
        for i in range(len(f)):
            t0 = time.perf_counter()
            clf.classify(f[i:i + 1])
            times.append(time.perf_counter() - t0)
        lat = []
        file = BankFile.of_loaded(bank)
        for e in range(args.enrollments):
            rows = rng.choice(len(true), args.examples, replace=False)
            t0 = time.perf_counter()
            add_examples(file, torch.as_tensor(feats['single-view'])[rows], f'new{e}', 'bench',
                         policy=policy)
            lat.append(time.perf_counter() - t0)
        print(f'{name}: complete {acc["complete"]:.2f} %, single-view {acc["single-view"]:.2f} %;'
              f' lone query {1e3 * statistics.median(times):.2f} ms (median of {len(times)});'
              f' enrollment of {args.examples} examples {statistics.median(lat):.2f} s '
              f'(median of {len(lat)}: {", ".join(f"{x:.2f}" for x in lat)})', flush=True)


if __name__ == '__main__':
    main()
