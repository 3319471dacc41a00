"""`point_gn bank add|remove` as a user runs them, on real ModelNet40 objects."""

from __future__ import annotations

from pathlib import Path

from conftest import MODELNET, load_modelnet_split
import numpy as np
import pytest
import torch

from point_gn_ros.bank.enroll import BankFile, class_counts
from point_gn_ros.cli import main
from point_gn_ros.recognizer import Recognizer


def test_add_files_then_remove(small_bank_path: Path, tmp_path: Path,
                               capsys: pytest.CaptureFixture) -> None:
    xyz, labels, names = load_modelnet_split('test')
    # One particular object, a "toolbox": its scans at different scales and offsets.
    obj = xyz[np.flatnonzero(labels == names.index('cone'))[3]]
    rng = np.random.default_rng(0)
    folder = tmp_path / 'toolbox'
    folder.mkdir()
    for i in range(5):
        cloud = obj[rng.permutation(len(obj))[:800]] * rng.uniform(0.5, 2) + rng.normal(size=3)
        np.save(folder / f'scan_{i}.npy', cloud.astype(np.float32))
    np.save(tmp_path / 'extra.npy', obj[::2] + 3.0)
    out = tmp_path / 'taught.npz'
    assert main(['bank', 'add', str(small_bank_path), str(folder), str(tmp_path / 'extra.npy'),
                 '--class', 'toolbox', '-o', str(out)]) == 0
    text = capsys.readouterr().out
    assert "added 6 example(s) to new class 'toolbox'" in text and 'v1' in text
    bf = BankFile.load(out)
    assert bf.bank.class_names[-1] == 'toolbox' and class_counts(bf.bank)['toolbox'] == 6
    assert bf.bank.enrollments[0].source.startswith('point_gn bank add: files:')
    assert len(BankFile.load(small_bank_path).bank.class_names) == 40     # input untouched
    # Another view of the same object is now a toolbox.
    view = obj[rng.permutation(len(obj))[:600]] + 5.0
    rec = Recognizer.from_bank(out)
    assert rec.class_names[int(rec.classify_clouds([view]).labels[0])] == 'toolbox'

    # More of an existing class, from the dataset itself, in place.
    assert main(['bank', 'add', str(out), str(MODELNET),
                 '--class', 'vase', '--split', 'test', '--limit', '3']) == 0
    assert class_counts(BankFile.load(out).bank)['vase'] == 4 + 3

    assert main(['bank', 'remove', str(out), 'toolbox']) == 0
    assert "removed 6 entries of class 'toolbox'" in capsys.readouterr().out
    back = BankFile.load(out)
    assert 'toolbox' not in back.bank.class_names and back.bank.meta['bank_version'] == 3
    assert [e.action for e in back.bank.enrollments] == ['add', 'add', 'remove']
    assert main(['bank', 'history', str(out)]) == 0
    text = capsys.readouterr().out
    assert 'bank version 3' in text and 'v1 ' in text and "add 'toolbox' x6" in text
    assert "remove 'toolbox'" in text and 'last refit (v3)' in text


def test_add_augmented_d4(small_bank_path: Path, tmp_path: Path,
                          capsys: pytest.CaptureFixture) -> None:
    xyz, labels, names = load_modelnet_split('test')
    obj = xyz[np.flatnonzero(labels == names.index('cone'))[3]]
    folder = tmp_path / 'scans'
    folder.mkdir()
    for i in range(2):
        np.save(folder / f'scan_{i}.npy', obj[i::2])
    out = tmp_path / 'aug.npz'
    assert main(['bank', 'add', str(small_bank_path), str(folder), '--class', 'toolbox',
                 '--augment', 'd4', '--lda-prior', 'balanced', '-o', str(out)]) == 0
    assert "added 2 example(s) (16 entries, d4) to new class 'toolbox'" in capsys.readouterr().out
    bank = BankFile.load(out).bank
    assert class_counts(bank)['toolbox'] == 16 and bank.meta['refit']['lda_prior'] == 'balanced'
    assert main(['bank', 'history', str(out)]) == 0
    assert "add 'toolbox' x16 (2 examples, d4)" in capsys.readouterr().out


def test_add_records_its_refit_knobs(small_bank_path: Path, tmp_path: Path,
                                     capsys: pytest.CaptureFixture) -> None:
    xyz, labels, names = load_modelnet_split('test')
    obj = xyz[np.flatnonzero(labels == names.index('cone'))[3]]
    np.save(tmp_path / 'scan.npy', obj[::2])
    out = tmp_path / 'prior.npz'
    with pytest.raises(SystemExit):       # the vote prior is gone: an unknown option
        main(['bank', 'add', str(small_bank_path), str(tmp_path / 'scan.npy'), '--class',
              'toolbox', '--vote-prior', '1.4', '-o', str(out)])
    assert '--vote-prior' in capsys.readouterr().err and not out.exists()
    assert main(['bank', 'add', str(small_bank_path), str(tmp_path / 'scan.npy'), '--class',
                 'toolbox', '--lda-debias', '0.5', '-o', str(out)]) == 0
    assert BankFile.load(out).bank.meta['refit']['lda_debias'] == 0.5
    with pytest.raises(SystemExit):       # out of [0, 2]
        main(['bank', 'add', str(out), str(tmp_path / 'scan.npy'), '--class', 'x',
              '--lda-debias', '2.5'])
    assert 'must be in [0, 2]' in capsys.readouterr().err
    assert main(['bank', 'add', str(small_bank_path), str(tmp_path / 'scan.npy'), '--class',
                 'toolbox', '--lda-debias', '1', '--steal-budget', '0.01', '-o', str(out)]) == 0
    assert BankFile.load(out).bank.meta['refit']['lda_steal_budget'] == 0.01
    # Without the knobs: train CV's choice (README, "Teaching the robot new objects").
    assert main(['bank', 'add', str(small_bank_path), str(tmp_path / 'scan.npy'), '--class',
                 'toolbox', '-o', str(out)]) == 0
    refit = BankFile.load(out).bank.meta['refit']
    assert (refit['lda_prior'], refit['lda_debias'], refit['lda_steal_budget']) == \
        ('typical', 2.0, 0.001), refit
    with pytest.raises(SystemExit):       # out of [0, 0.5]
        main(['bank', 'add', str(out), str(tmp_path / 'scan.npy'), '--class', 'x',
              '--steal-budget', '0.7'])
    assert 'must be in [0, 0.5]' in capsys.readouterr().err


def test_errors_are_one_line(small_bank_path: Path, tmp_path: Path,
                             capsys: pytest.CaptureFixture) -> None:
    assert main(['bank', 'remove', str(small_bank_path), 'no_such_class']) == 2
    assert "no class 'no_such_class'" in capsys.readouterr().err
    assert main(['bank', 'add', str(small_bank_path), str(tmp_path / 'missing.npy'),
                 '--class', 'x']) == 2
    assert 'no such file' in capsys.readouterr().err
    one = tmp_path / 'one.npy'
    np.save(one, load_modelnet_split('test')[0][0])
    assert main(['bank', 'add', str(small_bank_path), str(one), '--class', 'x', '-o',
                 str(tmp_path / 'one_bank.npz')]) == 0


def test_add_fused_views_of_one_object(small_bank_path: Path, tmp_path: Path,
                                       capsys: pytest.CaptureFixture) -> None:
    from point_gn_ros.core.views import simulate_views

    xyz, labels, names = load_modelnet_split('test')
    obj = xyz[np.flatnonzero(labels == names.index('cone'))[3]] + np.float32([1.0, 2.0, 0.0])
    folder = tmp_path / 'views'
    folder.mkdir()
    views = simulate_views(obj, 5, seed=0)           # five sides of it, in one frame
    for i, v in enumerate(views):
        np.save(folder / f'view_{i}.npy', v.points)
    out = tmp_path / 'fused.npz'
    assert main(['bank', 'add', str(small_bank_path), str(folder), '--class', 'toolbox',
                 '--fuse-views', '-o', str(out)]) == 0
    assert "added 14 example(s) to new class 'toolbox'" in capsys.readouterr().out
    bank = BankFile.load(out).bank
    assert class_counts(bank)['toolbox'] == 14
    assert '5 views fused into 9 more examples' in bank.enrollments[0].source
    # Views of a moving frame cannot be fused: refused in one line, nothing written.
    for i, v in enumerate(views):
        np.save(folder / f'view_{i}.npy', v.points + np.float32([4.0 * i, 0.0, 0.0]))
    assert main(['bank', 'add', str(small_bank_path), str(folder), '--class', 'toolbox',
                 '--fuse-views', '-o', str(tmp_path / 'no.npz')]) == 2
    assert 'do not overlap' in capsys.readouterr().err and not (tmp_path / 'no.npz').exists()


def test_add_files_in_a_y_up_frame(small_bank_path: Path, tmp_path: Path,
                                   capsys: pytest.CaptureFixture) -> None:
    from point_gn_ros.commands.common import UP_AXES

    xyz, labels, names = load_modelnet_split('test')
    obj = xyz[np.flatnonzero(labels == names.index('cone'))[3]]          # z up
    np.save(tmp_path / 'z_up.npy', obj)
    np.save(tmp_path / 'y_up.npy', (obj.astype(np.float64) @ UP_AXES['y']).astype(np.float32))

    def taught(name: str, *up: str) -> torch.Tensor:
        out = tmp_path / f'{name}.npz'
        assert main(['bank', 'add', str(small_bank_path), str(tmp_path / f'{name}.npy'),
                     '--class', 'toolbox', '-o', str(out), *up]) == 0
        bank = BankFile.load(out).bank
        return bank.features[bank.labels == bank.class_names.index('toolbox')]

    # The y-up file, told its up axis, is enrolled as the z-up object is (same entry)...
    same = taught('z_up')
    assert torch.equal(taught('y_up', '--up', 'y'), same)
    assert BankFile.load(tmp_path / 'y_up.npz').bank.enrollments[0].source \
        .endswith('(up y)')
    # ... and not so when it is read as z up (a lying object).
    assert not torch.allclose(taught('y_up'), same, atol=1e-3)
