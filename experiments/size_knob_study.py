#!/usr/bin/env python3
"""The taught-class layer's knobs (bank/taught.py) by CV on two data sets, no test object read.

KAPPA (logit per unit cosine to a taught class mean), W_SIZE (weight of the size
plausibility) and GATE_COS (the best cosine to a taught mean from which the prototypes
re-divide the taught block) are scored on:

  tabletop   the restaurant Kinect-sim tree (metres): 5 views of each of the 20 classes taught
             into the shipped bank (`add_examples` with `bank add`'s policy, measured sizes), the
             other views queried; mean class accuracy over --draws draws
  mn40       ModelNet40 TRAIN objects, one simulated single-view scan each (seed 5), each given
             a plausible real size (the class's size prior, x 0.8-1.25 per object):
             (a) few-shot: 10 random classes, 5 scans each as prototypes + size models, the
                 other scans (<= 20 a class) queried among those 10 (the layer's argmax inside
                 the taught block); mean class accuracy over --draws draws;
             (b) the cost to built classes: the tabletop classes of draw 0 taught into the
                 shipped bank, then the train scans (<= 20 a class, no size: unit-sphere data
                 as `point_gn eval` passes them) classified: accuracy before - after, points

and the fit rule (fit < 0 -> unknown) on (c) the same sized train scans against the shipped bank.
A knob value is kept only if it holds on both data sets.

usage: experiments/size_knob_study.py [--cache DIR] [--draws 3]
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
from point_gn_ros.bank.taught import PRIOR_COUNT, PRIOR_VAR, plausible_scale
from point_gn_ros.core.size import size_descriptors
from point_gn_ros.core.views import VIEW_PROTOCOLS
from point_gn_ros.datasets import open_dataset
from point_gn_ros.datasets.views import ViewsDataset
from point_gn_ros.evaluation.teach import mean_class_accuracy
from point_gn_ros.recognizer import Encoder, make_encoder

SHARED = Path(__file__).resolve().parents[2] / 'shared' / 'datasets'
KAPPAS = (5.0, 10.0, 20.0)
W_SIZES = (0.25, 0.5, 1.0, 2.0)
GATES = (-1.0, 0.6, 0.75, 0.85)          # -1: always open (no gate)
POLICY = RefitPolicy(lda_prior='typical', lda_debias=2.0, lda_steal_budget=0.001)


def tabletop(cache: Path, draws: int) -> tuple[dict, BankFile]:
    """Mean class accuracy per (kappa, w, gate); and draw 0's taught bank."""
    ds = open_dataset(SHARED / 'restaurant_kinectsim' / 'all', split='train')
    base = BankFile.load(None)
    enc = make_encoder(base.bank.config, 'cpu')
    feats = torch.as_tensor(encode_dataset(ds, enc, 64, progress=False, cache_dir=cache))
    sizes = size_descriptors([ds[i][0] for i in range(len(ds))])
    y = np.asarray(ds.labels)
    names = list(ds.class_names)
    scores: dict = {}
    first = None
    for draw in range(draws):
        rng = np.random.default_rng(draw)
        sup = np.concatenate([rng.permutation(np.flatnonzero(y == c))[:5]
                              for c in range(len(names))])
        bf = base
        for c in range(len(names)):
            idx = sup[y[sup] == c]
            bf = add_examples(bf, feats[idx], names[c], 'study', POLICY, sizes=sizes[idx]).file
        first = bf if first is None else first
        clf = Classifier(bf.bank, 'cpu')
        q = np.setdiff1d(np.arange(len(y)), sup)
        prob, _ = clf.evaluate(feats[q])
        z = clf.transform(feats[q])
        ymap = np.array([bf.bank.class_names.index(n) for n in names])
        for k in KAPPAS:
            for w in W_SIZES:
                for g in GATES:
                    layer = replace(clf.taught, kappa=k, w_size=w, gate_cos=g)
                    pred = layer.apply(prob, z, sizes[q])[0].argmax(1).numpy()
                    scores.setdefault((k, w, g), []).append(
                        mean_class_accuracy(pred, ymap[y[q]]))
    return scores, first


def sized_train_scans(cache: Path, enc: Encoder
                      ) -> tuple[torch.Tensor, np.ndarray, np.ndarray, list[str]]:
    """ModelNet40 train scans at plausible real sizes.

    One single-view scan (hpr, seed 5) of 25 objects a class (seed 0), each scaled to its
    class's size prior x 0.8-1.25 -> features (1000, D), labels (1000,), log sizes
    (1000, SIZE_DIM), class names.
    """
    ds = open_dataset(SHARED / 'modelnet40_1024', split='train')
    y_all = np.asarray(ds.labels)
    rng = np.random.default_rng(0)
    pick = np.concatenate([rng.permutation(np.flatnonzero(y_all == c))[:25] for c in range(40)])
    views = ViewsDataset(ds, 1, 5, VIEW_PROTOCOLS['hpr'][0], include_full=False,
                         random_yaw=True)
    feats = torch.as_tensor(encode_dataset(views, enc, 64, progress=False,
                                           cache_dir=cache))[pick]
    clouds = []
    for i in pick:
        full = ds[int(i)][0]
        s = plausible_scale(full, ds.class_names[int(y_all[i])]) * rng.uniform(0.8, 1.25)
        clouds.append(views[int(i)][0] * s)
    return feats, y_all[pick], size_descriptors(clouds), list(ds.class_names)


def mn40(cache: Path, draws: int, taught: BankFile) -> tuple[dict, dict, float]:
    """(a) few-shot accuracy per (w / kappa); (b) drop (points) per (kappa, gate); (c) fit < 0."""
    base = BankFile.load(None)
    enc = make_encoder(base.bank.config, 'cpu')
    feats, y, sizes, _ = sized_train_scans(cache, enc)
    shipped = Classifier(base.bank, 'cpu', fit_threshold=0.0)
    z = shipped.transform(feats)
    # (c) the fit rule against the shipped bank, sized scans
    res = shipped.classify(feats, 1, sizes)
    fit_reject = float((res.fit < 0).mean())
    # (a) prototypes + size among 10 classes: the layer's division of the taught block
    few: dict = {}
    zq = z.double().numpy()
    for draw in range(draws):
        r = np.random.default_rng(100 + draw)
        classes = r.choice(40, 10, replace=False)
        sup = np.concatenate([r.permutation(np.flatnonzero(y == c))[:5] for c in classes])
        qry = np.setdiff1d(np.flatnonzero(np.isin(y, classes)), sup)
        means = np.stack([zq[sup[y[sup] == c]].mean(0) for c in classes])
        means /= np.linalg.norm(means, axis=1, keepdims=True)
        mu = np.stack([sizes[sup[y[sup] == c]].mean(0) for c in classes])
        m2 = np.stack([((sizes[sup[y[sup] == c]] - mu[j]) ** 2).sum(0)
                       for j, c in enumerate(classes)])
        var = (m2 + PRIOR_COUNT * PRIOR_VAR) / (5 - 1 + PRIOR_COUNT)
        cos = zq[qry] @ means.T
        plaus = -0.5 * (((sizes[qry][:, None] - mu[None]) ** 2) / var[None]).sum(-1)
        for ratio in (0.0,) + tuple(w / k for k in KAPPAS for w in W_SIZES):
            pred = classes[(cos + ratio * plaus).argmax(1)]
            few.setdefault(round(ratio, 4), []).append(mean_class_accuracy(pred, y[qry]))
    # (b) what teaching the tabletop classes costs these scans (no sizes, as eval)
    before = (shipped.evaluate(feats)[0].argmax(1).numpy() == y).mean()
    clf = Classifier(taught.bank, 'cpu')
    prob, _ = clf.evaluate(feats)
    zt = clf.transform(feats)
    drop: dict = {}
    for k in KAPPAS:
        for g in GATES:
            layer = replace(clf.taught, kappa=k, gate_cos=g)
            pred = layer.apply(prob, zt, None)[0].argmax(1).numpy()
            drop[(k, g)] = 100 * (before - (pred == y).mean())
    head_drop = 100 * (before - (prob.argmax(1).numpy() == y).mean())
    drop[('head', None)] = head_drop
    return few, drop, fit_reject


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--cache', default='cache')
    ap.add_argument('--draws', type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(2)
    cache = Path(args.cache)
    tab, taught = tabletop(cache, args.draws)
    few, drop, fit_reject = mn40(cache, args.draws, taught)
    print(f'## tabletop, 5 views a class taught, {args.draws} draws: mean class accuracy %')
    print('| kappa | w_size | ' + ' | '.join(f'gate {g:g}' for g in GATES) + ' |')
    print('|---|---|' + '---|' * len(GATES))
    for k in KAPPAS:
        for w in W_SIZES:
            print(f'| {k:g} | {w:g} | ' + ' | '.join(
                f'{100 * np.mean(tab[k, w, g]):.1f}' for g in GATES) + ' |')
    print(f'\n## ModelNet40 train scans at plausible sizes, 10-way 5-shot prototypes + size, '
          f'{args.draws} draws: mean class accuracy % by w_size / kappa')
    for ratio, v in sorted(few.items()):
        print(f'| {ratio:g} | {100 * np.mean(v):.1f} ± {100 * np.std(v):.1f} |')
    print('\n## ModelNet40 train scans (no size): accuracy drop in points after teaching the '
          '20 tabletop classes (draw 0)')
    print(f'head alone (no layer): {drop.pop(("head", None)):.2f}')
    for (k, g), v in sorted(drop.items()):
        print(f'| kappa {k:g} | gate {g:g} | {v:.2f} |')
    print(f'\n## fit rule (fit < 0) on the sized ModelNet40 train scans, shipped bank: '
          f'{100 * fit_reject:.2f} % rejected')


if __name__ == '__main__':
    main()
