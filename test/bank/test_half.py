"""Float16 fitted matrices (format 5, bank/store.py): fitted rounded, exact in the file."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from point_gn_ros.bank.builder import fit_selected
from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.bank.enroll import BankFile, add_examples
from point_gn_ros.bank.store import decode, encode, round_matrix
from point_gn_ros.bank.refit import RefitPolicy
from point_gn_ros.bank.selection import select
from point_gn_ros.bank.store import FeatureBank, HALF_VERSION
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.errors import BankError

CFG = EncoderConfig()
C = 4
HALF = ('tf_projection', 'head_whiten', 'head_lda_precision')


def _raw(per_class: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Features (N, D) of C classes and their labels (N,).

    The classes are apart along 40 dims, with 10 loud shared directions on top (the
    whitening's case).
    """
    d = CFG.feature_dim
    means = torch.zeros(C, d)
    means[:, :40] = torch.randn(C, 40, generator=torch.Generator().manual_seed(7)) * 1.5
    loud = torch.linalg.qr(torch.randn(d, 10, generator=torch.Generator().manual_seed(8)))[0].T
    y = torch.arange(C).repeat_interleave(per_class)
    g = torch.Generator().manual_seed(seed)
    return (means[y] + 10 * torch.randn(len(y), 10, generator=g) @ loud
            + torch.randn(len(y), d, generator=g)), y


def _bank(matrix_dtype: str) -> FeatureBank:
    """PCA + whitened vote + wide LDA: every matrix stored in float16, fitted on 30 / class."""
    x, y = _raw(30, seed=1)
    sel = select(x, y.numpy(), C, gammas=(10.0, 40.0), standardize_options=('standardize',),
                 dims_options=(16,), alphas=(), folds=3)
    sel = replace(sel, alpha=0.1, whiten_vote=True, lda_alpha=0.5, lda_wide=True,
                  fusion_weight=0.5)             # fixed knobs: every matrix is there
    tf, head, rows = fit_selected(x, y.numpy(), C, sel, 'float16', matrix_dtype)
    meta = {'head': sel.head_meta(), 'stored_dtype': 'float16',
            'selection': {'grid': {'gammas': [10.0, 40.0], 'alphas': [0.1, 0.3],
                                   'weights': [0.5], 'lda_alphas': [0.5]}}}
    if matrix_dtype == 'float16':
        meta['matrix_dtype'] = 'float16'
    return BankFile.of(FeatureBank(rows, y, [f'c{i}' for i in range(C)], CFG, tf, sel.gamma,
                                   meta, head=head), 'float16').bank


@pytest.fixture(scope='module')
def half() -> FeatureBank:
    return _bank('float16')


def test_rounding_is_exact_in_the_file_and_unrounded_values_are_refused() -> None:
    g = torch.Generator().manual_seed(0)
    for scale in (1e-4, 1.0, 2.2e5):          # a wide LDA's precision reaches 2e5 > 65504
        t = torch.randn(64, 64, generator=g) * scale
        r = round_matrix(t)
        half, e = encode(r.numpy())
        assert half.dtype == np.float16 and np.array_equal(decode(half, e), r.numpy())
        rel = ((r - t).abs() / t.abs()).max()
        assert 0 < rel < 1e-3                  # float16's 11-bit mantissa, not a cast to 0/inf
    with pytest.raises(ValueError, match='not rounded'):
        encode(np.float32([[0.1, 0.2000001]]))


def test_half_bank_is_format_5_and_loads_back_bit_for_bit(half: FeatureBank,
                                                          tmp_path: Path) -> None:
    path = half.save(tmp_path / 'half.npz', dtype='float16')
    full = _bank('float32').save(tmp_path / 'full.npz', dtype='float16')
    with np.load(path, allow_pickle=False) as z:
        assert all(z[k].dtype == np.float16 for k in ('tf_projection', 'head_whiten_triu',
                                                       'head_lda_precision'))
    assert path.stat().st_size < 0.6 * full.stat().st_size
    back = FeatureBank.load(path)
    assert back.meta['format_version'] == HALF_VERSION
    assert torch.equal(back.features, half.features)
    assert torch.equal(back.transform.projection, half.transform.projection)
    assert torch.equal(back.head.whiten, half.head.whiten)
    assert torch.equal(back.head.lda_precision, half.head.lda_precision)
    q, yq = _raw(10, seed=2)
    a, b = Classifier(half).classify(q), Classifier(back).classify(q)
    assert np.array_equal(a.probability, b.probability) and np.array_equal(a.labels, b.labels)
    assert (a.labels == yq.numpy()).mean() > 0.75     # measured 0.875
    # The same knobs with float32 matrices: the same answers to float16's precision.
    f32 = Classifier(FeatureBank.load(full)).classify(q)
    np.testing.assert_allclose(a.probability, f32.probability, atol=2e-2)


def test_enrolled_half_bank_refits_on_rounded_matrices_and_reloads_exactly(
        half: FeatureBank, tmp_path: Path) -> None:
    new, _ = _raw(6, seed=3)
    # gamma 'cv': the refit re-chooses the knobs and re-fits the whitening (small bank).
    res = add_examples(BankFile.of(half, 'float16'), new[:6] + 0.5, 'mug',
                       policy=RefitPolicy(gamma='cv', folds=3))
    assert res.bank.head.whiten is not None and not torch.equal(res.bank.head.whiten,
                                                                 half.head.whiten)
    back = BankFile.load(res.file.save(tmp_path / 'taught.npz'))
    assert torch.equal(back.bank.head.whiten, res.bank.head.whiten)
    q, _ = _raw(5, seed=4)
    a, b = Classifier(res.bank).classify(q), Classifier(back.bank).classify(q)
    assert np.array_equal(a.probability, b.probability)


@pytest.mark.parametrize('change', ['no scale', 'float32 in format 5', 'float16 in format 4'])
def test_inconsistent_half_matrices_are_refused(half: FeatureBank, tmp_path: Path,
                                                change: str) -> None:
    path = half.save(tmp_path / 'half.npz', dtype='float16')
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays['meta'].tobytes())
    if change == 'no scale':
        del meta['matrix_scale_log2']['tf_projection']
    elif change == 'float32 in format 5':
        arrays['tf_projection'] = arrays['tf_projection'].astype(np.float32)
    else:
        meta['format_version'] = 4
    arrays['meta'] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(path, **arrays)
    with pytest.raises(BankError, match='tf_projection'):
        FeatureBank.load(path)
