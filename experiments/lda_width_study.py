#!/usr/bin/env python3
"""LDA at another PCA width than the kernel vote, by CV (issue 8 study; train split only).

The shipped default's complete section votes on whitened PCA-512 features and fits its LDA at
the same width. Is an LDA on wider features (its own standardisation, PCA width W or all
dims) worth more? Yaw-aligned complete train objects (bank_augment_study.py's cached
features; run that with --setting yaw first), 5 stratified folds, vote whitening 0.1, the
best of gamma {20, 40, 80} x LDA shrinkage {0.01, 0.02} x weight {0.1, 0.2, 0.3, 0.5} for
every pair; differences against the first pair, +- paired standard error.

    python experiments/lda_width_study.py ../shared/datasets/modelnet40_1024 --cache DIR
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import json
from pathlib import Path

import numpy as np
import torch

from point_gn_ros.bank.discriminant import CovarianceFit
from point_gn_ros.bank.vote import log_vote_shares
from point_gn_ros.bank.selection import stratified_folds
from point_gn_ros.bank.model import FeatureTransform
from point_gn_ros.datasets import open_dataset

GAMMAS = (20.0, 40.0, 80.0)
LDA_ALPHAS = (0.01, 0.02)
WEIGHTS = (0.1, 0.2, 0.3, 0.5)


def cv(x: torch.Tensor, labels: np.ndarray, vote_dims: int, lda_dims: int | None
       ) -> tuple[float, tuple, np.ndarray]:
    """-> pooled CV accuracy of the best grid point, its (gamma, lda alpha, w), correctness."""
    lab, n = torch.from_numpy(labels), len(labels)
    votes = {g: torch.zeros(n, 40) for g in GAMMAS}
    ldas = {a: torch.zeros(n, 40) for a in LDA_ALPHAS}
    for val in stratified_folds(labels, 5, 0):
        tr, vi = np.setdiff1d(np.arange(n), val), torch.from_numpy(val)
        tf = FeatureTransform.fit(x[tr], 'standardize', vote_dims)
        fit = CovarianceFit.fit(tf(x[tr]), lab[tr], 40)
        u_b = torch.nn.functional.normalize(fit.whitened(fit.coords(tf(x[tr])), 0.1), dim=1)
        u_v = torch.nn.functional.normalize(fit.whitened(fit.coords(tf(x[val])), 0.1), dim=1)
        for g, lv in zip(GAMMAS, [log_vote_shares(u_v @ u_b.T, lab[tr], 40, g_) for g_ in GAMMAS],
                         strict=True):
            votes[g][vi] = lv
        tf2 = FeatureTransform.fit(x[tr], 'standardize', lda_dims)
        fit2 = CovarianceFit.fit(tf2(x[tr]), lab[tr], 40)
        for a in LDA_ALPHAS:
            logits = fit2.lda_logits(fit2.coords(tf2(x[val])), a)
            ldas[a][vi] = torch.log_softmax(logits, 1).float()
    best: tuple = (-1.0, None, None)
    for g, a, w in itertools.product(GAMMAS, LDA_ALPHAS, WEIGHTS):
        ok = ((votes[g] + w * ldas[a]).argmax(1) == lab).numpy().astype(float)
        if ok.mean() > best[0] + 1e-12:
            best = (float(ok.mean()), (g, a, w), ok)
    return best


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('dataset')
    p.add_argument('--cache', required=True)
    p.add_argument('--pairs', nargs='+', default=['512:512', '512:0', '512:1024'],
                   help='VOTE:LDA PCA widths (0: all dims); the first is the reference')
    args = p.parse_args()
    torch.set_num_threads(2)
    train = open_dataset(args.dataset, split='train')
    labels = np.asarray(train.labels, dtype=np.int64)
    key = hashlib.sha1(repr(('yaw', len(train))).encode()).hexdigest()[:16]
    x = torch.from_numpy(np.load(Path(args.cache) / f'augstudy_{key}.npy')).float()
    ref = None
    for pair in args.pairs:
        v, lw = (int(t) for t in pair.split(':'))
        acc, knobs, ok = cv(x, labels, v, lw or None)
        ref = ok if ref is None else ref
        d = ok - ref
        print(json.dumps({'vote_dims': v, 'lda_dims': lw or 'all', 'cv': acc, 'knobs': knobs,
                          'diff': float(d.mean()),
                          'se': float(d.std(ddof=1) / np.sqrt(len(d)))}), flush=True)


if __name__ == '__main__':
    main()
