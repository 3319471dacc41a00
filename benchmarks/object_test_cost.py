"""What the object test of taught classes (bank/model.py) costs a query, lone and batched.

The shipped bank with one class taught from 5 train scans, classified with and without the
test (`Classifier(object_test=...)`), one torch thread, twice each in turn (a noisy shared box).
Queries are train rows of the bank build's feature cache (`make default-bank CACHE=DIR`).

Run: python benchmarks/object_test_cost.py --cache DIR
"""

from __future__ import annotations

import argparse
from pathlib import Path
import sys
import time

import numpy as np
import torch

from point_gn_ros.bank.classifier import Classifier, _object_shift
from point_gn_ros.bank.enroll import BankFile, add_examples
from point_gn_ros.bank.refit import RefitPolicy


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--cache', required=True)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    bf = BankFile.load(None)
    cache = sorted(Path(args.cache).glob('feats_*.npy'), key=lambda f: -f.stat().st_size)[0]
    raw = torch.from_numpy(np.load(cache, mmap_mode='r')[:2000:9].copy())
    taught = add_examples(bf, raw[1:6], 'my_thing', policy=RefitPolicy(lda_prior='typical')).bank
    q = raw[50:250]
    for name, clf in 2 * (('without', Classifier(taught, object_test=False)),
                          ('with', Classifier(taught))):
        for x in q[:20]:
            clf.classify(x[None])
        t = time.perf_counter()
        for x in q:
            clf.classify(x[None])
        lone = (time.perf_counter() - t) / len(q) * 1e3
        t = time.perf_counter()
        clf.classify(q)
        batch = (time.perf_counter() - t) / len(q) * 1e3
        print(f'{name} the test: lone {lone:.3f} ms a query, batch of {len(q)} {batch:.3f} ms a '
              f'query')
    t = time.perf_counter()
    _object_shift(taught)
    print(f'building the shift of a bank version: {1e3 * (time.perf_counter() - t):.1f} ms')
    return 0


if __name__ == '__main__':
    sys.exit(main())
