"""Teach-and-query protocol: K scans per class taught into a bank, the rest queried. No ROS.

A robot team's own recordings (a class-per-folder tree in metres, z up) measured the way the
node is used: for each of D seeded draws, K scans of every class are taught into the given
bank by `add_examples` (the code path of `point_gn bank add` and the node's enrollment), the
other scans are classified by the enlarged bank. Reported per draw and as mean +- std:

  mean class accuracy   of the queries (an answer with a class the data set lacks is wrong)
  built share           share of queries answered with a class the data set does not have
  nearest mean          baseline: cosine to the mean of the K raw encoder features of each
                        class, among the data set's classes only
  geometry              baseline: nearest mean of the K metric size descriptors (core/size.py,
                        scaled by their pooled spread), among the data set's classes only
  open set              before the draw's last class is taught (class d mod C of draw d is
                        left out), the other classes' queries against the left-out class's
                        scans: AUROC of the shape-and-size fit (bank/taught.py), of the
                        answer's size misfit and of the top probability, and the default
                        rule's reject rates of both
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import torch

from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.bank.enroll import BankFile, add_examples
from point_gn_ros.bank.refit import RefitPolicy
from point_gn_ros.evaluation.openset import auroc


def mean_class_accuracy(pred: np.ndarray, true: np.ndarray) -> float:
    """pred, true: (M,) class ids (pred -1 or other ids: wrong) -> mean of per-class recall."""
    classes = np.unique(true)
    return float(np.mean([(pred[true == c] == c).mean() for c in classes]))


def nearest_mean(train: np.ndarray, train_y: np.ndarray, query: np.ndarray, classes: int,
                 cosine: bool = True) -> np.ndarray:
    """Nearest class mean: (N, F), (N,), (M, F) -> (M,) predicted class ids.

    cosine: by cosine to each class mean; else by Euclidean distance after dividing every
    column by its spread in `train` (pooled within-class standard deviation).
    """
    means = np.stack([train[train_y == c].mean(0) for c in range(classes)])
    if cosine:
        def unit(a: np.ndarray) -> np.ndarray:
            return a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
        return (unit(query) @ unit(means).T).argmax(1)
    within = np.sqrt(np.mean((train - means[train_y]) ** 2, axis=0)) + 1e-6
    d = (((query[:, None, :] - means[None]) / within) ** 2).sum(-1)
    return d.argmin(1)


def run_teach_protocol(bank_file: BankFile, class_names: list[str], labels: np.ndarray,
                       features: torch.Tensor, sizes: np.ndarray | None, shots: int = 5,
                       draws: int = 5, seed: int = 0, policy: RefitPolicy | None = None,
                       fit_threshold: float | None = None,
                       progress: Callable[[str], None] | None = None,
                       structural: np.ndarray | None = None) -> dict[str, Any]:
    """The protocol of the module docstring.

    labels: (M,) data set class ids into class_names; features: (M, D) raw encoder output;
    sizes: (M, SIZE_DIM) metric log sizes, or None (no units: size skipped); fit_threshold:
    the default rule's fit threshold (None: no fit rule; the reject rates then use only
    the bank's own unknown rule, off); structural: (M,) bool, the clouds the node's volume
    and scene rules call unknown (core/surface.py `structure_unknown`; None: no such rules),
    also counted in the reject rates.
    """
    ruled = np.zeros(len(labels), bool) if structural is None else np.asarray(structural, bool)
    labels = np.asarray(labels, dtype=np.int64)
    n_cls = len(class_names)
    counts = np.bincount(labels, minlength=n_cls)
    if counts.min() <= shots:
        short = [class_names[c] for c in np.flatnonzero(counts <= shots)]
        raise ValueError(f'every class needs more than {shots} scans (--shots); too few: '
                         f'{", ".join(short)}')
    policy = policy or RefitPolicy()
    rows = []
    for draw in range(draws):
        rng = np.random.default_rng(seed + draw)
        support = np.concatenate([rng.permutation(np.flatnonzero(labels == c))[:shots]
                                  for c in range(n_cls)])
        query = np.setdiff1d(np.arange(len(labels)), support)
        held = draw % n_cls
        order = [c for c in range(n_cls) if c != held] + [held]
        bf, open_row = bank_file, {}
        for c in order:
            if c == held and n_cls > 1:
                open_row = _open_set(bf, class_names, labels, features, sizes, query, held,
                                     fit_threshold, ruled)
            idx = support[labels[support] == c]
            bf = add_examples(bf, features[idx], class_names[c], source='point_gn fewshot',
                              policy=policy, sizes=None if sizes is None else sizes[idx]).file
        clf = Classifier(bf.bank, fit_threshold=fit_threshold)
        res = clf.classify(features[query], top_k=1,
                           sizes=None if sizes is None else sizes[query])
        ids = np.array([bf.bank.class_names.index(n) for n in class_names])
        to_ds = {int(b): i for i, b in enumerate(ids)}
        top1 = np.array([to_ds.get(int(p), -1) for p in res.topk_ids[:, 0]])
        true = labels[query]
        row = {'draw': draw, 'accuracy': mean_class_accuracy(top1, true),
               'built_share': float((top1 < 0).mean()),
               'rejected': float(((res.labels < 0) | ruled[query]).mean()),
               'structure_rejected': float(ruled[query].mean()),
               'nearest_mean': mean_class_accuracy(nearest_mean(
                   features[support].numpy(), labels[support], features[query].numpy(),
                   n_cls), true)}
        if sizes is not None:
            row['geometry'] = mean_class_accuracy(nearest_mean(
                sizes[support], labels[support], sizes[query], n_cls, cosine=False), true)
        row.update(open_row)
        rows.append(row)
        if progress is not None:
            progress(f'draw {draw}: ' + ', '.join(
                f'{k} {v:.3f}' for k, v in row.items() if k not in ('draw', 'held_out')))
    keys = [k for k in rows[0] if k not in ('draw', 'held_out')]
    summary = {k: {'mean': float(np.nanmean([r.get(k, np.nan) for r in rows])),
                   'std': float(np.nanstd([r.get(k, np.nan) for r in rows]))} for k in keys}
    return {'shots': shots, 'draws': draws, 'seed': seed, 'classes': list(class_names),
            'metric_size': sizes is not None, 'fit_threshold': fit_threshold,
            'summary': summary, 'per_draw': rows}


def _open_set(bf: BankFile, class_names: list[str], labels: np.ndarray, features: torch.Tensor,
              sizes: np.ndarray | None, query: np.ndarray, held: int,
              fit_threshold: float | None, ruled: np.ndarray) -> dict[str, Any]:
    """The bank without class `held`: its scans (all of them) against the others' queries."""
    unseen = np.flatnonzero(labels == held)
    known = query[labels[query] != held]
    rows = np.concatenate([known, unseen])
    clf = Classifier(replace(bf.bank), fit_threshold=fit_threshold)
    res = clf.classify(features[rows], top_k=1, sizes=None if sizes is None else sizes[rows])
    is_unseen = np.r_[np.zeros(len(known), bool), np.ones(len(unseen), bool)]
    out = {'held_out': class_names[held],
           'auroc_top_probability': auroc(-res.scores[is_unseen], -res.scores[~is_unseen])}
    if res.fit is not None:
        out['auroc_fit'] = auroc(-res.fit[is_unseen], -res.fit[~is_unseen])
    if res.size_misfit is not None:
        out['auroc_size'] = auroc(res.size_misfit[is_unseen], res.size_misfit[~is_unseen])
    rejected = (res.labels < 0) | ruled[rows]
    out['unseen_rejected'] = float(rejected[is_unseen].mean())
    out['taught_rejected'] = float(rejected[~is_unseen].mean())
    return out
