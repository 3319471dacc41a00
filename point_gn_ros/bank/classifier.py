"""Bank classifier: cosine similarity, exp(-gamma (1 - cos)) votes per class, softmax.

The reference computes `exp(-gamma (1 - cos)) @ onehot` and a softmax of that. With
gamma in the thousands those sums underflow in float32, so we evaluate them in the
log domain: log-evidence per class = logsumexp over its entries of -gamma (1 - cos),
and score = softmax(log-evidence) = each class's share of the kernel votes. The
argmax is the reference's; the score is a probability-like number in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from point_gn_ros.bank.store import FeatureBank

UNKNOWN = -1
# Upper bound on queries x bank entries held at once (float32 similarity block).
_MAX_BLOCK = 1 << 24


@dataclass
class Classification:
    """Per-query results, plain numpy.

    labels (B,) int64, -1 = unknown; scores (B,) float32 (score of the best class,
    also when it is rejected as unknown); topk_ids (B, k) int64; topk_scores (B, k)
    float32.
    """

    labels: np.ndarray
    scores: np.ndarray
    topk_ids: np.ndarray
    topk_scores: np.ndarray

    def __len__(self) -> int:
        return int(self.labels.shape[0])


def votes_from_similarity(sims: torch.Tensor, bank_labels: torch.Tensor, num_classes: int,
                          gamma: float) -> torch.Tensor:
    """Kernel-vote shares from cosine similarities.

    sims: (B, N) cosine to each bank entry; bank_labels: (N,) int64 -> (B, C) float32,
    rows sum to 1.
    """
    logits = (sims - 1.0) * gamma                                # (B, N), <= 0
    logits = logits - logits.max(dim=1, keepdim=True).values     # best entry -> exp(0)
    votes = torch.zeros(sims.shape[0], num_classes, dtype=logits.dtype, device=logits.device)
    votes.index_add_(1, bank_labels, logits.exp_())
    return votes / votes.sum(dim=1, keepdim=True)


def class_scores(query: torch.Tensor, bank_feats: torch.Tensor, bank_labels: torch.Tensor,
                 num_classes: int, gamma: float) -> torch.Tensor:
    """Kernel-vote shares.

    query: (B, d) unit rows; bank_feats: (N, d) unit rows; bank_labels: (N,) int64
    -> (B, C) float32, rows sum to 1. Queries are processed in blocks so a large
    bank never needs a huge similarity matrix.
    """
    step = max(1, _MAX_BLOCK // max(1, bank_feats.shape[0]))
    out = [votes_from_similarity(q @ bank_feats.T, bank_labels, num_classes, gamma)
           for q in query.split(step)]
    return torch.cat(out) if out else torch.zeros(0, num_classes)


class Classifier:
    """Classifies encoder features against a loaded bank."""

    def __init__(self, bank: FeatureBank, device: str = 'cpu',
                 unknown_threshold: float | None = None, gamma: float | None = None) -> None:
        """unknown_threshold: None/0 = off; < 0 = the bank's calibrated threshold."""
        self.bank = bank
        self.device = torch.device(device)
        self.gamma = float(gamma if gamma is not None else bank.gamma)
        self.transform = bank.transform.to(self.device)
        self.features = bank.features.to(self.device)
        self.labels = bank.labels.to(self.device)
        if unknown_threshold is not None and unknown_threshold < 0:
            calib = bank.meta.get('unknown_calibration')
            if not calib:
                raise ValueError(f'{bank.path}: bank holds no calibrated unknown threshold')
            unknown_threshold = float(calib['threshold'])
        self.unknown_threshold = unknown_threshold or None

    @torch.no_grad()
    def scores(self, features: torch.Tensor) -> torch.Tensor:
        """features: (B, D) raw encoder output -> (B, C) class scores."""
        q = self.transform(features.to(self.device))
        return class_scores(q, self.features, self.labels, self.bank.num_classes, self.gamma)

    @torch.no_grad()
    def classify(self, features: torch.Tensor, top_k: int = 5) -> Classification:
        """features: (B, D) float32 raw encoder output -> Classification."""
        s = self.scores(features).cpu()
        k = max(1, min(top_k, s.shape[1]))
        top_s, top_i = s.topk(k, dim=1)
        labels = top_i[:, 0].clone()
        if self.unknown_threshold is not None:
            labels[top_s[:, 0] < self.unknown_threshold] = UNKNOWN
        return Classification(labels=labels.numpy().astype(np.int64),
                              scores=top_s[:, 0].numpy().astype(np.float32),
                              topk_ids=top_i.numpy().astype(np.int64),
                              topk_scores=top_s.numpy().astype(np.float32))
