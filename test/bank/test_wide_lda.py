"""Wide LDA (bank/model.py Head): the head's LDA on every standardised dim, chosen by CV.

Kept through the bank file and refitted in closed form by enrollment.
"""

from pathlib import Path

import numpy as np
import pytest
import torch

from point_gn_ros.bank.builder import fit_selected
from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.bank.enroll import BankFile, add_examples, remove_class
from point_gn_ros.bank.discriminant import lda_from_means, lda_noise_trace
from point_gn_ros.bank.refit import RefitPolicy
from point_gn_ros.bank.selection import select
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.errors import BankError

CFG = EncoderConfig()
D = CFG.feature_dim
CLASSES, PCA_DIMS = 5, 8


def _samples(centres: torch.Tensor, y: torch.Tensor, seed: int) -> torch.Tensor:
    """Rows centres[y] + 12 loud shared directions (they fill the PCA) + noise: (N, D)."""
    loud = torch.linalg.qr(torch.randn(D, 12, generator=torch.Generator().manual_seed(0)))[0].T
    g = torch.Generator().manual_seed(seed)
    return (centres[y] + 40 * torch.randn(len(y), 12, generator=g) @ loud
            + torch.randn(len(y), D, generator=g)).float()


def _data(per_class: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Classes apart only along 30 quiet dims -> raw features (N, D), labels (N,) int64."""
    centres = torch.zeros(CLASSES, D)
    centres[:, :30] = 1.5 * torch.randn(CLASSES, 30, generator=torch.Generator().manual_seed(1))
    y = torch.arange(CLASSES).repeat_interleave(per_class)
    return _samples(centres, y, seed), y


def _wide_bank() -> tuple[FeatureBank, object]:
    x, y = _data(40, seed=1)
    sel = select(x, y.numpy(), CLASSES, gammas=(10.0, 40.0), standardize_options=('none',),
                 dims_options=(PCA_DIMS,), alphas=(0.1,), weights=(0.5, 1.0, 2.0),
                 lda_alphas=(0.1, 0.5), wide_lda=True)
    tf, head, u = fit_selected(x, y.numpy(), CLASSES, sel)
    names = [f'c{i}' for i in range(CLASSES)]
    meta = {'head': sel.head_meta(), 'provenance': {'per_class': {n: 40 for n in names}}}
    bank = FeatureBank(u, y, names, CFG, tf, sel.gamma, meta, head=head)
    return bank, sel


@pytest.fixture(scope='module')
def wide() -> tuple[FeatureBank, object]:
    return _wide_bank()


def test_cv_picks_the_wide_lda_when_the_pca_drops_what_separates(wide) -> None:  # noqa: ANN001
    bank, sel = wide
    assert sel.lda_wide and sel.fusion_weight > 0
    narrow = select(*_data(40, seed=1)[:1], _data(40, seed=1)[1].numpy(), CLASSES,
                    gammas=(10.0, 40.0), standardize_options=('none',),
                    dims_options=(PCA_DIMS,), alphas=(0.1,), weights=(0.5, 1.0, 2.0),
                    lda_alphas=(0.1, 0.5))
    assert not narrow.lda_wide
    assert sel.cv_accuracy > narrow.cv_accuracy + 0.2     # measured 1.00 vs 0.55
    head = bank.head
    assert head.lda_wide and head.lda_coef.shape == (CLASSES, D)
    assert head.lda_precision.shape == (D, D) and head.lda_means.shape == (CLASSES, D)
    # held-out objects: the classifier reads the standardised rows
    xq, yq = _data(20, seed=2)
    res = Classifier(bank).classify(xq)
    assert (res.labels == yq.numpy()).mean() > 0.95
    np.testing.assert_allclose(res.probability.sum(1), 1, atol=1e-5)


def test_the_stored_precision_gives_the_fitted_lda(wide) -> None:  # noqa: ANN001
    head = wide[0].head
    counts = torch.bincount(wide[0].labels)
    coef, bias = lda_from_means(head.lda_means, head.lda_precision, counts)
    scale = float(head.lda_coef.abs().max())
    assert torch.allclose(coef, head.lda_coef, atol=1e-4 * scale)
    assert torch.allclose(bias, head.lda_bias, atol=1e-4 * float(head.lda_bias.abs().max()))


def test_wide_head_round_trips_and_is_validated(wide, tmp_path: Path) -> None:  # noqa: ANN001
    bank = wide[0]
    path = bank.save(tmp_path / 'wide.npz', dtype='float32')
    back = FeatureBank.load(path)
    assert back.head.lda_wide and torch.equal(back.head.lda_precision, bank.head.lda_precision)
    xq, _ = _data(10, seed=3)
    a, b = Classifier(bank).classify(xq), Classifier(back).classify(xq)
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_allclose(a.probability, b.probability, atol=1e-6)   # rows re-normalised
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    assert arrays['head_lda_precision'].shape == (D * (D + 1) // 2,)
    del arrays['head_lda_precision']
    np.savez(tmp_path / 'broken.npz', **arrays)
    with pytest.raises(BankError, match='wide-LDA head needs'):
        FeatureBank.load(tmp_path / 'broken.npz')


def test_enrollment_refits_the_wide_lda_in_closed_form(wide, tmp_path: Path) -> None:  # noqa: ANN001
    bank = wide[0]
    bf = BankFile.of(bank, 'float32')
    # a new class apart along other quiet dims
    centre = torch.zeros(1, D)
    centre[0, 30:60] = 1.5 * torch.randn(30, generator=torch.Generator().manual_seed(7))
    new = _samples(centre, torch.zeros(40, dtype=torch.int64), seed=8)
    keep = RefitPolicy(gamma='keep')        # knobs kept: the closed-form path of big banks
    res = add_examples(bf, new, 'mug', source='test', policy=keep)
    head = res.bank.head
    assert head.lda_wide and head.lda_coef.shape == (CLASSES + 1, D)
    assert torch.equal(head.lda_precision, bank.head.lda_precision)     # covariance kept
    expect = bank.transform.standardized(new).mean(0)
    assert torch.allclose(head.lda_means[-1], expect, atol=1e-6)
    queries = _samples(centre, torch.zeros(10, dtype=torch.int64), seed=9)
    assert (Classifier(res.bank).classify(queries).labels == CLASSES).all()
    # save + restart + load: the same answers, bit for bit
    back = BankFile.load(res.file.save(tmp_path / 'taught.npz'))
    assert torch.equal(back.bank.head.lda_coef, head.lda_coef)
    assert torch.equal(back.bank.head.lda_means, head.lda_means)
    np.testing.assert_array_equal(Classifier(res.bank).classify(queries).probability,
                                  Classifier(back.bank).classify(queries).probability)
    # forget it: the bank's LDA is back (means and coefficients of the built classes)
    gone = remove_class(res.file, 'mug', policy=keep).bank.head
    assert torch.equal(gone.lda_means, bank.head.lda_means)
    scale = float(bank.head.lda_coef.abs().max())
    assert torch.allclose(gone.lda_coef, bank.head.lda_coef, atol=1e-4 * scale)


def test_debias_lifts_only_the_taught_class_by_the_mean_noise(wide) -> None:  # noqa: ANN001
    bank = wide[0]
    head = bank.head
    # the stored trace is the one the kept precision implies
    alpha = float(bank.meta['head']['lda_alpha'])
    assert head.lda_trace > 0
    assert abs(lda_noise_trace(head.lda_precision, alpha) - head.lda_trace) < 1e-3 * head.lda_trace
    new = _samples(torch.zeros(1, D), torch.zeros(5, dtype=torch.int64), seed=11)
    runs = {f: add_examples(BankFile.of(bank, 'float32'), new, 'mug',
                            policy=RefitPolicy(gamma='keep', lda_debias=f)).bank.head
            for f in (0.0, 0.5)}
    lift = runs[0.5].lda_bias - runs[0.0].lda_bias
    assert torch.allclose(lift[:CLASSES], torch.zeros(CLASSES))          # built: untouched
    assert abs(float(lift[CLASSES]) - 0.5 * head.lda_trace / (2 * 5)) < 1e-3 * head.lda_trace
    with pytest.raises(ValueError, match='lda_debias'):
        RefitPolicy(lda_debias=2.5)


def test_steal_budget_gives_each_taught_class_its_own_share(wide) -> None:  # noqa: ANN001
    """A class taught on top of a built one gets less of the correction than a distinct one."""
    bank = wide[0]
    head = bank.head
    x, y = _data(40, seed=1)
    near = x[y == 0][:5]            # five of class 0's own rows: inside its spread
    far = torch.zeros(1, D)
    far[0, 30:60] = 1.5 * torch.randn(30, generator=torch.Generator().manual_seed(7))
    far = _samples(far, torch.zeros(5, dtype=torch.int64), seed=13)

    def taught(policy: RefitPolicy):  # noqa: ANN202
        bf = add_examples(BankFile.of(bank, 'float32'), near, 'near', policy=policy).file
        return add_examples(bf, far, 'far', policy=policy)

    res = taught(RefitPolicy(gamma='keep', lda_debias=2.0, lda_steal_budget=0.01))
    shares = res.bank.meta['refit']['lda_debias_shares']
    assert set(shares) == {'near', 'far'} and 0 <= shares['near'] < shares['far'] == 2.0
    loose = taught(RefitPolicy(gamma='keep', lda_debias=2.0, lda_steal_budget=0.5))
    assert loose.bank.meta['refit']['lda_debias_shares']['near'] > shares['near']
    plain = taught(RefitPolicy(gamma='keep'))
    lift = (res.bank.head.lda_bias - plain.bank.head.lda_bias).double()
    assert torch.allclose(lift[:CLASSES], torch.zeros(CLASSES, dtype=torch.float64), atol=1e-3)
    for name, f in shares.items():
        c = res.bank.class_names.index(name)
        assert abs(float(lift[c]) - f * head.lda_trace / (2 * 5)) < 1e-3 * head.lda_trace
