"""Discriminant head: closed-form fit, CV choice, calibrated probabilities, novelty, bank file."""

import json
import logging
from pathlib import Path

import numpy as np
import pytest
import torch

from point_gn_ros.bank.builder import fit_selected
from point_gn_ros.bank.classifier import Classifier, UNKNOWN
from point_gn_ros.bank.discriminant import CovarianceFit, best_temperature, fit_head
from point_gn_ros.bank.model import Head
from point_gn_ros.bank.selection import calibrate_novelty, select
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.bank.model import FeatureTransform
from point_gn_ros.bank.vote import ExactSearch, log_vote_shares, reference_head
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.errors import BankError


def class_scores(query: torch.Tensor, feats: torch.Tensor, labels: torch.Tensor,
                 num_classes: int, gamma: float) -> torch.Tensor:
    """The reference kernel-vote shares (bank/vote.py `log_vote_shares`): (B, C)."""
    return log_vote_shares(query @ feats.T, labels, num_classes, gamma).exp()


def _gaussians(per_class: int, seed: int = 0, d: int = 6, classes: int = 4
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Classes sharing one anisotropic covariance -> x (N, d), y (N,), means, cov."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(d, d, generator=g, dtype=torch.float64)
    cov = a @ a.T / d + 0.1 * torch.eye(d, dtype=torch.float64)
    means = 2 * torch.randn(classes, d, generator=g, dtype=torch.float64)
    y = torch.arange(classes).repeat_interleave(per_class)
    x = means[y] + torch.randn(len(y), d, generator=g, dtype=torch.float64) @ \
        torch.linalg.cholesky(cov).T
    return x, y, means, cov


def test_covariance_fit_recovers_means_covariance_and_lda() -> None:
    x, y, means, cov = _gaussians(5000)
    fit = CovarianceFit.fit(x.float(), y, 4)
    assert torch.allclose(fit.means, means, atol=0.08)
    est = fit.evecs @ torch.diag(fit.evals) @ fit.evecs.T
    assert torch.allclose(est, cov, atol=0.06)
    w = fit.whitening(0.0).double()               # no shrinkage: W Sigma W = I
    assert torch.allclose(w @ est @ w, torch.eye(6, dtype=torch.float64), atol=1e-3)
    coef, bias = fit.lda(0.0)
    inv = torch.linalg.inv(est)
    assert torch.allclose(coef.double(), fit.means @ inv, atol=1e-3)
    assert torch.allclose(bias.double(), -0.5 * ((fit.means @ inv) * fit.means).sum(1)
                          + np.log(0.25), atol=1e-3)
    # full shrinkage: Sigma_1 = tr(Sigma)/d I, so W is a multiple of the identity
    w1 = fit.whitening(1.0).double()
    assert torch.allclose(w1, torch.eye(6, dtype=torch.float64) * w1[0, 0], atol=1e-6)


def _head_bank(per_class: int = 40, seed: int = 0) -> tuple[FeatureBank, torch.Tensor]:
    """A bank whose head whitens and fuses LDA (fixed knobs), raw dims = encoder width."""
    cfg = EncoderConfig()
    g = torch.Generator().manual_seed(seed)
    y = torch.arange(5).repeat_interleave(per_class)
    raw = torch.randn(5, cfg.feature_dim, generator=g)[y] + \
        2 * torch.randn(len(y), cfg.feature_dim, generator=g)
    tf = FeatureTransform.fit(raw, 'standardize', 32)
    z = tf(raw)
    head = fit_head(z, y, 5, gamma=20.0, alpha=0.2, lda_alpha=0.1, fusion_weight=0.3,
                    temperature=2.0)
    bank = FeatureBank(head.vote_space(z), y, [f'c{i}' for i in range(5)], cfg, tf, 20.0,
                       {'head': {'alpha': 0.2}}, head=head)
    return bank, raw


def test_fused_scores_are_probabilities_and_novelty_is_a_distance() -> None:
    bank, raw = _head_bank()
    clf = Classifier(bank)
    far = 5 * torch.randn(10, raw.shape[1], generator=torch.Generator().manual_seed(1))
    res = clf.classify(torch.cat([raw[:10], far]), top_k=3)
    p = res.probability
    assert p.shape == (20, 5) and (p >= 0).all() and (p <= 1).all()
    np.testing.assert_allclose(p.sum(1), 1, atol=1e-5)
    np.testing.assert_allclose(res.scores, p.max(1), atol=1e-6)
    np.testing.assert_array_equal(res.topk_ids[:, 0], p.argmax(1))
    # bank members are at novelty ~0; random directions far from the bank
    assert (res.novelty[:10] < 1e-2).all() and (res.novelty[10:] > 0.2).all()  # min 0.31
    assert (res.labels[:10] == bank.labels[:10].numpy()).all()


def test_head_round_trips_through_the_bank_file(tmp_path: Path) -> None:
    bank, raw = _head_bank()
    path = bank.save(tmp_path / 'head.npz', dtype='float32')
    back = FeatureBank.load(path)
    assert back.head is not None and back.head.whiten is not None
    assert back.head.fusion_weight == 0.3 and back.head.temperature == 2.0
    a, b = Classifier(bank).evaluate(raw[:7]), Classifier(back).evaluate(raw[:7])
    assert torch.allclose(a[0], b[0], atol=1e-5) and torch.allclose(a[1], b[1], atol=1e-5)
    with np.load(path, allow_pickle=False) as z:
        assert {'head_whiten', 'head_lda_coef', 'head_lda_bias'} <= set(z.files)
        assert z['head_whiten'].shape == (32, 32) and z['head_lda_coef'].shape == (5, 32)
    assert 'whitened vote + 0.3 x LDA' in back.summary()


def test_head_arrays_are_validated(tmp_path: Path) -> None:
    bank, _ = _head_bank()
    path = bank.save(tmp_path / 'head.npz', dtype='float32')
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays['head_whiten'] = arrays['head_whiten'][:3]
    np.savez(path, **arrays)
    with pytest.raises(BankError, match='head_whiten'):
        FeatureBank.load(path)


def test_format_1_bank_loads_as_the_plain_vote_with_a_log_line(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    bank, raw = _head_bank()
    path = bank.save(tmp_path / 'v1.npz', dtype='float32')
    with np.load(path, allow_pickle=False) as z:      # what a format-1 file holds
        arrays = {k: z[k] for k in z.files if not k.startswith('head_')}
    meta = json.loads(arrays['meta'].tobytes())
    meta['format_version'] = 1
    meta.pop('head')
    meta['unknown_calibration'] = {'threshold': 0.9}
    arrays['meta'] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(path, **arrays)
    with caplog.at_level(logging.WARNING):
        old = FeatureBank.load(path)
    assert 'no discriminant head' in caplog.text and 'point_gn bank build' in caplog.text
    assert old.head is None and old.classifier_head.is_plain_vote
    res = Classifier(old, unknown_threshold=-1).classify(raw[:6])
    shares = class_scores(old.transform(raw[:6]), old.features, old.labels, 5, old.gamma)
    np.testing.assert_allclose(res.probability, shares.numpy(), atol=1e-5)
    # a format-1 calibration thresholds the top vote share, as it always did
    assert ((res.labels == UNKNOWN) == (res.scores < 0.9)).all()
    meta['format_version'] = 7          # a future format: refused, naming the rebuild
    arrays['meta'] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(path, **arrays)
    with pytest.raises(BankError, match='point_gn bank build'):
        FeatureBank.load(path)


def test_cv_falls_back_to_the_vote_with_one_example_per_class() -> None:
    x, y, _, _ = _gaussians(1, classes=6)
    sel = select(x.float(), y.numpy(), 6, gammas=(5.0, 50.0))
    assert sel.fallback and 'no held-out data' in sel.fallback
    assert not sel.whiten_vote and sel.fusion_weight == 0 and sel.temperature == 1.0
    tf, head, bank = fit_selected(x.float(), y.numpy(), 6, sel)
    assert head.is_plain_vote
    pred = reference_head(head, tf(x.float()), ExactSearch(bank, y, 6))[0].argmax(1)
    assert torch.equal(pred, y)


def test_cv_shrinks_folds_for_few_shots() -> None:
    x, y, _, _ = _gaussians(3, classes=4)
    sel = select(x.float(), y.numpy(), 4, gammas=(5.0, 50.0))
    assert sel.folds_used == 3 and '3-fold' in sel.fallback
    assert sel.heldout_scores.shape == (12,)


def test_cv_picks_the_vote_when_lda_cannot_help() -> None:
    # Every class is two opposite clusters: all class means coincide, LDA is chance.
    g = torch.Generator().manual_seed(3)
    centres = 3 * torch.randn(4, 8, generator=g)
    y = torch.arange(4).repeat_interleave(40)
    sign = torch.tensor([1.0, -1.0]).repeat(80)[:, None]
    x = sign * centres[y] + 0.5 * torch.randn(160, 8, generator=g)
    sel = select(x, y.numpy(), 4, gammas=(5.0, 20.0, 50.0), standardize_options=('none',))
    assert sel.fusion_weight == 0 and sel.lda_alpha is None
    assert sel.cv_accuracy > 0.9


def test_cv_picks_the_head_when_a_nuisance_direction_dominates() -> None:
    # Classes differ along weak directions; a shared, strong within-class direction swamps
    # cosine similarity unless the covariance is whitened away.
    x, y, means, _ = _gaussians(60, seed=1, d=10)
    x = x - 0.5 * means[y]                       # halve the class separation
    g = torch.Generator().manual_seed(5)
    x = x + 15 * torch.randn(len(y), 1, generator=g, dtype=torch.float64) * torch.ones(10)
    sel = select(x.float(), y.numpy(), 4, gammas=(5.0, 20.0, 50.0, 200.0),
                 standardize_options=('none',))
    assert sel.whiten_vote or sel.fusion_weight > 0
    assert sel.cv_accuracy > sel.vote_cv_accuracy + 0.1      # measured 0.94 vs 0.82
    np.testing.assert_allclose(sel.heldout_scores, sel.heldout_scores.clip(0, 1))


def test_temperature_recovers_a_known_one() -> None:
    g = torch.Generator().manual_seed(0)
    s = 4 * torch.randn(20000, 5, generator=g, dtype=torch.float64)
    y = torch.multinomial(torch.softmax(s / 2.5, dim=1), 1, generator=g)[:, 0]
    t, loss = best_temperature(s, y.numpy())
    assert abs(t - 2.5) < 0.15 and np.isfinite(loss)


def test_calibrated_novelty_threshold_rejects_far_objects() -> None:
    bank, raw = _head_bank()
    bank.meta['unknown_calibration'] = calibrate_novelty(np.linspace(0, 0.2, 101), 0.05)
    clf = Classifier(bank, unknown_threshold=-1)
    assert clf.novelty_threshold == pytest.approx(0.19) and clf.unknown_threshold is None
    far = 5 * torch.randn(5, raw.shape[1], generator=torch.Generator().manual_seed(1))
    res = clf.classify(torch.cat([raw[:5], far]))
    assert (res.labels[:5] >= 0).all() and (res.labels[5:] == UNKNOWN).all()
    explicit = Classifier(bank, unknown_threshold=0.999).classify(raw[:5])
    assert ((explicit.labels == UNKNOWN) == (explicit.scores < 0.999)).all()


def test_plain_head_is_the_vote() -> None:
    z = torch.nn.functional.normalize(torch.randn(30, 8), dim=1)
    y = torch.arange(30) % 3
    prob, nov = reference_head(Head(10.0), z[:5], ExactSearch(z, y, 3))
    assert torch.allclose(prob, class_scores(z[:5], z, y, 3, 10.0), atol=1e-5)
    assert torch.allclose(nov, torch.zeros(5), atol=1e-5)


def test_classes_without_entries_get_probability_zero() -> None:
    x, y, _, _ = _gaussians(12, classes=3)
    sel = select(x.float(), y.numpy(), 5, gammas=(5.0, 50.0))       # classes 3, 4: empty
    tf, head, bank = fit_selected(x.float(), y.numpy(), 5, sel)
    prob, _ = reference_head(head, tf(x.float()), ExactSearch(bank, y, 5))
    assert torch.isfinite(prob).all() and (prob[:, 3:] < 1e-6).all()
    assert torch.allclose(prob.sum(1), torch.ones(len(y)), atol=1e-5)
    if head.lda_bias is not None:
        assert torch.isfinite(head.lda_bias).all()                  # storable


@pytest.mark.parametrize('n', [12, 300])        # low-rank (SVD) and full (eigh) paths
def test_lda_logits_in_coordinates_equal_the_stored_coefficients(n: int) -> None:
    x, y, _, _ = _gaussians(n // 4, d=20)
    z = torch.nn.functional.normalize(x.float(), dim=1)
    fit = CovarianceFit.fit(z, y, 4)
    for a in (0.05, 0.4):
        coef, bias = fit.lda(a)
        assert torch.allclose(fit.lda_logits(fit.coords(z), a).float(), z @ coef.T + bias,
                              rtol=1e-4, atol=1e-3)
        u = fit.whitened(fit.coords(z), a)
        g1 = torch.nn.functional.normalize(u, dim=1)
        g2 = torch.nn.functional.normalize(z @ fit.whitening(a), dim=1)
        assert torch.allclose(g1 @ g1.T, g2 @ g2.T, atol=1e-4)
