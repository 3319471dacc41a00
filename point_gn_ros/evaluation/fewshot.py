"""N-way K-shot episodes: a support set as the bank, queries classified against it.

Each episode's support set is a bank like any other: transform and head (whitened
vote, LDA fusion, temperature) chosen by stratified k-fold CV on the support set
alone (fewer folds, or the plain vote, when the shots are too few; see `select`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from point_gn_ros.bank.builder import fit_selected
from point_gn_ros.bank.selection import select
from point_gn_ros.bank.model import Standardize
from point_gn_ros.bank.vote import ExactSearch, reference_head

PAPER_SETTINGS = ((5, 10), (5, 20), (10, 10), (10, 20))


def sample_episode(labels: np.ndarray, ways: int, shots: int, queries: int,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> support indices (ways*shots,), query indices (ways*queries,), chosen classes (ways,)."""
    counts = np.bincount(labels)
    eligible = np.flatnonzero(counts >= shots + queries)
    if len(eligible) < ways:
        raise ValueError(f'only {len(eligible)} classes have {shots + queries} objects; '
                         f'{ways}-way {shots}-shot with {queries} queries is impossible')
    classes = np.sort(rng.choice(eligible, ways, replace=False))
    support, query = [], []
    for c in classes:
        idx = rng.permutation(np.flatnonzero(labels == c))
        support.append(idx[:shots])
        query.append(idx[shots:shots + queries])
    return np.concatenate(support), np.concatenate(query), classes


def run_fewshot(labels: np.ndarray, encode: Callable[[np.ndarray], torch.Tensor], ways: int,
                shots: int, queries: int = 20, episodes: int = 10,
                seed: int = 0, folds: int = 5,
                standardize_options: tuple[Standardize, ...] = ('centre', 'standardize')
                ) -> dict:
    """Mean and std accuracy over seeded episodes, with the head each episode's CV chose.

    encode: indices (M,) -> raw features (M, D); called once for all episodes.
    """
    rng = np.random.default_rng(seed)
    eps = [sample_episode(labels, ways, shots, queries, rng) for _ in range(episodes)]
    needed = np.unique(np.concatenate([np.concatenate(e[:2]) for e in eps]))
    feats = dict(zip(needed.tolist(), encode(needed), strict=True))
    accs, heads = [], []
    for support, query, classes in eps:
        remap = {int(c): i for i, c in enumerate(classes)}
        s_lab = torch.tensor([remap[int(labels[i])] for i in support])
        q_lab = torch.tensor([remap[int(labels[i])] for i in query])
        s_raw = torch.stack([feats[int(i)] for i in support])
        q_raw = torch.stack([feats[int(i)] for i in query])
        sel = select(s_raw, s_lab.numpy(), ways, standardize_options=standardize_options,
                     folds=folds, seed=seed)
        tf, head, bank = fit_selected(s_raw, s_lab.numpy(), ways, sel)
        pred = reference_head(head, tf(q_raw), ExactSearch(bank, s_lab, ways))[0].argmax(1)
        accs.append(float((pred == q_lab).float().mean()))
        heads.append({'vote_only': head.is_plain_vote, 'whitened': head.whiten is not None,
                      'fusion_weight': head.fusion_weight, 'fallback': sel.fallback})
    return {'ways': ways, 'shots': shots, 'queries': queries, 'episodes': episodes,
            'mean': float(np.mean(accs)), 'std': float(np.std(accs)), 'accuracies': accs,
            'heads': heads}
