"""Cross-validation on the bank: folds, grid choice, open-set calibration, few-shot."""

import numpy as np
import torch

from point_gn_ros.evaluation.fewshot import run_fewshot, sample_episode
from point_gn_ros.bank.selection import calibrate_unknown, select, stratified_folds


def test_folds_are_stratified_disjoint_and_complete() -> None:
    labels = np.repeat(np.arange(4), [10, 20, 5, 7])
    folds = stratified_folds(labels, 5)
    allidx = np.concatenate(folds)
    assert sorted(allidx.tolist()) == list(range(len(labels)))
    for f in folds:
        counts = np.bincount(labels[f], minlength=4)
        assert (np.abs(counts - np.bincount(labels) / 5) <= 1).all()


def _data(seed: int = 0, scale_noise: float = 1.0) -> tuple[torch.Tensor, np.ndarray]:
    g = torch.Generator().manual_seed(seed)
    labels = np.repeat(np.arange(4), 30)
    centres = torch.randn(4, 32, generator=g)
    feats = centres[labels] + 0.9 * torch.randn(len(labels), 32, generator=g)
    # one huge nuisance dimension: only standardisation tames it
    feats[:, 0] = 100 * scale_noise * torch.randn(len(labels), generator=g)
    return feats, labels


def test_select_prefers_standardisation_when_a_dimension_dominates() -> None:
    feats, labels = _data()
    sel = select(feats, labels, 4, gammas=(5.0, 50.0), standardize_options=('none', 'standardize'),
                 alphas=())     # the plain vote: one table row per (standardize, gamma)
    assert sel.standardize == 'standardize'
    none_acc = max(r['cv_accuracy'] for r in sel.table if r['standardize'] == 'none')
    assert sel.cv_accuracy > none_acc
    assert len(sel.table) == 4 and sel.heldout_scores.shape == (120,)


def test_calibration_rejects_the_stated_share() -> None:
    scores = np.linspace(0, 1, 1001)
    cal = calibrate_unknown(scores, 0.05)
    assert abs((scores < cal['threshold']).mean() - 0.05) < 0.002


def test_fewshot_episodes_are_disjoint_and_seeded() -> None:
    labels = np.repeat(np.arange(8), 40)
    rng = np.random.default_rng(0)
    s, q, classes = sample_episode(labels, 5, 10, 20, rng)
    assert len(s) == 50 and len(q) == 100 and not set(s) & set(q)
    assert set(labels[s]) == set(classes) == set(labels[q])
    g = torch.Generator().manual_seed(0)
    table = torch.randn(len(labels), 16, generator=g)
    table += torch.nn.functional.one_hot(torch.from_numpy(labels), 16).float() * 4
    r1 = run_fewshot(labels, lambda idx: table[torch.from_numpy(idx)], 5, 10, episodes=3)
    r2 = run_fewshot(labels, lambda idx: table[torch.from_numpy(idx)], 5, 10, episodes=3)
    assert r1 == r2 and r1['mean'] > 0.9


def test_group_folds_never_split_a_group_and_stay_stratified() -> None:
    rng = np.random.default_rng(1)
    objects = np.repeat(np.arange(4), [10, 20, 5, 7])      # labels of 42 source objects
    views = rng.integers(1, 6, len(objects))               # 1-5 simulated views each
    labels = np.repeat(objects, views)
    groups = np.repeat(rng.permutation(1000)[:len(objects)], views)
    folds = stratified_folds(labels, 5, seed=3, groups=groups)
    allidx = np.concatenate(folds)
    assert sorted(allidx.tolist()) == list(range(len(labels)))
    fold_of = np.empty(len(labels), dtype=int)
    for f, idx in enumerate(folds):
        fold_of[idx] = f
    for g in np.unique(groups):
        assert len(set(fold_of[groups == g])) == 1
    for c in range(4):      # each class spread over the folds, within one group's size
        per_fold = [int((labels[f] == c).sum()) for f in folds]
        assert max(per_fold) - min(per_fold) <= views.max(), per_fold
        assert min(per_fold) > 0


def test_select_accepts_groups() -> None:
    feats, labels = _data()
    groups = np.arange(len(labels)) // 3
    sel = select(feats, labels, 4, gammas=(5.0, 50.0), groups=groups)
    assert sel.heldout_scores.shape == (120,)
