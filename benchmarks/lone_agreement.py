#!/usr/bin/env python3
"""The compiled head (bank/vote.py), lone and in batches, against the torch reference: labels.

usage: benchmarks/lone_agreement.py [--bank BANK] [--data DIR] [--split test] [--cache DIR]

Encodes the split as `point_gn eval` does, complete objects at random yaw (seed 0) and one
single-view scan of each object (seed 0), then classifies every row three times through the
bank's Classifier, every section searched exactly: in one batch by the torch reference head
(`compiled=False`), alone (the compiled lone path), and in one batch as the node does (torch
embedding, then the compiled finish). Reports the labels that differ from the torch head's, the
accuracies and the largest probability, novelty and gate differences. An agreement check of
implementations of one function, not an accuracy figure.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from point_gn_ros.bank.builder import encode_dataset
from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.core.views import VIEW_PROTOCOLS
from point_gn_ros.datasets import open_dataset
from point_gn_ros.datasets.views import ViewsDataset
from point_gn_ros.recognizer import make_encoder


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--bank', default=None, help='bank (default: the shipped one)')
    ap.add_argument('--data', default=str(Path(__file__).resolve().parents[2] / 'shared' /
                                          'datasets' / 'modelnet40_1024'))
    ap.add_argument('--split', default='test')
    ap.add_argument('--cache', default=None, help='encoded-feature cache directory')
    args = ap.parse_args()
    torch.set_num_threads(1)            # as the node runs its classifier

    bank = FeatureBank.load(args.bank)
    clf = Classifier(bank, search='exact')
    ref = Classifier(bank, search='exact', compiled=False)
    if not clf.lone:
        raise SystemExit('this bank has no compiled lone-query path (bank/vote.py)')
    ds = open_dataset(args.data, split=args.split)
    true = np.asarray(ds.labels)
    sources = {'complete objects, random yaw 0':
               ViewsDataset(ds, 0, 0, include_full=True, random_yaw=True),
               'single-view scans, seed 0':
               ViewsDataset(ds, 1, 0, VIEW_PROTOCOLS['hpr'][0], include_full=False,
                            random_yaw=True)}
    print('| queries | labels differing: lone / batch | accuracy torch / lone / batch | '
          'max prob. diff: lone / batch | max novelty diff | max gate diff |\n'
          '|---|---:|---:|---:|---:|---:|')
    for what, source in sources.items():
        feats = encode_dataset(source, make_encoder(bank.config), cache_dir=args.cache)
        with torch.no_grad():
            prob, nov, gate = ref._evaluate(feats)
            batch_prob = clf._evaluate(feats)[0]
            lone = [clf._evaluate(feats[i:i + 1]) for i in range(len(feats))]
        lone_prob = torch.cat([o[0] for o in lone])
        lone_nov = torch.cat([o[1] for o in lone])
        gate_diff = '-' if gate is None else \
            f'{float((torch.cat([o[2] for o in lone]) - gate).abs().max()):.2g}'
        lab, lone_lab = prob.argmax(1).numpy(), lone_prob.argmax(1).numpy()
        batch_lab = batch_prob.argmax(1).numpy()
        print(f'| {len(feats)} {args.split} {what} | {int((lab != lone_lab).sum())} / '
              f'{int((lab != batch_lab).sum())} | {100 * (lab == true).mean():.2f} / '
              f'{100 * (lone_lab == true).mean():.2f} / '
              f'{100 * (batch_lab == true).mean():.2f} % | '
              f'{float((lone_prob - prob).abs().max()):.2g} / '
              f'{float((batch_prob - prob).abs().max()):.2g} | '
              f'{float((lone_nov - nov).abs().max()):.2g} | {gate_diff} |', flush=True)


if __name__ == '__main__':
    main()
