"""Feature bank file: round trip, validation and every corruption/mismatch error."""

import json
from pathlib import Path
import zipfile

import numpy as np
import pytest
import torch

from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.errors import BankError
from point_gn_ros.bank.model import FeatureTransform


def _bank(n: int = 30, classes: int = 3, dims: int | None = None) -> FeatureBank:
    cfg = EncoderConfig()
    raw = torch.randn(n, cfg.feature_dim)
    tf = FeatureTransform.fit(raw, 'standardize', dims)
    return FeatureBank(features=tf(raw), labels=torch.arange(n) % classes,
                       class_names=[f'c{i}' for i in range(classes)], config=cfg,
                       transform=tf, gamma=50.0, meta={'provenance': {'dataset': 'x'}})


@pytest.mark.parametrize('dtype', ['float16', 'float32', 'int8', 'int4'])
@pytest.mark.parametrize('dims', [None, 16, 15])
def test_round_trip(tmp_path: Path, dtype: str, dims: int | None) -> None:
    bank = _bank(dims=dims)
    path = bank.save(tmp_path / 'b.npz', dtype=dtype)
    back = FeatureBank.load(path, expected_config=EncoderConfig())
    assert back.class_names == bank.class_names and back.gamma == 50.0
    assert back.config == bank.config
    assert torch.equal(back.labels, bank.labels)
    tol = {'float16': 2e-3, 'float32': 1e-6, 'int8': 1e-2, 'int4': 8e-2}[dtype]
    assert torch.allclose(back.features, bank.features, atol=tol)
    assert float((back.features * bank.features).sum(1).min()) > 1 - tol
    x = torch.randn(4, EncoderConfig().feature_dim)
    assert torch.allclose(back.transform(x), bank.transform(x), atol=1e-5)
    assert back.meta['stored_dtype'] == dtype and back.meta['encoder_version'] == 1
    assert 'x' in back.summary()


def test_int4_packs_two_values_a_byte_exactly_and_restores_idempotently(tmp_path: Path) -> None:
    from point_gn_ros.bank.store import pack_int4, to_stored, unpack_int4
    q = np.random.default_rng(0).integers(-7, 8, (5, 9)).astype(np.int8)
    packed = pack_int4(q)
    assert packed.shape == (5, 5) and packed.dtype == np.uint8
    assert np.array_equal(unpack_int4(packed, 9), q)
    bank = _bank(dims=15)
    stored = to_stored(bank.features, 'int4')
    assert stored.nbytes == len(bank) * 8                     # an eighth of float32, padded
    back = FeatureBank.load(bank.save(tmp_path / 'b.npz', dtype='int4'))
    assert np.array_equal(to_stored(back.features, 'int4'), stored)   # saving again: same bytes


def test_int4_bank_with_the_wrong_row_width_is_refused(tmp_path: Path) -> None:
    path = _bank(dims=16).save(tmp_path / 'b.npz', dtype='int4')
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays['features'] = arrays['features'][:, :7]
    np.savez(path, **arrays)
    with pytest.raises(BankError, match='int4 features have 7 bytes a row, 16 dims need 8'):
        FeatureBank.load(path)


def test_load_never_unpickles(tmp_path: Path) -> None:
    path = tmp_path / 'evil.npz'
    np.savez(path, features=np.array([{'a': 1}], dtype=object), labels=np.zeros(1),
             tf_mean=np.zeros(1), tf_scale=np.ones(1), meta=np.zeros(1, np.uint8))
    with pytest.raises(BankError, match='evil.npz'):
        FeatureBank.load(path)


def _rewrite(path: Path, **changes) -> None:
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays['meta'].tobytes())
    for key, value in changes.items():
        if key.startswith('meta_'):
            meta[key[5:]] = value
        elif value is None:
            arrays.pop(key)
        else:
            arrays[key] = value
    arrays['meta'] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(path, **arrays)


@pytest.mark.parametrize('changes, message', [
    ({'features': None}, 'missing arrays'),
    ({'meta_encoder_version': 999}, 'encoder version'),
    ({'meta_format_version': 7}, 'format version'),
    ({'labels': np.zeros(5, np.int32)}, 'labels must be'),
    ({'labels': np.full(30, 9, np.int32)}, 'out of range'),
    ({'features': np.full((30, 1620), np.nan, np.float32)}, 'non-finite'),
    ({'features': np.zeros((30, 1620), np.int32)}, 'float16/float32'),
    ({'tf_mean': np.zeros(10, np.float32)}, 'transform expects'),
    ({'tf_scale': np.zeros(1620, np.float32)}, 'positive'),
    ({'meta_gamma': -1}, 'gamma'),
    ({'meta_encoder_config': {'sigma': 0.4, 'bogus': 1}}, 'incomplete metadata'),
])
def test_each_corruption_gives_one_clear_error(tmp_path: Path, changes: dict,
                                               message: str) -> None:
    path = _bank().save(tmp_path / 'bank.npz', dtype='float32')
    _rewrite(path, **changes)
    with pytest.raises(BankError, match=message) as err:
        FeatureBank.load(path)
    assert str(path) in str(err.value)


def test_truncated_file(tmp_path: Path) -> None:
    path = _bank().save(tmp_path / 'bank.npz')
    path.write_bytes(path.read_bytes()[:2000])
    with pytest.raises(BankError, match='truncated'):
        FeatureBank.load(path)


def test_garbage_metadata(tmp_path: Path) -> None:
    path = _bank().save(tmp_path / 'bank.npz')
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays['meta'] = np.frombuffer(b'\xff{not json', np.uint8)
    np.savez(path, **arrays)
    with pytest.raises(BankError, match='JSON'):
        FeatureBank.load(path)


def test_missing_file_and_not_a_zip(tmp_path: Path) -> None:
    with pytest.raises(BankError, match='not found'):
        FeatureBank.load(tmp_path / 'nope.npz')
    (tmp_path / 'text.npz').write_text('hello')
    with pytest.raises(BankError, match='text.npz'):
        FeatureBank.load(tmp_path / 'text.npz')
    assert not zipfile.is_zipfile(tmp_path / 'text.npz')


def test_mismatched_encoder_configuration(tmp_path: Path) -> None:
    path = _bank().save(tmp_path / 'bank.npz')
    with pytest.raises(BankError, match='sigma'):
        FeatureBank.load(path, expected_config=EncoderConfig(sigma=0.3))
