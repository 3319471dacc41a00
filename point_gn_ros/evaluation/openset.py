"""Open-set figures: a bank of known classes queried with known and unseen classes. No ROS."""

from __future__ import annotations

from typing import Any

import numpy as np


class KnownSubset:
    """The known classes of a dataset, relabelled 0..K-1 (the Dataset contract).

    dataset: any Dataset; known: (K,) sorted class ids. `index` (M,) maps rows back.
    """

    def __init__(self, dataset, known: np.ndarray) -> None:
        self.dataset = dataset
        labels = np.asarray(dataset.labels)
        self.index = np.flatnonzero(np.isin(labels, known)).astype(np.int64)
        self.labels = np.searchsorted(known, labels[self.index])
        self.class_names = [dataset.class_names[i] for i in known]
        self.path, self.format = dataset.path, dataset.format
        self.split = f'{dataset.split} ({len(known)} known classes)'

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> tuple[np.ndarray, int]:
        return self.dataset[int(self.index[i])][0], int(self.labels[i])


def choose_known(spec: str, class_names: list[str], seed: int = 0) -> np.ndarray:
    """Known class ids (sorted) from 'N' (N classes drawn with `seed`) or 'a,b,c' (names).

    -> (K,) int64; raises ValueError naming what is wrong.
    """
    spec = spec.strip()
    if spec.isdigit():
        n = int(spec)
        if not 1 <= n < len(class_names):
            raise ValueError(f'--open-set {n}: need 1..{len(class_names) - 1} known classes')
        rng = np.random.default_rng(seed)
        return np.sort(rng.choice(len(class_names), n, replace=False)).astype(np.int64)
    names = [s.strip() for s in spec.split(',') if s.strip()]
    unknown = sorted(set(names) - set(class_names))
    if unknown:
        raise ValueError(f'--open-set: no such classes {unknown}')
    if not 1 <= len(set(names)) < len(class_names):
        raise ValueError('--open-set: give at least one and fewer than all classes')
    return np.sort([class_names.index(n) for n in set(names)]).astype(np.int64)


def auroc(positive: np.ndarray, negative: np.ndarray) -> float:
    """Probability that a positive scores above a negative (ties count half)."""
    pos, neg = np.asarray(positive, np.float64), np.asarray(negative, np.float64)
    if len(pos) == 0 or len(neg) == 0:
        return float('nan')
    both = np.concatenate([pos, neg])
    order = np.argsort(both, kind='mergesort')
    ranks = np.empty(len(both))
    ranks[order] = np.arange(1, len(both) + 1)
    # average ranks over ties
    vals = both[order]
    starts = np.flatnonzero(np.r_[True, vals[1:] != vals[:-1]])
    ends = np.r_[starts[1:], len(vals)]
    for s, e in zip(starts, ends, strict=True):
        if e - s > 1:
            ranks[order[s:e]] = (s + 1 + e) / 2
    u = ranks[:len(pos)].sum() - len(pos) * (len(pos) + 1) / 2
    return float(u / (len(pos) * len(neg)))


def open_set_report(true: np.ndarray, known: np.ndarray, pred: np.ndarray,
                    novelty: np.ndarray, top_prob: np.ndarray, top1: np.ndarray
                    ) -> dict[str, Any]:
    """Figures of one open-set run.

    true: (M,) dataset class ids; known: (K,) the bank's classes as dataset ids, in
    bank order; pred: (M,) bank class ids, -1 = rejected as unknown (the default
    threshold); novelty, top_prob: (M,). AUROCs treat unseen classes as positives.
    """
    true = np.asarray(true)
    is_known = np.isin(true, known)
    mapped = np.full(len(true), -2)
    mapped[is_known] = np.searchsorted(known, true[is_known])
    return {
        'known_objects': int(is_known.sum()), 'unseen_objects': int((~is_known).sum()),
        'auroc_novelty': auroc(novelty[~is_known], novelty[is_known]),
        'auroc_top_probability': auroc(-top_prob[~is_known], -top_prob[is_known]),
        'known_accuracy_closed_set': float((top1[is_known] == mapped[is_known]).mean()),
        'known_accuracy_at_threshold': float((pred[is_known] == mapped[is_known]).mean()),
        'known_false_reject_rate': float((pred[is_known] < 0).mean()),
        'unknown_recall_at_threshold': float((pred[~is_known] < 0).mean()),
    }
