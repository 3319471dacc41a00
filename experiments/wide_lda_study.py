#!/usr/bin/env python3
"""Whether the head's LDA gains from every standardised dim instead of the PCA's (train only).

The default bank's sections project the standardised 1,620-dim encoder features onto their
PCA basis (scan section: 320 dims) before the head; the PCA keeps the directions of most
spread, which need not be those that tell classes apart. This study scores, on the CV folds
the bank builder uses (scan section: every `--every`-th train object's 8 HPR scans, 5 folds
grouped by object; complete section: every object, stratified), the whitened vote on the PCA
dims plus an LDA fitted on:
  pca     the same PCA dims (the builder's head before `--wide-lda`)
  W       the first W PCA dims of the standardised features (--widths)
  all     every standardised dim (bank/model.py Head's wide LDA)
  rank R  every dim, the covariance kept at rank R plus an isotropic rest (storable as a
          (D, R) basis instead of a (D, D) precision; --ranks)
each with its shrinkage and fusion weight chosen on the same held-out scores. Reads the
feature cache of `make default-bank CACHE=DIR` (the default bank's exact features); the test
split is not read.

    python experiments/wide_lda_study.py ../shared/datasets/modelnet40_1024 --cache DIR \
        --section scans --every 9
"""

from __future__ import annotations

import argparse
from dataclasses import replace
import itertools
import json

import numpy as np
import torch

from point_gn_ros.bank import selection as sel
from point_gn_ros.bank.builder import feature_cache_path
from point_gn_ros.bank.discriminant import CovarianceFit
from point_gn_ros.bank.model import FeatureTransform
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.core.views import VIEW_PROTOCOLS
from point_gn_ros.datasets import open_dataset
from point_gn_ros.datasets.views import ViewsDataset

VIEWS = 8


def lda_scores(feats: torch.Tensor, lab: torch.Tensor, parts: list[np.ndarray], width,  # noqa: ANN001
               rank: int | None, alphas: tuple[float, ...]) -> dict[float, torch.Tensor]:
    """Out-of-fold LDA log-probabilities (N, C) per shrinkage, LDA on `width` dims."""
    out = {a: torch.zeros(len(lab), 40) for a in alphas}
    for val in parts:
        train = np.setdiff1d(np.arange(len(lab)), val)
        tf = FeatureTransform.fit(feats[train], 'standardize', width)
        fit = CovarianceFit.fit(tf(feats[train]), lab[train], 40)
        if rank is not None:               # top-`rank` eigenpairs, the rest their mean
            order = torch.argsort(fit.evals, descending=True)
            evals = fit.evals.clone()
            evals[order[rank:]] = fit.evals[order[rank:]].mean()
            fit = replace(fit, evals=evals)
        coords = fit.coords(tf(feats[val]))
        for a in alphas:
            out[a][torch.from_numpy(val)] = torch.log_softmax(fit.lda_logits(coords, a), 1).float()
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('dataset')
    p.add_argument('--cache', required=True, help='feature cache of make default-bank')
    p.add_argument('--section', choices=('scans', 'complete'), default='scans')
    p.add_argument('--every', type=int, default=9, help='every N-th object (builder: 9)')
    p.add_argument('--widths', type=int, nargs='*', default=[512, 800])
    p.add_argument('--ranks', type=int, nargs='*', default=[128, 256, 512])
    p.add_argument('--alphas', type=float, nargs='+', default=[0.001, 0.003, 0.01, 0.03])
    args = p.parse_args()
    torch.set_num_threads(2)
    train = open_dataset(args.dataset, split='train')
    built = ViewsDataset(train, VIEWS, 0, VIEW_PROTOCOLS['hpr'][0], include_full=True,
                         random_yaw=True)
    cfg = EncoderConfig(yaw_align=True, upsample='midpoint')
    raw = np.load(feature_cache_path(built, cfg, args.cache), mmap_mode='r')
    rows = np.arange(len(raw))
    src, scan = rows // (VIEWS + 1), rows % (VIEWS + 1) != 0
    pick = (scan if args.section == 'scans' else ~scan) & (src % args.every == 0)
    feats = torch.from_numpy(np.ascontiguousarray(raw[pick]))
    labels = np.asarray(train.labels)[src[pick]].astype(np.int64)
    lab = torch.from_numpy(labels)
    groups = src[pick] if args.section == 'scans' else None
    parts = sel.stratified_folds(labels, 5, 0, groups)
    dims, gamma = (320, 80.0) if args.section == 'scans' else (512, 40.0)
    fs = sel._fold_scores(feats, lab, 40, parts, 'standardize', dims, (gamma,), (0.1,),
                          tuple(args.alphas), (True,))
    vote = fs.votes[0.1][0]
    weights = (0.0, 0.05, 0.1, 0.2, 0.3, 0.5)

    def best(lda: dict) -> dict:       # noqa: ANN001
        acc, a, w = max((float(((vote + w * lda[a]).argmax(1) == lab).double().mean()), a, w)
                        for a, w in itertools.product(lda, weights))
        return {'cv_accuracy': round(100 * acc, 2), 'lda_alpha': a, 'weight': w}

    print(json.dumps({'section': args.section, 'rows': len(labels), 'vote_dims': dims,
                      'gamma': gamma}))
    print(json.dumps({'lda': 'pca', **best({a: fs.lda[a, False] for a in args.alphas})}),
          flush=True)
    for width in [*args.widths, None]:
        row = best(lda_scores(feats, lab, parts, width, None, tuple(args.alphas)))
        print(json.dumps({'lda': width or 'all', **row}), flush=True)
    for rank in args.ranks:
        row = best(lda_scores(feats, lab, parts, None, rank, tuple(args.alphas)))
        print(json.dumps({'lda': f'all, rank {rank}', **row}), flush=True)


if __name__ == '__main__':
    main()
