#!/usr/bin/env python3
"""The size region of the unknown rule (bank/taught.py): its radius by CV, no test object read.

A query answered with class c is unknown when its size lies outside c's size region:
distance (-2 plausibility) > region_c. region_c is REGION_CHI2, widened for taught classes to
the REGION_QUANTILE of their own examples' leave-one-out distances where those need more.
Candidates: the 90 / 95 / 99 / 99.9 % chi-square quantiles (6 degrees of freedom), with and
without the widening. Measured on:

  tabletop   restaurant Kinect-sim tree (metres), --folds folds: a class left out, the other
             19 taught into the shipped bank (5 views each, `add_examples` as `bank add`),
             their other views (taught) and every view of the left-out class (unseen)
             classified: share rejected by the region (the answered class's) of each
  mn40       ModelNet40 TRAIN, one single-view scan of 25 objects a class at a plausible
             real size (size prior x 0.8-1.25; size_knob_study.sized_train_scans):
             (a) built classes, shipped bank: share of the scans outside their answer's region;
             (b) taught: 10 classes, 5 scans each taught, --folds folds: share of those
                 classes' other scans outside their answer's region

usage: experiments/open_set_study.py [--cache DIR] [--folds 6]
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from point_gn_ros.bank.builder import encode_dataset
from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.bank.enroll import BankFile, add_examples
from point_gn_ros.bank.refit import RefitPolicy
from point_gn_ros.bank.taught import KEY, REGION_CHI2, REGION_QUANTILE, loo_distances
from point_gn_ros.core.size import size_descriptors
from point_gn_ros.datasets import open_dataset
from point_gn_ros.recognizer import make_encoder
from size_knob_study import sized_train_scans  # experiments/, beside this script

SHARED = Path(__file__).resolve().parents[2] / 'shared' / 'datasets'
RADII = {'95 %': REGION_CHI2, '99 %': 16.81, '99.9 %': 22.46, '99.99 %': 27.86, '2 x 95 %': 25.18,
         '3 x 95 %': 37.77}
WIDENING = ('none', 'class', 'pooled')
POLICY = RefitPolicy()


def outside(clf: Classifier, feats: torch.Tensor, sizes: np.ndarray, radius: float,
            widen: str) -> tuple[np.ndarray, np.ndarray]:
    """(M,) bool: the answer's size outside its region at this radius and widening; (M,) answers.

    widen: 'none'; 'class' (a taught class's region: at least the REGION_QUANTILE of its own
    examples' leave-one-out distances); 'pooled' (of every taught class's, pooled).
    """
    layer = clf.taught
    region = np.full(len(layer.region), radius)
    loo = {clf.bank.class_names.index(name): loo_distances(
        np.asarray(rec.get('sizes', []), dtype=np.float64))
        for name, rec in clf.bank.meta.get(KEY, {}).items()}
    pooled = [v for d in loo.values() for v in d]
    for i, d in loo.items():
        if widen == 'class' and d:
            region[i] = max(radius, float(np.quantile(d, REGION_QUANTILE)))
        elif widen == 'pooled' and pooled:
            region[i] = max(radius, float(np.quantile(pooled, REGION_QUANTILE)))
    clf._taught = replace(layer, region=region)
    res = clf.classify(feats, top_k=1, sizes=sizes)
    clf._taught = layer
    return np.asarray(res.size_misfit > 1.0), res.topk_ids[:, 0]


def teach(base: BankFile, feats: torch.Tensor, sizes: np.ndarray, y: np.ndarray,
          names: list[str], classes: list[int], support: np.ndarray) -> BankFile:
    bf = base
    for c in classes:
        idx = support[y[support] == c]
        bf = add_examples(bf, feats[idx], names[c], source='open_set_study', policy=POLICY,
                          sizes=sizes[idx]).file
    return bf


def table(title: str, rows: dict) -> None:
    print(f'\n## {title}')
    print('| radius | widening | ' + ' | '.join(rows[next(iter(rows))]) + ' |')
    print('|---|---|' + '---|' * len(rows[next(iter(rows))]))
    for (r, w), v in rows.items():
        print(f'| {r} | {w} | '
              + ' | '.join(f'{100 * np.mean(x):.1f} %' for x in v.values()) + ' |')


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--cache', default='cache')
    ap.add_argument('--folds', type=int, default=6)
    ap.add_argument('--part', choices=('both', 'tabletop', 'mn40'), default='both')
    args = ap.parse_args()
    torch.set_num_threads(2)
    cache = Path(args.cache)
    base = BankFile.load(None)
    enc = make_encoder(base.bank.config, 'cpu')
    cells = [(r, w) for r in RADII for w in WIDENING]

    if args.part != 'mn40':
        tabletop(base, enc, cache, cells, args.folds)
    if args.part != 'tabletop':
        mn40(base, enc, cache, cells, args.folds)


def tabletop(base: BankFile, enc, cache: Path, cells: list, folds: int) -> None:
    """The tabletop half of the module docstring."""
    ds = open_dataset(SHARED / 'restaurant_kinectsim' / 'all', split='train')
    feats = torch.as_tensor(encode_dataset(ds, enc, 64, progress=False, cache_dir=cache))
    sizes = size_descriptors([ds[i][0] for i in range(len(ds))])
    y, names = np.asarray(ds.labels), list(ds.class_names)
    tab = {cell: {'unseen rejected': [], 'taught rejected': [], 'of right answers': []}
           for cell in cells}
    held_out = np.random.default_rng(0).permutation(len(names))
    for fold in range(folds):
        rng = np.random.default_rng(fold)
        held = int(held_out[fold % len(names)])
        classes = [c for c in range(len(names)) if c != held]
        support = np.concatenate([rng.permutation(np.flatnonzero(y == c))[:5] for c in classes])
        clf = Classifier(teach(base, feats, sizes, y, names, classes, support).bank)
        known = np.setdiff1d(np.flatnonzero(y != held), support)
        unseen = np.flatnonzero(y == held)
        for r, w in cells:
            tab[r, w]['unseen rejected'].append(outside(clf, feats[unseen], sizes[unseen],
                                                        RADII[r], w)[0].mean())
            out, ans = outside(clf, feats[known], sizes[known], RADII[r], w)
            right = ans == np.array([clf.bank.class_names.index(names[c]) for c in y[known]])
            tab[r, w]['taught rejected'].append(out.mean())
            tab[r, w]['of right answers'].append(out[right].mean())
        print(f'fold {fold}: {names[held]} left out', flush=True)
    table(f'tabletop, one class left out, 19 taught (5 views), {folds} folds', tab)


def mn40(base: BankFile, enc, cache: Path, cells: list, folds: int) -> None:
    """The ModelNet40 half of the module docstring."""
    mfeats, my, msizes, mnames = sized_train_scans(cache, enc)
    shipped = Classifier(base.bank)
    mres = {cell: {'built rejected': [], 'taught rejected': [], 'of right answers': []}
            for cell in cells}
    for r, w in cells:
        mres[r, w]['built rejected'].append(outside(shipped, mfeats, msizes, RADII[r],
                                                    w)[0].mean())
    for fold in range(folds):
        r_ = np.random.default_rng(100 + fold)
        classes = [int(c) for c in r_.choice(40, 10, replace=False)]
        support = np.concatenate([r_.permutation(np.flatnonzero(my == c))[:5] for c in classes])
        clf = Classifier(teach(base, mfeats, msizes, my, mnames, classes, support).bank)
        q = np.setdiff1d(np.flatnonzero(np.isin(my, classes)), support)
        for r, w in cells:
            out, ans = outside(clf, mfeats[q], msizes[q], RADII[r], w)
            mres[r, w]['taught rejected'].append(out.mean())
            mres[r, w]['of right answers'].append(out[ans == my[q]].mean())
    table("ModelNet40 train scans at plausible sizes: outside their answer's region", mres)


if __name__ == '__main__':
    main()
