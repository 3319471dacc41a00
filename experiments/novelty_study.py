#!/usr/bin/env python3
"""Which score tells unseen classes apart? A pseudo open set on the TRAIN split only.

The 30 known classes of the open-set benchmark (choose_known('30', names, 0)) are split
at random into 20 pseudo-known and 10 pseudo-unseen; a head with the aligned study's
CV-chosen knobs is fitted on 4/5 of the pseudo-known objects and the held-out fifth
(known) and every pseudo-unseen object are scored. AUROC (unseen = positive) per
candidate measure, over 3 seeded repetitions. No test object is read.

usage: experiments/novelty_study.py [--data ../shared/datasets/modelnet40_1024] [--cache DIR]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from point_gn_ros.bank.builder import encode_dataset
from point_gn_ros.bank.discriminant import CovarianceFit, fit_head
from point_gn_ros.bank.selection import stratified_folds
from point_gn_ros.bank.model import FeatureTransform
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.datasets import open_dataset
from point_gn_ros.evaluation.openset import auroc, choose_known
from point_gn_ros.recognizer import make_encoder
from point_gn_ros.bank.vote import ExactSearch, reference_head

# The aligned head chosen by 5-fold CV on the full train split (benchmarks/log/2026-11-29.md).
GAMMA, ALPHA, LDA_ALPHA, WEIGHT, TEMPERATURE = 160.0, 0.2, 0.01, 0.3, 7.99


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--data', default=str(Path(__file__).resolve().parents[2] / 'shared' /
                                          'datasets' / 'modelnet40_1024'))
    ap.add_argument('--cache', default='cache')
    args = ap.parse_args()
    train = open_dataset(args.data, split='train')
    feats = encode_dataset(train, make_encoder(EncoderConfig()), progress=False,
                           cache_dir=Path(args.cache))
    y = np.asarray(train.labels)
    known30 = choose_known('30', list(train.class_names), 0)
    rng = np.random.default_rng(1)
    res: dict[str, list[float]] = {'1 - best cosine, whitened (novelty)': [],
                                   '1 - best cosine, unwhitened': [],
                                   '1 - top-1 calibrated probability': [],
                                   'min Mahalanobis distance to class means': []}
    for rep in range(3):
        perm = rng.permutation(known30)
        pk, pu = np.sort(perm[:20]), np.sort(perm[20:])
        idx = np.flatnonzero(np.isin(y, pk))
        val = idx[stratified_folds(y[idx], 5, rep)[0]]
        trn = np.setdiff1d(idx, val)
        unseen = np.flatnonzero(np.isin(y, pu))
        lab = torch.from_numpy(np.searchsorted(pk, y[trn]))
        tf = FeatureTransform.fit(feats[trn], 'standardize')
        z = tf(feats[trn])
        head = fit_head(z, lab, 20, GAMMA, ALPHA, LDA_ALPHA, WEIGHT, TEMPERATURE)
        q = np.concatenate([val, unseen])
        is_unseen = np.r_[np.zeros(len(val)), np.ones(len(unseen))].astype(bool)
        zq = tf(feats[q])
        prob, novelty = reference_head(head, zq, ExactSearch(head.vote_space(z), lab, 20))
        fit = CovarianceFit.fit(z, lab, 20)
        u = fit.whitened(fit.coords(zq), LDA_ALPHA).double()
        means = fit.whitened(fit.coords(fit.means.float()), LDA_ALPHA).double()
        for name, v in zip(res, (novelty, 1 - (zq @ z.T).max(1).values,
                                 1 - prob.max(1).values, torch.cdist(u, means).min(1).values),
                           strict=True):
            v = v.numpy()
            res[name].append(auroc(v[is_unseen], v[~is_unseen]))
    print('| measure | AUROC per repetition | mean |\n|---|---|---:|')
    for name, vals in res.items():
        print(f'| {name} | {", ".join(f"{v:.3f}" for v in vals)} | {np.mean(vals):.3f} |')


if __name__ == '__main__':
    main()
