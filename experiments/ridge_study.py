#!/usr/bin/env python3
"""Kernel ridge vs the head on the shipped default's complete objects, by CV (issue 8 study).

Yaw-aligned complete train objects as the default bank encodes them (its build's feature
cache: `make default-bank CACHE=DIR` first), 5 stratified folds (seed 0), standardise + PCA
512 + whitening 0.1 as the default's complete section. Prints the CV accuracy of the vote, the
LDA, the head (vote + w x LDA), a linear (primal) ridge on the whitened rows and kernel ridge
regression over a grid, and (--quantised) KRR fitted on float rows but queried against int4
rows. Train split only.

    python experiments/ridge_study.py --cache DIR [--gammas 0.5 1 3 10] [--quantised]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from point_gn_ros.bank.discriminant import fit_ridge, ridge_cv_scores
from point_gn_ros.bank.store import stored_rows
from point_gn_ros.bank.vote import log_vote_shares, ridge_scores
from point_gn_ros.bank.builder import encode_dataset
from point_gn_ros.bank.discriminant import CovarianceFit
from point_gn_ros.bank.selection import stratified_folds
from point_gn_ros.bank.model import FeatureTransform
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.core.views import VIEW_PROTOCOLS
from point_gn_ros.datasets import open_dataset
from point_gn_ros.datasets.views import ViewsDataset
from point_gn_ros.recognizer import make_encoder

C = 40


def complete_rows(data: str, cache: str) -> tuple[torch.Tensor, np.ndarray]:
    """The default bank's complete-object features (9,843, 1,620) and labels, from its cache."""
    ds = open_dataset(data, split='train')
    cfgs = VIEW_PROTOCOLS['hpr']
    vds = ViewsDataset(ds, 8, 0, cfgs if len(cfgs) > 1 else cfgs[0], include_full=True,
                       random_yaw=True)
    cfg = EncoderConfig(yaw_align=True, upsample='midpoint')
    feats = encode_dataset(vds, make_encoder(cfg, 'cpu'), cache_dir=cache, progress=True)
    full = np.asarray(vds.view_index) < 0
    return feats[torch.from_numpy(full)].float(), np.asarray(vds.labels)[full].astype(np.int64)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--data', default='../shared/datasets/modelnet40_1024')
    p.add_argument('--cache', required=True)
    p.add_argument('--gammas', type=float, nargs='+', default=[1.0, 3.0, 10.0])
    p.add_argument('--lambdas', type=float, nargs='+', default=[0.001, 0.01, 0.1])
    p.add_argument('--quantised', action='store_true')
    args = p.parse_args()
    torch.set_num_threads(2)
    x, labels = complete_rows(args.data, args.cache)
    lab, n = torch.from_numpy(labels), len(labels)
    right: dict[str, torch.Tensor] = {}

    def put(key: str, vi: torch.Tensor, scores: torch.Tensor) -> None:
        right.setdefault(key, torch.zeros(n, dtype=torch.bool))[vi] = \
            scores.argmax(1) == lab[vi]

    for f, val in enumerate(stratified_folds(labels, 5, 0)):
        t0 = time.time()
        tr, vi = np.setdiff1d(np.arange(n), val), torch.from_numpy(val)
        tf = FeatureTransform.fit(x[tr], 'standardize', 512)
        fit = CovarianceFit.fit(tf(x[tr]), lab[tr], C)
        u_tr, u_val = (torch.nn.functional.normalize(fit.whitened(fit.coords(tf(x[i])), 0.1),
                                                     dim=1) for i in (tr, val))
        lda = torch.log_softmax(fit.lda_logits(fit.coords(tf(x[val])), 0.01), 1).float()
        put('LDA (0.01)', vi, lda)
        for g in (20.0, 40.0, 80.0):
            lv = log_vote_shares(u_val @ u_tr.T, lab[tr], C, g)
            put(f'vote gamma {g:g}', vi, lv)
            for w in (0.1, 0.2, 0.3):
                put(f'head: vote gamma {g:g} + {w:g} x LDA', vi, lv + w * lda)
        phi = torch.cat([u_tr, torch.ones(len(tr), 1)], 1).double()
        phi_v = torch.cat([u_val, torch.ones(len(val), 1)], 1).double()
        y = torch.nn.functional.one_hot(lab[tr], C).double()
        for lam in (0.01, 1.0, 10.0):
            w = torch.linalg.solve(phi.T @ phi + lam * torch.eye(phi.shape[1], dtype=phi.dtype),
                                   phi.T @ y)
            put(f'linear ridge lambda {lam:g}', vi, phi_v @ w)
        for (g, lam), s in ridge_cv_scores(u_tr, u_val, lab[tr], C, tuple(args.gammas),
                                           tuple(args.lambdas)).items():
            put(f'KRR gamma {g:g} lambda {lam:g}', vi, s)
        if args.quantised:
            q_tr = stored_rows(u_tr, 'int4')
            for g, lam in ((1.0, 0.01), (0.5, 0.01)):
                for name, fit_rows in (('float fit', u_tr), ('int4 fit', q_tr)):
                    a = fit_ridge(fit_rows, lab[tr], C, g, lam)
                    put(f'KRR gamma {g:g} lambda {lam:g}, {name}, int4 rows queried', vi,
                        ridge_scores(u_val @ q_tr.T, a, g))
        print(f'fold {f}: {time.time() - t0:.0f} s', flush=True)
    for key, ok in sorted(right.items(), key=lambda kv: -float(kv[1].double().mean())):
        print(f'{100 * float(ok.double().mean()):6.2f} %  {key}')


if __name__ == '__main__':
    main()
