"""Incremental search index: an enrollment's index derived from the previous version's.

A derived index must be exactly the index built afresh on the same bank version with the same
basis (rotation, scales): same codes, same candidates, same votes and probabilities.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.bank.enroll import BankFile, add_examples, remove_class
from point_gn_ros.bank.refit import RefitPolicy
from point_gn_ros.bank.discriminant import fit_head
from point_gn_ros.bank.live import LiveBank
from point_gn_ros.bank.index import BASIS_DRIFT, BankIndex, IndexedSearch, _project
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.bank.model import FeatureTransform
from point_gn_ros.commands.bench_cmd import synthetic_bank
from point_gn_ros.core import kernels
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.bank.vote import CompiledHead

D = EncoderConfig().feature_dim
DIMS = 96
needs_kernels = pytest.mark.skipif(kernels.load() is None, reason='no C compiler')


def _rows(n: int, seed: int, classes: int = 8) -> tuple[np.ndarray, np.ndarray]:
    return synthetic_bank(n, DIMS, seed=seed, classes=classes)


def _same_index(a: BankIndex, b: BankIndex, queries: np.ndarray) -> None:
    assert np.array_equal(a.codes, b.codes) and np.array_equal(a.labels, b.labels)
    assert np.array_equal(a.features, b.features) and a.num_classes == b.num_classes
    for q in queries:
        assert np.array_equal(np.sort(a.candidates_for(q)), np.sort(b.candidates_for(q)))
    for q in queries:
        rows = np.sort(a.candidates_for(q))
        assert np.array_equal(a.dots(q, rows), b.dots(q, rows))


@needs_kernels
def test_projection_of_a_row_does_not_depend_on_the_batch() -> None:
    feats, _ = _rows(1_000, seed=1)
    rot = np.linalg.qr(np.random.default_rng(0).normal(size=(DIMS, 64)))[0].astype(np.float32)
    lib = kernels.load()
    full = _project(feats, rot, lib)
    np.testing.assert_allclose(full, feats @ rot, atol=1e-5)
    for start, m in ((0, 1), (5, 2), (17, 7), (990, 10), (333, 64)):
        assert np.array_equal(_project(feats[start:start + m], rot, lib), full[start:start + m])


@needs_kernels
def test_appended_rows_give_the_fresh_index_on_the_same_basis() -> None:
    feats, labels = _rows(4_000, seed=2)
    base = BankIndex(feats, labels, 8, candidates=256)
    new, _ = _rows(20, seed=3)
    feats2 = np.concatenate([feats, new])
    labels2 = np.concatenate([labels, np.full(20, 8)])              # a new class
    derived = base.derive(feats2, labels2, 9)
    assert derived is not None and derived.basis is base.basis and derived.changed == 20
    fresh = BankIndex(feats2, labels2, 9, candidates=256, basis=base.basis)
    _same_index(derived, fresh, np.concatenate([new[:5], feats[:5]]))
    # the new class is found by its own examples, like the float32 search finds it
    assert all(derived.labels[rows[np.argmax(derived.dots(q, rows))]] == 8
               for q in new for rows in [derived.candidates_for(q)])
    # more rows of an existing class chain on the same basis
    more, _ = _rows(10, seed=4)
    feats3 = np.concatenate([feats2, more])
    labels3 = np.concatenate([labels2, np.full(10, 3)])
    again = derived.derive(feats3, labels3, 9)
    assert again is not None and again.changed == 30
    _same_index(again, BankIndex(feats3, labels3, 9, candidates=256, basis=base.basis),
                more[:4])


@needs_kernels
def test_removed_class_gives_the_fresh_index_on_the_same_basis() -> None:
    feats, labels = _rows(4_000, seed=5)
    base = BankIndex(feats, labels, 8, candidates=256)
    small = labels == 2
    # removal is checked on the data: rows of a class of the right size, labels shifted
    labels_small = labels.copy()
    labels_small[np.flatnonzero(small)[40:]] = 3                    # class 2: 40 entries
    base = BankIndex(feats, labels_small, 8, candidates=256)
    keep = labels_small != 2
    kept = labels_small[keep]
    derived = base.derive(feats[keep], kept - (kept > 2), 7)
    assert derived is not None and derived.changed == 40
    fresh = BankIndex(feats[keep], kept - (kept > 2), 7, candidates=256, basis=base.basis)
    _same_index(derived, fresh, feats[:6])


@needs_kernels
def test_rows_that_moved_or_drifted_far_get_a_fresh_index() -> None:
    feats, labels = _rows(2_000, seed=6)
    base = BankIndex(feats, labels, 8, candidates=128)
    moved = feats.copy()
    moved[7] = -moved[7]                             # e.g. a refit re-whitened the rows
    assert base.derive(moved, labels, 8) is None
    assert base.derive(feats, np.roll(labels, 1), 8) is None
    assert base.derive(feats[:-5], labels[:-5], 8) is None          # not a whole class
    many, _ = _rows(int(BASIS_DRIFT * 2_000) + 1, seed=7)
    grown = np.concatenate([feats, many])
    assert base.derive(grown, np.concatenate([labels, np.zeros(len(many), int)]), 8) is None
    # IndexedSearch falls back to a fresh build (its own basis), and says so
    prev = IndexedSearch(torch.from_numpy(feats), torch.from_numpy(labels), 8)
    nxt = IndexedSearch.derive(prev, torch.from_numpy(moved), torch.from_numpy(labels), 8)
    assert not nxt.derived and nxt.index.basis is not prev.index.basis


def _head_bank(n: int = 6_000) -> FeatureBank:
    feats, labels = synthetic_bank(n, DIMS, seed=0, classes=8)
    z, y = torch.from_numpy(feats), torch.from_numpy(labels)
    h = fit_head(z, y, 8, gamma=50.0, alpha=0.3, lda_alpha=0.1, fusion_weight=0.2,
                 temperature=2.0)
    tf = FeatureTransform(torch.zeros(D), torch.ones(D), torch.eye(D)[:, :DIMS].contiguous())
    return FeatureBank(h.vote_space(z), y, [f'c{i}' for i in range(8)], EncoderConfig(), tf,
                       50.0, {'head': {'alpha': 0.3, 'lda_alpha': 0.1}}, head=h)


def _raw(rows: np.ndarray) -> torch.Tensor:
    out = torch.zeros(len(rows), D)
    out[:, :DIMS] = torch.from_numpy(rows)
    return out


@needs_kernels
def test_enrollment_versions_classify_as_a_fresh_build_on_the_same_basis() -> None:
    """The node's path: LiveBank add / remove with the model derived from the previous one.

    The default refit keeps the section's whitening on a bank this large (gamma 'auto' does
    not run CV above 2,000 entries): stored rows do not move, so every version derives.
    """
    def make(bank: FeatureBank) -> Classifier:
        return Classifier(bank, search='indexed')

    def derive(bank: FeatureBank, prev: Classifier) -> Classifier:
        return Classifier(bank, search='indexed', previous=prev)

    live = LiveBank(BankFile.of(_head_bank(), 'float32'), make, RefitPolicy(), derive)
    basis = live.current().model.search.index.basis
    rng = np.random.default_rng(8)
    scale = ((1.0 + np.arange(DIMS)) ** -0.6).astype(np.float32)
    centre = rng.standard_normal(DIMS).astype(np.float32) * scale
    q_new = _raw(centre + 0.2 * rng.normal(size=(6, DIMS)).astype(np.float32) * scale)
    q_old = _raw(synthetic_bank(6_000, DIMS, seed=0, classes=8)[0][:6])
    steps = [lambda: live.add(_raw(centre + 0.2 * rng.normal(size=(20, DIMS)).astype(
                 np.float32) * scale), 'mug', 'test'),
             lambda: live.add(_raw(centre + 0.2 * rng.normal(size=(5, DIMS)).astype(
                 np.float32) * scale), 'c1', 'test'),
             lambda: live.add(_raw(rng.normal(size=(10, DIMS)).astype(np.float32) * scale),
                              'cup', 'test'),
             lambda: live.remove('cup', 'test')]
    for step in steps:
        res = step()
        assert res.refit['gamma_reason'].startswith('kept')
        clf = live.current().model
        assert clf.search.derived and clf.search.index.basis is basis
        ref = Classifier(res.bank, search='exact')          # same head, any search object
        ref.search = IndexedSearch(ref.features, ref.labels, res.bank.num_classes,
                                   basis=basis)
        ref.compiled_head = CompiledHead.build(ref.transform, ref.head, res.bank.num_classes,
                                               ref.search)
        q = torch.cat([q_new, q_old])
        a, b = clf.classify(q), ref.classify(q)
        assert np.array_equal(a.labels, b.labels) and np.array_equal(a.probability,
                                                                     b.probability)
        assert np.array_equal(a.novelty, b.novelty)
        fresh = Classifier(res.bank, search='indexed').classify(q)  # its own basis
        assert np.array_equal(a.labels, fresh.labels)
    assert (live.current().model.classify(q_new).labels ==
            live.current().bank.class_names.index('mug')).all()
    # removing a large class moves the bank more than BASIS_DRIFT: a fresh basis
    live.remove('c3', 'test')
    assert not live.current().model.search.derived


@needs_kernels
def test_a_two_section_enrollment_derives_the_scan_index() -> None:
    bank = _head_bank(3_000)
    two = replace(bank, views=_head_bank(6_000), gate=None)
    bf = BankFile.of(two, 'float32').with_stats()
    prev = Classifier(bf.bank, search='indexed')
    res = add_examples(bf, _raw(_rows(4, seed=9)[0]), 'mug', 'test')
    clf = Classifier(res.bank, search='indexed', previous=prev)
    assert clf.search.derived and clf.views is not None and clf.views.search.derived
    res2 = remove_class(res.file, 'mug', 'test')
    assert Classifier(res2.bank, search='indexed', previous=clf).views.search.derived
