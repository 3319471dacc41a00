"""`point_gn bank build` says what it left out and what it chose.

A class-per-folder tree with good .npy clouds, a 0-byte PCD, a truncated PCD and a stray
text file: the build lists each skipped file with its reason, warns that the classes are
smaller than the CV folds, prints its settings, and with --strict refuses to build.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from point_gn_ros.cli import main as cli_main

PCD_HEADER = ('# .PCD v.7\nVERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n'
              'WIDTH 50\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 50\nDATA ascii\n')


def _tree(root: Path) -> Path:
    rng = np.random.default_rng(0)
    for c, shape in (('ball', 1.0), ('rod', 0.05)):
        (root / c).mkdir(parents=True)
        for i in range(3):
            xyz = rng.normal(size=(200, 3)) * np.array([shape, shape, 1.0])
            np.save(root / c / f'{i}.npy', xyz.astype(np.float32))
    (root / 'ball' / 'zero.pcd').write_bytes(b'')
    (root / 'rod' / 'cut.pcd').write_text(PCD_HEADER + '0.1 0.2 0.3\n' * 20)   # 20 of 50
    (root / 'rod' / 'notes.txt').write_text('not points\n')
    return root


def test_skipped_files_small_classes_and_settings_are_reported(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    root = _tree(tmp_path / 'data')
    out = tmp_path / 'bank.npz'
    assert cli_main(['bank', 'build', str(root), '-o', str(out), '--folds', '3',
                     '--dtype', 'float32']) == 0
    captured = capsys.readouterr()
    err = captured.err
    assert f'skipped {root}/ball/zero.pcd: empty file (0 bytes)' in err
    assert f'skipped {root}/rod/cut.pcd: ascii PCD data has 60 values' in err
    assert f'skipped {root}/rod/notes.txt: ' in err
    assert 'warning: 3 file(s) skipped, not in the bank' in err
    assert 'fewer examples than --folds' not in err                 # 3 each, 3 folds: fine
    assert 'settings: num_points=1024' in captured.out and 'folds=3' in captured.out
    assert 'yaw_align=' in captured.out and out.is_file()

    assert cli_main(['bank', 'build', str(root), '-o', str(tmp_path / 'b2.npz'),
                     '--folds', '5']) == 0
    assert ('warning: 2 class(es) have fewer examples than --folds 5'
            in capsys.readouterr().err)


def test_strict_refuses_a_tree_with_skipped_files(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture) -> None:
    root = _tree(tmp_path / 'data')
    out = tmp_path / 'bank.npz'
    assert cli_main(['bank', 'build', str(root), '-o', str(out), '--strict']) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith('point_gn: error: ') and '3 file(s) could not be used' in err[-1]
    assert not out.exists()


def test_a_class_without_examples_is_an_error(tmp_path: Path,
                                              capsys: pytest.CaptureFixture) -> None:
    root = _tree(tmp_path / 'data')
    (root / 'empty_class').mkdir()
    (root / 'empty_class' / 'broken.pcd').write_bytes(b'')
    assert cli_main(['bank', 'build', str(root), '-o', str(tmp_path / 'b.npz')]) == 2
    err = capsys.readouterr().err
    assert 'empty_class' in err and 'point_gn: error: ' in err


def test_wide_lda_flag_reaches_the_cv(tmp_path: Path) -> None:
    from point_gn_ros.bank.store import FeatureBank
    root = _tree(tmp_path / 'data')
    out = tmp_path / 'wide.npz'
    assert cli_main(['bank', 'build', str(root), '-o', str(out), '--folds', '3', '--dims', '3',
                     '--standardize', 'standardize', '--wide-lda', 'all']) == 0
    sel = FeatureBank.load(out).meta['selection']
    assert sel['grid']['wide_lda'] is True and sel['dims'] == 3
    assert all('lda_wide' in row for row in sel['table'])
