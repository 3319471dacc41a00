"""The head's kernel ridge term: fit, enrollment steps, file, classifier."""

from dataclasses import replace
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from point_gn_ros.bank.builder import fit_selected
from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.bank.discriminant import fit_ridge
from point_gn_ros.bank.enroll import BankFile, add_examples, remove_class
from point_gn_ros.bank.live import LiveBank
from point_gn_ros.bank.refit import RefitPolicy, active_view
from point_gn_ros.bank.selection import select
from point_gn_ros.bank.store import FeatureBank, RIDGE_VERSION
from point_gn_ros.bank.vote import ridge_scores
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.errors import BankError

C, D = 5, 1620


def _unit(n: int, d: int = 16, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(n, d, generator=g), dim=1)


def _raw(labels: torch.Tensor, seed: int = 0) -> torch.Tensor:
    """Positive encoder-like features (N, D): class means 0.1 apart in units of the noise."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(C, D, generator=torch.Generator().manual_seed(99)) * 0.12
    return (3 + means[labels] + torch.randn(len(labels), D, generator=g)).abs()


def _ridge_bank(dtype: str = 'int4') -> tuple[FeatureBank, torch.Tensor]:
    """A CV-chosen head with a ridge term of fixed knobs, rows as a `dtype` file holds them."""
    y = torch.arange(C).repeat_interleave(40)
    x = _raw(y)
    sel = select(x, y.numpy(), C, standardize_options=('standardize',), dims_options=(32,),
                 folds=3)
    sel = replace(sel, alpha=0.1, whiten_vote=True, ridge_gamma=1.0, ridge_lambda=0.01,
                  ridge_weight=30.0, temperature=2.0)
    tf, head, rows = fit_selected(x, y.numpy(), C, sel, dtype)
    bank = FeatureBank(rows, y, [f'c{i}' for i in range(C)], EncoderConfig(), tf, sel.gamma,
                       meta={'head': {**sel.head_meta(),
                                      'ridge': {'stored_dtype': dtype, 'temperature': 2.0,
                                                'temperature_without': 0.5}},
                             'stored_dtype': dtype}, head=head)
    return bank, _raw(torch.arange(C).repeat(3), seed=1)


def test_fit_solves_the_regularised_kernel_system() -> None:
    rows, y = _unit(50), torch.arange(50) % 4
    a = fit_ridge(rows, y, 4, gamma=1.5, lam=0.05).double()
    k = torch.exp(1.5 * (rows.double() @ rows.double().T - 1))
    residual = (k + 0.05 * torch.eye(50, dtype=torch.float64)) @ a \
        - torch.nn.functional.one_hot(y, 4).double()
    assert float(residual.abs().max()) < 1e-5
    # The scores of the bank's own rows nearly reproduce their labels.
    s = ridge_scores(rows @ rows.T, a.float(), 1.5)
    assert (s.argmax(1) == y).all()


def test_ridge_bank_round_trips_bit_for_bit_and_is_versioned(tmp_path: Path) -> None:
    bank, q = _ridge_bank()
    path = bank.save(tmp_path / 'ridge.npz', dtype='int4')
    back = FeatureBank.load(path)
    assert back.meta['format_version'] == RIDGE_VERSION
    assert torch.equal(back.features, bank.features)   # fitted on the stored rows
    assert torch.equal(back.head.ridge_coef, bank.head.ridge_coef)
    assert torch.equal(back.head.whiten, bank.head.whiten)
    with np.load(path, allow_pickle=False) as z:    # format 4: a symmetric whitening halved
        assert {'head_ridge_coef', 'head_whiten_triu'} <= set(z.files)
        assert 'head_whiten' not in z.files
    assert (back.head.ridge_gamma, back.head.ridge_lambda, back.head.ridge_weight) == \
        (1.0, 0.01, 30.0)
    a, b = Classifier(bank).evaluate(q), Classifier(back).evaluate(q)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    torch.testing.assert_close(a[0].sum(1), torch.ones(len(q)))
    # The ridge term changes the answer (else this test would pass without it).
    plain = Classifier(replace(bank, head=replace(bank.head, ridge_weight=0.0))).evaluate(q)
    assert not torch.allclose(plain[0], a[0], atol=1e-3)
    assert '+ 30 x kernel ridge' in back.summary()
    assert 'kernel ridge' in '\n'.join(__import__(
        'point_gn_ros.commands.bank_cmd', fromlist=['x']).describe_selection(back.meta))


def test_a_ridge_bank_is_not_saved_in_another_dtype(tmp_path: Path) -> None:
    bank, _ = _ridge_bank('int4')
    with pytest.raises(ValueError, match='fitted on rows stored as int4'):
        bank.save(tmp_path / 'f16.npz', dtype='float16')


def test_ridge_arrays_are_validated(tmp_path: Path) -> None:
    bank, _ = _ridge_bank()
    path = bank.save(tmp_path / 'ridge.npz', dtype='int4')
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    for name, value, match in (('head_ridge_coef', arrays['head_ridge_coef'][:5],
                                'head_ridge_coef'),
                               ('head_ridge_coef', None, 'come together')):
        broken = dict(arrays)
        if value is None:
            del broken[name]
        else:
            broken[name] = value
        np.savez(tmp_path / 'bad.npz', **broken)
        with pytest.raises(BankError, match=match):
            FeatureBank.load(tmp_path / 'bad.npz')


def test_ridge_head_always_searches_exactly() -> None:
    bank, q = _ridge_bank()
    clf = Classifier(bank, search='indexed')
    assert clf.search_kind == 'exact'
    assert Classifier(replace(bank, head=replace(bank.head, ridge_weight=0.0)),
                      search='indexed').search_kind == 'indexed'


def test_every_enrollment_publishes_the_ridge_term_fitted() -> None:
    bank, q = _ridge_bank()
    new = _raw(torch.zeros(8, dtype=torch.int64), seed=5) + 0.4 * torch.rand(D)
    res = add_examples(BankFile.of(bank), new, 'mine', policy=RefitPolicy(gamma='keep'))
    fb = res.file.bank
    assert fb.head.has_ridge and fb.head.temperature == bank.head.temperature
    assert 'pending' not in fb.meta['head']['ridge']
    assert fb.meta['refit']['ridge'] == 'refitted in full'
    assert torch.equal(fb.head.ridge_coef, fit_ridge(fb.features, fb.labels, C + 1, 1.0, 0.01))


def test_full_policy_refits_and_save_restart_answers_the_same(tmp_path: Path) -> None:
    bank, q = _ridge_bank()
    new = _raw(torch.zeros(8, dtype=torch.int64), seed=5) + 0.4 * torch.rand(D)
    full = RefitPolicy(min_examples=1, gamma='keep')
    res = add_examples(BankFile.of(bank), new, 'mine', policy=full)
    fb = res.file.bank
    assert fb.head.ridge_coef.shape == (len(bank) + 8, C + 1)
    assert torch.equal(fb.head.ridge_coef, fit_ridge(fb.features, fb.labels, C + 1, 1.0, 0.01))
    probe = torch.cat([q, new[:3]])
    before = Classifier(fb).evaluate(probe)
    assert (before[0][len(q):].argmax(1) == C).all()     # the taught class is predicted
    back = FeatureBank.load(res.file.save(tmp_path / 'enrolled.npz'))
    after = Classifier(back).evaluate(probe)
    assert torch.equal(before[0], after[0]) and torch.equal(before[1], after[1])
    gone = remove_class(BankFile.load(tmp_path / 'enrolled.npz'), 'mine', policy=full)
    # The class's rows and column go; the refit on the built rows gives the built ones again.
    assert torch.equal(gone.file.bank.head.ridge_coef, bank.head.ridge_coef)


def test_live_bank_publishes_versions_with_the_ridge_fitted(tmp_path: Path) -> None:
    bank, q = _ridge_bank()
    live = LiveBank(BankFile.of(bank), Classifier, RefitPolicy(gamma='keep'))
    new = _raw(torch.zeros(8, dtype=torch.int64), seed=5) + 0.4 * torch.rand(D)
    res = live.add(new, 'mine', 'test')
    snap = live.current()
    assert snap.version == res.version and snap.bank.head.has_ridge
    assert torch.equal(snap.bank.head.ridge_coef,
                       fit_ridge(snap.bank.features, snap.bank.labels, C + 1, 1.0, 0.01))
    assert (snap.model.evaluate(new[:3])[0].argmax(1) == C).all()
    # what the node answers is what the saved file answers once loaded
    back = FeatureBank.load(res.file.save(tmp_path / 'enrolled.npz'))
    probe = torch.cat([q, new[:3]])
    assert torch.equal(Classifier(back).evaluate(probe)[0], snap.model.evaluate(probe)[0])


def test_a_file_with_its_ridge_refit_pending_loads_fitted(tmp_path: Path) -> None:
    """An older writer could save an enrollment's ridge term unfitted (marked pending)."""
    bank, q = _ridge_bank()
    new = _raw(torch.zeros(8, dtype=torch.int64), seed=5) + 0.4 * torch.rand(D)
    fitted = add_examples(BankFile.of(bank), new, 'mine', policy=RefitPolicy(gamma='keep'))
    fb = fitted.file.bank
    meta = json.loads(json.dumps(fb.meta))
    meta['head']['ridge'].update(pending=True, weight=0.0, weight_pending=fb.head.ridge_weight,
                                 temperature=fb.head.temperature, gamma=fb.head.ridge_gamma,
                                 **{'lambda': fb.head.ridge_lambda})
    legacy = replace(fb, meta=meta, head=replace(fb.head, ridge_coef=None, ridge_weight=0.0,
                                                 temperature=0.5))
    path = legacy.save(tmp_path / 'pending.npz', dtype='float32')
    back = FeatureBank.load(path)
    assert back.head.has_ridge and back.head.temperature == fb.head.temperature
    assert 'pending' not in back.meta['head']['ridge']
    assert torch.equal(back.head.ridge_coef, fit_ridge(back.features, back.labels, C + 1, 1.0,
                                                       0.01))
    probe = torch.cat([q, new[:3]])
    # fitted on the loaded (re-normalised) rows: the same answers up to that rounding
    loaded, fitted = Classifier(back).evaluate(probe)[0], Classifier(fb).evaluate(probe)[0]
    torch.testing.assert_close(loaded, fitted, atol=1e-4, rtol=0)
    assert torch.equal(loaded.argmax(1), fitted.argmax(1))


def test_active_view_keeps_rows_and_ridge_coefficients_aligned() -> None:
    bank, _ = _ridge_bank()
    res = add_examples(BankFile.of(bank), _raw(torch.zeros(2, dtype=torch.int64), seed=7),
                       'few', policy=RefitPolicy(min_examples=3))
    view = active_view(res.file.bank, 3)
    assert len(view) == len(bank) and view.head.ridge_coef.shape[0] == len(bank)
    Classifier(view).evaluate(_raw(torch.arange(2), seed=8))
