"""Classifier: agreement with the reference formula, stability, chunking, top-k, open set."""

import numpy as np
import pytest
import torch

from point_gn_ros.bank import vote as vote_mod
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.bank.classifier import Classifier, UNKNOWN
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.bank.model import FeatureTransform
from point_gn_ros.bank.vote import log_vote_shares


def class_scores(query: torch.Tensor, feats: torch.Tensor, labels: torch.Tensor,
                 num_classes: int, gamma: float) -> torch.Tensor:
    """The reference kernel-vote shares (bank/vote.py `log_vote_shares`): (B, C)."""
    return log_vote_shares(query @ feats.T, labels, num_classes, gamma).exp()


def _bank(n: int = 200, classes: int = 5, gamma: float = 20.0, seed: int = 0,
          calibration: float | None = None) -> FeatureBank:
    g = torch.Generator().manual_seed(seed)
    cfg = EncoderConfig()
    labels = torch.arange(n) % classes
    centres = torch.randn(classes, cfg.feature_dim, generator=g)
    raw = centres[labels] + 0.8 * torch.randn(n, cfg.feature_dim, generator=g)
    tf = FeatureTransform.identity(cfg.feature_dim)
    meta = {'unknown_calibration': {'threshold': calibration}} if calibration else {}
    return FeatureBank(tf(raw), labels, [f'c{i}' for i in range(classes)], cfg, tf, gamma, meta)


def test_matches_reference_formula_where_it_does_not_underflow() -> None:
    bank = _bank(gamma=5.0)
    q = torch.randn(16, bank.features.shape[1])
    ours = Classifier(bank).scores(q).double()
    cos = torch.nn.functional.normalize(q.double(), dim=1) @ bank.features.double().T
    onehot = torch.nn.functional.one_hot(bank.labels, bank.num_classes).double()
    ref = torch.exp(-5.0 * (1 - cos)) @ onehot
    assert torch.allclose(ours, ref / ref.sum(1, keepdim=True), atol=1e-5)
    assert torch.equal(ours.argmax(1), ref.argmax(1))


def test_large_gamma_stays_finite_and_tends_to_nearest_neighbour() -> None:
    bank = _bank(gamma=1e5)
    q = torch.randn(32, bank.features.shape[1])
    s = Classifier(bank).scores(q)
    assert torch.isfinite(s).all()
    assert torch.allclose(s.sum(1), torch.ones(32))
    nn_label = bank.labels[(torch.nn.functional.normalize(q, dim=1) @ bank.features.T).argmax(1)]
    assert torch.equal(s.argmax(1), nn_label)


def test_chunked_scores_equal_unchunked(monkeypatch: pytest.MonkeyPatch) -> None:
    bank = _bank()
    q = torch.randn(50, bank.features.shape[1])
    full = Classifier(bank).scores(q)
    monkeypatch.setattr(vote_mod, 'MAX_BLOCK', 1000)  # 5 queries per block
    assert torch.allclose(Classifier(bank).scores(q), full, atol=1e-6)


def test_topk_sorted_and_consistent() -> None:
    bank = _bank()
    res = Classifier(bank).classify(torch.randn(8, bank.features.shape[1]), top_k=3)
    assert res.topk_ids.shape == (8, 3) and res.topk_scores.shape == (8, 3)
    assert (np.diff(res.topk_scores, axis=1) <= 0).all()
    np.testing.assert_array_equal(res.labels, res.topk_ids[:, 0])
    np.testing.assert_array_equal(res.scores, res.topk_scores[:, 0])
    # top_k larger than the number of classes is clamped
    assert Classifier(bank).classify(torch.randn(2, 1620), top_k=50).topk_ids.shape == (2, 5)


def test_classifies_bank_members_correctly() -> None:
    bank = _bank()
    # Bank features are already transformed; the identity transform re-normalises them.
    res = Classifier(bank).classify(bank.features[:40])
    assert (res.labels == bank.labels[:40].numpy()).mean() > 0.95


def test_unknown_threshold_explicit_and_from_bank() -> None:
    bank = _bank(calibration=0.99)
    q = torch.randn(20, bank.features.shape[1])  # far from every class: weak evidence
    assert (Classifier(bank).classify(q).labels >= 0).all()
    off = Classifier(bank, unknown_threshold=0.0).classify(q)
    assert (off.labels >= 0).all()
    res = Classifier(bank, unknown_threshold=-1).classify(q)
    assert (res.labels[res.scores < 0.99] == UNKNOWN).all()
    assert (res.labels == UNKNOWN).any()
    with pytest.raises(ValueError, match='calibrated'):
        Classifier(_bank(), unknown_threshold=-1)


def test_empty_batch() -> None:
    bank = _bank()
    res = Classifier(bank).classify(torch.zeros(0, 1620))
    assert len(res) == 0 and res.topk_ids.shape == (0, 5)


def test_class_scores_rows_sum_to_one_with_missing_class() -> None:
    feats = torch.nn.functional.normalize(torch.randn(10, 8), dim=1)
    labels = torch.zeros(10, dtype=torch.int64)  # class 1 has no entries
    s = class_scores(feats, feats, labels, 2, 10.0)
    assert torch.allclose(s[:, 0], torch.ones(10)) and (s[:, 1] == 0).all()


def test_a_novelty_calibrated_bank_thresholds_novelty_everywhere() -> None:
    """unknown_threshold < 0 on a bank whose calibration measures novelty.

    The Classifier applies it as a novelty threshold, not a probability one, wherever it is
    resolved.
    """
    from point_gn_ros.bank.classifier import unknown_rules
    pytest.importorskip('rcl_interfaces')
    from point_gn_ros.node.params import NodeConfigError, resolve_unknown_threshold

    bank = _bank()
    q = torch.randn(24, bank.features.shape[1])
    novelty = Classifier(bank).classify(q).novelty
    cut = float(np.median(novelty))
    bank.meta['unknown_calibration'] = {'threshold': cut, 'measure': 'novelty',
                                        'false_reject_rate': 0.05}
    rules = unknown_rules(bank, -1)
    assert rules.probability is None and rules.novelty == cut
    clf = Classifier(bank, unknown_threshold=-1)
    res = clf.classify(q)
    assert ((res.labels == UNKNOWN) == (res.novelty > cut)).all()
    assert 0 < (res.labels == UNKNOWN).sum() < len(q)
    # the node's check and the live swap resolve it the same way (no probability threshold)
    assert resolve_unknown_threshold(bank, -1) is None
    other = Classifier(bank)
    other.set_unknown_threshold(-1)
    assert other.rules == clf.rules
    assert np.array_equal(other.classify(q).labels, res.labels)
    other.set_unknown_threshold(0.5)
    assert other.rules.probability == 0.5 and other.rules.novelty is None
    bank.meta.pop('unknown_calibration')
    with pytest.raises(ValueError, match='calibrat'):
        other.set_unknown_threshold(-1)
    assert other.rules.probability == 0.5          # unchanged by the refused value
    with pytest.raises(NodeConfigError, match='calibrat'):
        resolve_unknown_threshold(bank, -1)
