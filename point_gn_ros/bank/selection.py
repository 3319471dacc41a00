"""Choosing gamma, feature transform and open-set threshold by cross-validation on the bank.

Nothing here ever sees a test split: every figure is a held-out fold of the bank.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import itertools

import numpy as np
import torch

from point_gn_ros.bank.classifier import votes_from_similarity
from point_gn_ros.bank.transform import FeatureTransform, Standardize

DEFAULT_GAMMAS = tuple(float(g) for g in np.geomspace(5, 5000, 19).round(1))


def stratified_folds(labels: np.ndarray, k: int = 5, seed: int = 0,
                     groups: np.ndarray | None = None) -> list[np.ndarray]:
    """Split indices into k folds with every class spread evenly: list of (n_i,) int64.

    groups: (N,) int or None. Entries sharing a group id (a source object and its
    simulated views) always land in the same fold, so no fold is scored against a
    near-copy of itself; a group takes the label of its first entry for stratification.
    """
    labels = np.asarray(labels)
    if groups is None:
        rng = np.random.default_rng(seed)
        folds: list[list[int]] = [[] for _ in range(k)]
        offset = 0
        for c in np.unique(labels):
            idx = rng.permutation(np.flatnonzero(labels == c))
            for j, i in enumerate(idx):
                folds[(j + offset) % k].append(int(i))
            offset += len(idx)
        return [np.sort(np.asarray(f, dtype=np.int64)) for f in folds]
    groups = np.asarray(groups)
    if groups.shape != labels.shape:
        raise ValueError(f'groups {groups.shape} must match labels {labels.shape}')
    uniq, first, inverse = np.unique(groups, return_index=True, return_inverse=True)
    members = [np.flatnonzero(inverse == g) for g in range(len(uniq))]
    group_label = labels[first]
    rng = np.random.default_rng(seed)
    fold_of_group = np.empty(len(uniq), dtype=np.int64)
    total = np.zeros(k, dtype=np.int64)
    for c in np.unique(group_label):
        gs = rng.permutation(np.flatnonzero(group_label == c))
        per_class = np.zeros(k, dtype=np.int64)
        # Largest groups first, each to the fold holding fewest of this class (then fewest
        # overall): near-even class counts per fold even with uneven group sizes.
        for g in sorted(gs, key=lambda g: -len(members[g])):
            f = int(np.lexsort((total, per_class))[0])
            fold_of_group[g] = f
            per_class[f] += len(members[g])
            total[f] += len(members[g])
    return [np.sort(np.concatenate([members[g] for g in np.flatnonzero(fold_of_group == f)]
                                   + [np.zeros(0, dtype=np.int64)])).astype(np.int64)
            for f in range(k)]


@dataclass
class Selection:
    """Best knobs and the CV table they were picked from."""

    gamma: float
    standardize: Standardize
    dims: int | None
    cv_accuracy: float
    table: list[dict] = field(default_factory=list)
    heldout_scores: np.ndarray | None = None    # (N,) top-1 score of each entry, held out
    heldout_correct: np.ndarray | None = None   # (N,) bool


def _fold_scores(feats: torch.Tensor, labels: torch.Tensor, num_classes: int,
                 train: np.ndarray, val: np.ndarray, standardize: Standardize,
                 dims: int | None, gammas: tuple[float, ...]) -> list[torch.Tensor]:
    tf = FeatureTransform.fit(feats[train], standardize, dims)
    sims = tf(feats[val]) @ tf(feats[train]).T      # once per fold, reused for every gamma
    return [votes_from_similarity(sims, labels[train], num_classes, g) for g in gammas]


def select(feats: torch.Tensor, labels: np.ndarray, num_classes: int,
           gammas: tuple[float, ...] = DEFAULT_GAMMAS,
           standardize_options: tuple[Standardize, ...] = ('none', 'standardize'),
           dims_options: tuple[int | None, ...] = (None,), folds: int = 5,
           seed: int = 0, groups: np.ndarray | None = None) -> Selection:
    """Grid search by stratified k-fold CV on the bank.

    feats: (N, D) float32 raw encoder features; labels: (N,) int; groups: (N,) int or
    None (entries of one group never split across folds). Returns the
    combination with the best mean held-out accuracy (ties: the earlier, simpler one).
    """
    lab = torch.from_numpy(np.asarray(labels, dtype=np.int64))
    parts = stratified_folds(np.asarray(labels), folds, seed, groups)
    everything = np.arange(len(labels))
    table = []
    best = None
    for std, dims in itertools.product(standardize_options, dims_options):
        correct = np.zeros((len(gammas), len(labels)), dtype=bool)
        top = np.zeros((len(gammas), len(labels)), dtype=np.float32)
        for val in parts:
            train = np.setdiff1d(everything, val)
            for gi, s in enumerate(_fold_scores(feats, lab, num_classes, train, val, std, dims,
                                                gammas)):
                best_s, pred = s.max(dim=1)
                correct[gi, val] = (pred == lab[val]).numpy()
                top[gi, val] = best_s.numpy()
        acc = correct.mean(axis=1)
        for g, a in zip(gammas, acc, strict=True):
            table.append({'standardize': std, 'dims': dims, 'gamma': g, 'cv_accuracy': float(a)})
        gi = int(np.argmax(acc))
        if best is None or acc[gi] > best.cv_accuracy + 1e-12:
            best = Selection(gamma=gammas[gi], standardize=std, dims=dims,
                             cv_accuracy=float(acc[gi]), heldout_scores=top[gi],
                             heldout_correct=correct[gi])
    assert best is not None
    best.table = table
    return best


def calibrate_unknown(heldout_scores: np.ndarray, false_reject_rate: float = 0.05) -> dict:
    """Threshold on the top-1 score rejecting `false_reject_rate` of held-out bank objects.

    Every bank object is a known class, so the share of them falling below the
    threshold is exactly the false-reject rate expected on in-distribution input.
    """
    thr = float(np.quantile(heldout_scores, false_reject_rate))
    return {'threshold': thr, 'false_reject_rate': float(false_reject_rate),
            'method': f'{false_reject_rate:.0%} quantile of held-out (k-fold) top-1 scores'}
