#!/usr/bin/env python3
"""How far few-shot classifiers can go on the tabletop set with the features the node has.

Among the 20 tabletop classes only (no built class), K views a class as the support, the
other views queried, mean class accuracy over --draws seeded draws, for:

  ncm raw / ncm z       cosine to the class mean of the raw encoder features / of the shipped
                        bank's transformed rows (the taught layer's space)
  size                  per-class Gaussian of the 6 log sizes (core/size.py), the taught
                        layer's variance prior (bank/taught.py)
  size + 10 ncm z       the taught layer's division of the taught block
  lda size + d2 (+ z)   shrinkage LDA (pooled within-class covariance of the support, 0.3 of
                        its mean variance on the diagonal) on the log sizes and a metric pair-
                        distance histogram (40 log bins, 5 mm - 5 m, of 256 points; not in the
                        product), with or without z

usage: experiments/fewshot_ceiling_study.py [--cache DIR] [--draws 10]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from point_gn_ros.bank.builder import encode_dataset
from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.bank.enroll import BankFile
from point_gn_ros.bank.taught import KAPPA, PRIOR_COUNT, PRIOR_VAR
from point_gn_ros.core.size import size_descriptors
from point_gn_ros.datasets import open_dataset
from point_gn_ros.evaluation.teach import mean_class_accuracy
from point_gn_ros.recognizer import make_encoder

SHARED = Path(__file__).resolve().parents[2] / 'shared' / 'datasets'
EDGES = np.linspace(np.log(0.005), np.log(5.0), 41)


def unit(a: np.ndarray) -> np.ndarray:
    return a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)


def d2_histogram(xyz: np.ndarray, rng: np.random.Generator, n: int = 256) -> np.ndarray:
    """(N, 3) metres -> (40,) square-rooted histogram of log pair distances (sums to 1 squared)."""
    p = xyz[rng.choice(len(xyz), min(n, len(xyz)), replace=False)]
    d = np.linalg.norm(p[:, None] - p[None], axis=-1)[np.triu_indices(len(p), 1)]
    h = np.histogram(np.log(np.maximum(d, 1e-4)), EDGES)[0].astype(np.float64)
    return np.sqrt(h / max(h.sum(), 1.0))


def means(x: np.ndarray, y: np.ndarray, classes: int) -> np.ndarray:
    return np.stack([x[y == c].mean(0) for c in range(classes)])


def ncm(x: np.ndarray, ys: np.ndarray, s: np.ndarray, q: np.ndarray, c: int) -> np.ndarray:
    return unit(x[q]) @ unit(means(unit(x[s]), ys, c)).T


def size_gauss(x: np.ndarray, ys: np.ndarray, s: np.ndarray, q: np.ndarray, c: int) -> np.ndarray:
    mu = means(x[s], ys, c)
    m2 = np.stack([((x[s][ys == k] - mu[k]) ** 2).sum(0) for k in range(c)])
    n = np.bincount(ys, minlength=c)[:, None]
    var = (m2 + PRIOR_COUNT * PRIOR_VAR) / (n - 1 + PRIOR_COUNT)
    return -0.5 * (((x[q][:, None] - mu[None]) ** 2) / var[None]).sum(-1)


def lda(x: np.ndarray, ys: np.ndarray, s: np.ndarray, q: np.ndarray, c: int,
        shrink: float = 0.3) -> np.ndarray:
    mu = means(x[s], ys, c)
    r = x[s] - mu[ys]
    cov = r.T @ r / max(len(s) - c, 1)
    cov = (1 - shrink) * cov + shrink * np.trace(cov) / len(cov) * np.eye(len(cov))
    w = np.linalg.solve(cov, mu.T)
    return x[q] @ w - 0.5 * (mu * w.T).sum(1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--cache', default='cache')
    ap.add_argument('--draws', type=int, default=10)
    args = ap.parse_args()
    torch.set_num_threads(2)
    ds = open_dataset(SHARED / 'restaurant_kinectsim' / 'all', split='train')
    base = BankFile.load(None)
    enc = make_encoder(base.bank.config, 'cpu')
    raw = torch.as_tensor(encode_dataset(ds, enc, 64, progress=False,
                                         cache_dir=Path(args.cache)))
    z = Classifier(base.bank).transform(raw).numpy()
    clouds = [ds[i][0] for i in range(len(ds))]
    size = size_descriptors(clouds)
    rng = np.random.default_rng(0)
    d2 = np.stack([d2_histogram(c, rng) for c in clouds])
    f, y, c = raw.numpy(), np.asarray(ds.labels), len(ds.class_names)
    rules = {
        'ncm raw': lambda s, q, ys: ncm(f, ys, s, q, c),
        'ncm z': lambda s, q, ys: ncm(z, ys, s, q, c),
        'size': lambda s, q, ys: size_gauss(size, ys, s, q, c),
        'size + 10 ncm z': lambda s, q, ys: size_gauss(size, ys, s, q, c)
        + KAPPA * ncm(z, ys, s, q, c),
        'lda size + d2': lambda s, q, ys: lda(np.c_[size, d2], ys, s, q, c),
        'lda size + d2 + z': lambda s, q, ys: lda(np.c_[3 * size, 3 * d2, z], ys, s, q, c),
    }
    print(f'## tabletop, 20 classes among themselves, mean class accuracy over {args.draws} draws')
    print('| classifier | 5 views a class | 30 views a class |\n|---|---|---|')
    for name, rule in rules.items():
        cells = []
        for shots in (5, 30):
            accs = []
            for draw in range(args.draws):
                r = np.random.default_rng(draw)
                s = np.concatenate([r.permutation(np.flatnonzero(y == k))[:shots]
                                    for k in range(c)])
                q = np.setdiff1d(np.arange(len(y)), s)
                accs.append(mean_class_accuracy(rule(s, q, y[s]).argmax(1), y[q]))
            cells.append(f'{100 * np.mean(accs):.1f} ± {100 * np.std(accs):.1f} %')
        print(f'| {name} | ' + ' | '.join(cells) + ' |', flush=True)


if __name__ == '__main__':
    main()
