"""Enrollment core: add / remove / refit, copy-on-write, exact save + load, thread safety."""

from __future__ import annotations

from dataclasses import replace
import os
from pathlib import Path
import signal
import subprocess
import sys
import threading
import time

from unittest import mock

import numpy as np
import pytest
import torch

from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.bank.enroll import (BankFile, EnrollError, add_examples, bank_version,
                                      class_counts, remove_class)
from point_gn_ros.bank.refit import RefitPolicy, active_view, refit
from point_gn_ros.bank.live import LiveBank
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.bank.model import FeatureTransform
from point_gn_ros.core.config import EncoderConfig

D = EncoderConfig().feature_dim


def _clusters(classes: int, per_class: int, seed: int = 0, spread: float = 0.3
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Raw features of well-separated Gaussian classes: (N, D), labels (N,), centres (C, D)."""
    g = torch.Generator().manual_seed(seed)
    centres = torch.randn(classes, D, generator=g)
    labels = torch.arange(classes).repeat_interleave(per_class)
    feats = centres[labels] + spread * torch.randn(len(labels), D, generator=g)
    return feats, labels, centres


def _bank(classes: int = 4, per_class: int = 10, dtype: str = 'float16') -> tuple[BankFile,
                                                                                  torch.Tensor]:
    feats, labels, centres = _clusters(classes, per_class)
    tf = FeatureTransform.fit(feats, 'standardize')
    bank = FeatureBank(features=tf(feats), labels=labels,
                       class_names=[f'c{i}' for i in range(classes)], config=EncoderConfig(),
                       transform=tf, gamma=50.0,
                       meta={'unknown_calibration': {'threshold': 0.5, 'false_reject_rate': 0.05,
                                                     'method': 'test'}})
    return BankFile.of(bank, dtype), centres


def _queries(centre: torch.Tensor, n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return centre + 0.3 * torch.randn(n, D, generator=g)


def test_add_new_class_is_predicted_and_old_bank_untouched() -> None:
    bf, _ = _bank()
    before = bf.bank.features.clone()
    new_centre = torch.randn(D, generator=torch.Generator().manual_seed(99))
    res = add_examples(bf, _queries(new_centre, 5, 1), 'mug', source='test')
    assert res.new_class and res.count == 5 and res.version == 1
    assert res.bank.class_names[-1] == 'mug' and class_counts(res.bank)['mug'] == 5
    # Copy-on-write: the old bank is exactly as it was.
    assert torch.equal(bf.bank.features, before) and bf.bank.num_classes == 4
    assert bank_version(bf.bank) == 0
    pred = Classifier(res.bank).classify(_queries(new_centre, 20, 2)).labels
    assert (pred == 4).all()
    log = [e.to_json() for e in res.bank.enrollments]
    assert log == [{'version': 1, 'action': 'add', 'class': 'mug', 'count': 5,
                    'time': log[0]['time'], 'source': 'test', 'near_duplicates': 0}]


def test_more_examples_of_an_existing_class() -> None:
    bf, centres = _bank()
    res = add_examples(bf, _queries(centres[2], 3, 5), 'c2')
    assert not res.new_class and res.bank.num_classes == 4
    assert class_counts(res.bank)['c2'] == 13 and len(res.bank) == 43


def test_remove_class_relabels_and_forgets() -> None:
    bf, centres = _bank()
    res = remove_class(bf, 'c1', source='test')
    assert res.count == 10 and res.bank.class_names == ['c0', 'c2', 'c3']
    assert res.bank.labels.max() == 2 and len(res.bank) == 30
    pred = Classifier(res.bank).classify(_queries(centres[3], 10, 3)).labels
    assert (pred == 2).all()                      # c3 now has id 2
    with pytest.raises(EnrollError, match="no class 'zz'"):
        remove_class(res.file, 'zz')


def test_bad_input_is_refused_clearly() -> None:
    bf, _ = _bank()
    with pytest.raises(EnrollError, match='dims'):
        add_examples(bf, torch.zeros(2, 7), 'x')
    with pytest.raises(EnrollError, match='M >= 1'):
        add_examples(bf, torch.zeros(0, D), 'x')
    with pytest.raises(EnrollError, match='non-finite'):
        add_examples(bf, torch.full((1, D), float('nan')), 'x')
    with pytest.raises(EnrollError, match='single lines'):
        add_examples(bf, torch.zeros(1, D), ' ')


def test_near_duplicates_reported() -> None:
    bf, centres = _bank()
    x = _queries(centres[0], 3, 7)
    x = torch.cat([x, x[:1], x[:1] + 1e-4])        # the same scan sent again (twice)
    res = add_examples(bf, x, 'c0')
    assert res.duplicate_count == 2
    assert {d.other for d in res.duplicates} == {'new #0'}
    again = add_examples(res.file, x[:1], 'c3')     # a copy filed under another class
    assert again.duplicate_count == 1 and not again.duplicates[0].same_class
    assert 'near-duplicate' in again.describe()


def test_min_examples_gate() -> None:
    bf, _ = _bank()
    policy = RefitPolicy(min_examples=3)
    centre = torch.randn(D, generator=torch.Generator().manual_seed(42))
    res = add_examples(bf, _queries(centre, 2, 1), 'mug', policy=policy)
    view = active_view(res.bank, 3)
    assert len(view) == 40 and view.class_names == res.bank.class_names
    assert (Classifier(view).classify(_queries(centre, 5, 2)).labels != 4).all()
    res = add_examples(res.file, _queries(centre, 1, 3), 'mug', policy=policy)
    assert active_view(res.bank, 3) is res.bank
    assert (Classifier(res.bank).classify(_queries(centre, 5, 2)).labels == 4).all()


def test_refit_policies() -> None:
    bf, centres = _bank()
    kept = refit(bf.bank, RefitPolicy(gamma='keep', calibration='keep'))[0]
    assert kept.gamma == 50.0 and kept.meta['refit']['gamma_reason'] == 'kept'
    assert kept.meta['unknown_calibration']['threshold'] == 0.5
    cv = refit(bf.bank, RefitPolicy(gamma='cv'))[0]
    assert 'CV' in cv.meta['refit']['gamma_reason']
    assert cv.meta['unknown_calibration']['threshold'] != 0.5     # recalibrated with it
    assert 'recalibrated' in cv.meta['refit']['calibration_reason']
    big = refit(bf.bank, RefitPolicy(gamma='auto', cv_max_entries=10))[0]
    assert big.gamma == 50.0 and 'auto' in big.meta['refit']['gamma_reason']
    recal = refit(bf.bank, RefitPolicy(gamma='keep', calibration='recalibrate'))[0]
    assert recal.gamma == 50.0 and recal.meta['unknown_calibration']['threshold'] != 0.5


@pytest.mark.parametrize('dtype', ['float16', 'float32', 'int8', 'int4'])
def test_save_load_is_bit_exact(tmp_path: Path, dtype: str) -> None:
    bf, centres = _bank(dtype=dtype)
    res = add_examples(bf, _queries(centres[1] * 1.5, 6, 11), 'new')
    res = remove_class(res.file, 'c0')
    path = res.file.save(tmp_path / 'b.npz')
    back = BankFile.load(path)
    assert torch.equal(back.bank.features, res.bank.features)
    assert np.array_equal(back.stored, res.file.stored)
    assert back.bank.meta['stored_dtype'] == dtype
    assert back.stored.dtype == (np.int8 if dtype == 'int4' else dtype)
    assert back.bank.meta['bank_version'] == 2 and len(back.bank.enrollments) == 2
    q = torch.randn(50, D)
    a, b = Classifier(res.bank).classify(q), Classifier(back.bank).classify(q)
    assert np.array_equal(a.labels, b.labels) and np.array_equal(a.scores, b.scores)
    # And a second round trip of the loaded bank is exact too.
    again = BankFile.load(back.save(tmp_path / 'c.npz'))
    assert torch.equal(again.bank.features, back.bank.features)
    assert not list(tmp_path.glob('.*tmp*'))


@pytest.mark.parametrize('dtype', ['float16', 'int4'])
def test_the_node_wraps_its_loaded_bank_without_rederiving_it(tmp_path: Path, dtype: str
                                                              ) -> None:
    """BankFile.of_loaded (node/enrollment.py's start) reads the file's values (int4: unpacked)."""
    bf, _ = _bank(dtype=dtype)
    loaded = FeatureBank.load(bf.save(tmp_path / 'b.npz'))
    wrapped = BankFile.of_loaded(loaded)
    assert wrapped.bank is loaded                     # the same rows, no second copy
    assert np.array_equal(wrapped.stored, bf.stored)
    again = FeatureBank.load(wrapped.save(tmp_path / 'c.npz'))
    assert torch.equal(again.features, loaded.features)


def test_loaded_bank_goes_live_without_copying_its_rows(tmp_path: Path) -> None:
    """FeatureBank.load's rows have room: LiveBank keeps them and appends after them."""
    bf, centres = _bank()
    loaded = FeatureBank.load(bf.save(tmp_path / 'b.npz'))
    before = loaded.features.clone()
    live = LiveBank(BankFile.of_loaded(loaded), lambda active: len(active))
    assert live.current().bank.features.data_ptr() == loaded.features.data_ptr()
    live.add(_queries(centres[1] + 2.0, 5, 3), 'new', 'test')
    grown = live.current().bank.features
    assert grown.shape[0] == len(before) + 5 and grown.data_ptr() == loaded.features.data_ptr()
    assert torch.equal(loaded.features, before) and torch.equal(grown[:len(before)], before)


def test_live_bank_readers_see_whole_versions() -> None:
    """Readers racing writers only ever see a snapshot whose parts agree."""
    bf, centres = _bank()
    live = LiveBank(bf, lambda active: (len(active), active.num_classes))
    stop = threading.Event()
    bad: list[str] = []
    seen: set[int] = set()

    def reader() -> None:
        while not stop.is_set():
            snap = live.current()
            n, c = snap.model
            if n != len(snap.bank) or c != len(snap.class_names) or \
                    sum(snap.counts().values()) != n:
                bad.append(f'v{snap.version}: model {n, c}, bank {len(snap.bank)}')
            seen.add(snap.version)

    threads = [threading.Thread(target=reader) for _ in range(2)]
    for t in threads:
        t.start()
    writers = []
    for w in range(2):
        def write(w: int = w) -> None:
            for i in range(8):
                live.add(_queries(centres[0], 2, 100 * w + i), f'w{w}_{i % 3}', 'test')
                if i % 3 == 2:
                    live.remove(f'w{w}_0', 'test')
        writers.append(threading.Thread(target=write))
    for t in writers:
        t.start()
    for t in writers:
        t.join()
    stop.set()
    for t in threads:
        t.join()
    assert not bad
    final = live.current()
    assert final.version == 16 + 2 * 2                     # every write is a version
    assert len(final.bank.enrollments) == final.version
    assert len(seen) > 1


def _saver_script(src: Path, dst: Path) -> str:
    return f"""
import sys
from point_gn_ros.bank.enroll import BankFile
bf = BankFile.load({str(src)!r})
print('ready', flush=True)
while True:
    bf.save({str(dst)!r})
"""


def test_sigkill_during_save_leaves_previous_bank(tmp_path: Path) -> None:
    """Kill a process that saves in a loop at random moments: the file always loads whole."""
    feats, labels, _ = _clusters(8, 400, seed=3)            # ~3 MB: saving takes a while
    tf = FeatureTransform.fit(feats, 'none')
    bank = FeatureBank(features=tf(feats), labels=labels,
                       class_names=[f'k{i}' for i in range(8)], config=EncoderConfig(),
                       transform=tf, gamma=20.0)
    src = BankFile.of(bank, 'float32').save(tmp_path / 'src.npz')
    dst = tmp_path / 'dst.npz'
    previous = BankFile.of(replace(bank, gamma=7.0), 'float32').save(dst)
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    rng = np.random.default_rng(0)
    for _ in range(3):
        proc = subprocess.Popen([sys.executable, '-c', _saver_script(src, dst)], env=env,
                                stdout=subprocess.PIPE)
        assert proc.stdout is not None and proc.stdout.readline().strip() == b'ready'
        time.sleep(float(rng.uniform(0.05, 0.6)))
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        back = FeatureBank.load(previous)                  # whole: old or new, never half
        assert back.gamma in (7.0, 20.0) and len(back) == 3200
    # A killed save may leave its hidden temporary file, never a visible half bank.
    assert sorted(p.name for p in tmp_path.glob('[!.]*')) == ['dst.npz', 'src.npz']


@pytest.fixture(scope='module')
def head_bank() -> tuple[BankFile, torch.Tensor]:
    """A bank with a discriminant head (whitened vote + 0.5 x LDA), 32 PCA dims."""
    from point_gn_ros.bank.discriminant import fit_head

    feats, labels, centres = _clusters(5, 24, seed=4, spread=0.8)
    tf = FeatureTransform.fit(feats, 'standardize', 32)
    z = tf(feats)
    head = fit_head(z, labels, 5, 20.0, alpha=0.2, lda_alpha=0.2, fusion_weight=0.5,
                    temperature=2.0)
    meta = {'head': {'alpha': 0.2, 'whiten_vote': True, 'lda_alpha': 0.2,
                     'fusion_weight': 0.5, 'temperature': 2.0},
            'selection': {'grid': {'gammas': [20.0, 80.0], 'alphas': [0.2],
                                   'weights': [0.0, 0.5]}},
            'unknown_calibration': {'measure': 'novelty', 'threshold': 0.3,
                                    'false_reject_rate': 0.05, 'method': 'test'}}
    bank = FeatureBank(features=head.vote_space(z), labels=labels,
                       class_names=[f'c{i}' for i in range(5)], config=EncoderConfig(),
                       transform=tf, gamma=20.0, meta=meta, head=head)
    return BankFile.of(bank, 'float16'), centres


def test_head_refitted_in_closed_form(head_bank, tmp_path: Path) -> None:  # noqa: ANN001
    bf, centres = head_bank
    head = bf.bank.head
    new_centre = torch.randn(D, generator=torch.Generator().manual_seed(77))
    res = add_examples(bf, _queries(new_centre, 6, 1), 'new', policy=RefitPolicy(gamma='keep'))
    out = res.bank
    assert torch.equal(out.head.whiten, head.whiten)         # knobs kept: rows do not move
    assert np.array_equal(res.file.stored[:len(bf.stored)], bf.stored)
    if head.lda_coef is not None:
        assert out.head.lda_coef.shape[0] == 6 and out.head.fusion_weight == head.fusion_weight
    assert 'closed form' in out.meta['refit']['head']
    pred = Classifier(out).classify(_queries(new_centre, 10, 2)).labels
    assert (pred == 5).all()
    old = Classifier(out).classify(_queries(centres[2], 10, 3)).labels
    assert (old == 2).all()
    back = BankFile.load(res.file.save(tmp_path / 'h.npz'))
    q = torch.cat([_queries(new_centre, 5, 4), _queries(centres[0], 5, 5)])
    a, b = Classifier(out).classify(q), Classifier(back.bank).classify(q)
    assert np.array_equal(a.labels, b.labels) and np.array_equal(a.probability, b.probability)


def test_head_cv_refit_rewhitens_and_stays_exact(head_bank, tmp_path: Path) -> None:  # noqa: ANN001
    bf, centres = head_bank
    new_centre = torch.randn(D, generator=torch.Generator().manual_seed(78))
    res = add_examples(bf, _queries(new_centre, 6, 1), 'new', policy=RefitPolicy(gamma='cv',
                                                                                  folds=3))
    assert 'CV' in res.bank.meta['refit']['gamma_reason']
    assert res.bank.meta['unknown_calibration']['measure'] == 'novelty'
    assert 'recalibrated' in res.bank.meta['refit']['calibration_reason']
    back = BankFile.load(res.file.save(tmp_path / 'h.npz'))
    assert torch.equal(back.bank.features, res.bank.features)
    q = _queries(new_centre, 8, 9)
    assert (Classifier(back.bank).classify(q).labels == 5).all()


def test_head_min_examples_gate(head_bank) -> None:  # noqa: ANN001
    bf, _ = head_bank
    centre = torch.randn(D, generator=torch.Generator().manual_seed(79))
    res = add_examples(bf, _queries(centre, 2, 1), 'new', policy=RefitPolicy(min_examples=3,
                                                                             gamma='keep'))
    view = active_view(res.bank, 3)
    assert (Classifier(view).classify(_queries(centre, 8, 2)).labels != 5).all()


def test_head_recalibrated_at_kept_knobs(head_bank) -> None:  # noqa: ANN001
    bf, _ = head_bank
    centre = torch.randn(D, generator=torch.Generator().manual_seed(80))
    res = add_examples(bf, _queries(centre, 6, 1), 'new',
                       policy=RefitPolicy(gamma='keep', calibration='recalibrate', folds=3))
    assert res.bank.gamma == bf.bank.gamma
    assert torch.equal(res.bank.head.whiten, bf.bank.head.whiten)
    cal = res.bank.meta['unknown_calibration']
    assert cal['measure'] == 'novelty' and cal['threshold'] != 0.3
    assert 'recalibrated' in res.bank.meta['refit']['calibration_reason']


def test_incremental_lda_refit_matches_a_full_refit() -> None:
    """ScatterStats updates give the LDA a full pass over the bank gives (bank > dims)."""
    from point_gn_ros.bank.discriminant import fit_head

    feats, labels, centres = _clusters(4, 20, seed=6, spread=0.8)
    tf = FeatureTransform.fit(feats, 'standardize', 16)
    z = tf(feats)
    head = fit_head(z, labels, 4, 20.0, alpha=0.2, lda_alpha=0.05, fusion_weight=0.5)
    meta = {'head': {'alpha': 0.2, 'lda_alpha': 0.05, 'fusion_weight': 0.5,
                     'temperature': 1.0}}
    bank = FeatureBank(features=head.vote_space(z), labels=labels,
                       class_names=[f'c{i}' for i in range(4)], config=EncoderConfig(),
                       transform=tf, gamma=20.0, meta=meta, head=head)
    plain = BankFile.of(bank, 'float32')
    fast = plain.with_stats()
    assert fast.stats is not None and plain.stats is None
    # computed in blocks of rows (a large bank's float64 rows never all at once): the same sums
    with mock.patch('point_gn_ros.bank.enroll._BLOCK_ROWS', 7):
        blocked = plain.with_stats().stats
    for a, b in ((fast.stats.gram, blocked.gram), (fast.stats.sums, blocked.sums)):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    assert torch.equal(fast.stats.counts, blocked.counts)
    new = torch.randn(D, generator=torch.Generator().manual_seed(81))
    policy = RefitPolicy(gamma='keep')
    steps = [lambda b: add_examples(b, _queries(new, 5, 1), 'new', policy=policy),
             lambda b: add_examples(b, _queries(centres[1], 3, 2), 'c1', policy=policy),
             lambda b: remove_class(b, 'c2', policy=policy)]
    for step in steps:
        plain, fast = step(plain).file, step(fast).file
        assert fast.stats is not None
        for a, b in ((plain.bank.head.lda_coef, fast.bank.head.lda_coef),
                     (plain.bank.head.lda_bias, fast.bank.head.lda_bias)):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)
    q = torch.cat([_queries(new, 6, 3), _queries(centres[3], 6, 4)])
    assert np.array_equal(Classifier(plain.bank).classify(q).labels,
                          Classifier(fast.bank).classify(q).labels)


def test_balanced_lda_prior(head_bank) -> None:  # noqa: ANN001
    """'balanced' replaces the LDA's entry-share priors by equal ones, nothing else."""
    bf, _ = head_bank
    new_centre = torch.randn(D, generator=torch.Generator().manual_seed(80))
    feats = _queries(new_centre, 3, 1)
    res = {p: add_examples(bf, feats, 'new', policy=RefitPolicy(gamma='keep', lda_prior=p))
           for p in ('entries', 'balanced')}
    a, b = res['entries'].bank.head, res['balanced'].bank.head
    assert torch.equal(a.lda_coef, b.lda_coef) and a.gamma == b.gamma
    n = torch.bincount(res['entries'].bank.labels).double()          # 24 x 5, then 3
    want = ((n.sum() / n).log() - np.log(6)).float()
    assert torch.allclose(b.lda_bias - a.lda_bias, want, atol=1e-5)
    assert float(want[-1] - want[0]) == pytest.approx(np.log(8), abs=1e-5)   # 24 / 3
    assert res['balanced'].bank.meta['refit']['lda_prior'] == 'balanced'
    with pytest.raises(ValueError, match='lda_prior'):
        RefitPolicy(lda_prior='uniform')  # type: ignore[arg-type]


def test_typical_lda_prior_moves_only_the_enrolled_classes(head_bank) -> None:  # noqa: ANN001
    """'typical' moves the enrolled classes' LDA priors only.

    The built classes keep their entry-share priors (their answers do not move); an enrolled
    class gets a built class's mean share, also after a second enrollment.
    """
    bf, _ = head_bank
    built = list(bf.bank.class_names)                  # 5 classes of 24 entries, as built
    bf = replace(bf, bank=replace(bf.bank, meta={**bf.bank.meta,
                                                 'provenance': {'per_class': built}}))
    gen = torch.Generator().manual_seed(81)
    new_a, new_b = torch.randn(D, generator=gen), torch.randn(D, generator=gen)
    res = {}
    for p in ('entries', 'typical'):
        policy = RefitPolicy(gamma='keep', lda_prior=p)
        first = add_examples(bf, _queries(new_a, 3, 1), 'new_a', policy=policy).file
        res[p] = add_examples(first, _queries(new_b, 2, 2), 'new_b', policy=policy).bank
    a, b = res['entries'].head, res['typical'].head
    assert torch.equal(a.lda_coef, b.lda_coef)
    shift = b.lda_bias - a.lda_bias
    assert torch.equal(shift[:5], torch.zeros(5))
    assert torch.allclose(shift[5:], torch.tensor([np.log(24 / 3), np.log(24 / 2)]).float(),
                          atol=1e-5)
    assert res['typical'].meta['refit']['lda_prior'] == 'typical'
