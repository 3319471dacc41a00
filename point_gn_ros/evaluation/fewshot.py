"""N-way K-shot episodes: a support set as the bank, queries classified against it."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from point_gn_ros.bank.classifier import class_scores
from point_gn_ros.bank.transform import FeatureTransform
from point_gn_ros.bank.selection import DEFAULT_GAMMAS

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


def _loo_gamma(feats: torch.Tensor, labels: torch.Tensor, ways: int) -> float:
    """Gamma by leave-one-out on the support set alone."""
    sims = feats @ feats.T
    best_g, best_acc = DEFAULT_GAMMAS[0], -1.0
    for g in DEFAULT_GAMMAS:
        logits = (sims - 1.0) * g
        logits.fill_diagonal_(-float('inf'))
        logits = logits - logits.max(dim=1, keepdim=True).values
        votes = torch.zeros(len(labels), ways).index_add_(1, labels, logits.exp())
        acc = float((votes.argmax(1) == labels).float().mean())
        if acc > best_acc + 1e-12:
            best_g, best_acc = g, acc
    return best_g


def run_fewshot(labels: np.ndarray, encode: Callable[[np.ndarray], torch.Tensor], ways: int,
                shots: int, queries: int = 20, episodes: int = 10,
                seed: int = 0) -> dict:
    """Mean and std accuracy over seeded episodes.

    encode: indices (M,) -> raw features (M, D); called once for all episodes.
    """
    rng = np.random.default_rng(seed)
    eps = [sample_episode(labels, ways, shots, queries, rng) for _ in range(episodes)]
    needed = np.unique(np.concatenate([np.concatenate(e[:2]) for e in eps]))
    feats = dict(zip(needed.tolist(), encode(needed), strict=True))
    accs = []
    for support, query, classes in eps:
        remap = {int(c): i for i, c in enumerate(classes)}
        s_lab = torch.tensor([remap[int(labels[i])] for i in support])
        q_lab = torch.tensor([remap[int(labels[i])] for i in query])
        s_raw = torch.stack([feats[int(i)] for i in support])
        q_raw = torch.stack([feats[int(i)] for i in query])
        tf = FeatureTransform.fit(s_raw, 'centre')
        s, q = tf(s_raw), tf(q_raw)
        gamma = _loo_gamma(s, s_lab, ways)
        pred = class_scores(q, s, s_lab, ways, gamma).argmax(1)
        accs.append(float((pred == q_lab).float().mean()))
    return {'ways': ways, 'shots': shots, 'queries': queries, 'episodes': episodes,
            'mean': float(np.mean(accs)), 'std': float(np.std(accs)), 'accuracies': accs}
