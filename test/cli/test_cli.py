"""`point_gn bank build|info`, `eval`, `fewshot` as a user runs them."""

import json
from pathlib import Path
import subprocess
import sys

from conftest import load_modelnet_subset, write_npy_tree
import numpy as np
import pytest

from point_gn_ros.cli import main

CLASSES = ('chair', 'lamp', 'airplane')


@pytest.fixture(scope='module')
def tree(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder tree dataset of real ModelNet40 objects: train/test x 3 classes, .npy files."""
    # In metres, offset from the origin, as a user's own scans would be.
    return write_npy_tree(tmp_path_factory.mktemp('tree'), CLASSES, {'train': 8, 'test': 4},
                          scale=0.5, offset=2.0)


@pytest.fixture(scope='module')
def bank(tree: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp('bank') / 'tree_bank.npz'
    assert main(['bank', 'build', str(tree), '--split', 'train', '--folds', '2', '-o',
                 str(out)]) == 0
    return out


def test_bank_build_and_info(bank: Path, capsys: pytest.CaptureFixture) -> None:
    assert bank.is_file()
    assert main(['bank', 'info', str(bank)]) == 0
    out = capsys.readouterr().out
    assert '24 entries, 3 classes' in out and 'gamma' in out and 'chair' in out
    from point_gn_ros.core import kernels
    head = 'compiled' if kernels.load() is not None else 'reference'
    assert f'query path (CPU): {head} head' in out and 'exact search' in out
    assert main(['bank', 'info', str(bank), '--json']) == 0
    meta = json.loads(capsys.readouterr().out)
    assert meta['provenance']['count'] == 24 and meta['provenance']['split'] == 'train'
    assert meta['selection']['cv_folds'] == 2
    assert meta['format_version'] == 2 and meta['head']['folds_used'] == 2
    assert meta['unknown_calibration']['measure'] == 'probability'
    assert meta['novelty_calibration']['measure'] == 'novelty'
    assert main(['bank', 'info', str(bank)]) == 0
    out = capsys.readouterr().out
    assert 'head: kernel vote on' in out and 'temperature' in out
    assert 'plain kernel vote on the same folds' in out and 'probability below' in out


def test_eval_open_set(tree: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    # a bank of chairs and lamps (built from train), queried with all three test classes
    out = tmp_path / 'known.npz'
    args = ['eval', str(out), str(tree), '--split', 'test', '--open-set', 'chair,lamp',
            '--json']
    assert main(args) == 0
    report = json.loads(capsys.readouterr().out)
    assert report['known_classes'] == ['chair', 'lamp'] and out.is_file()
    assert report['known_objects'] == 8 and report['unseen_objects'] == 4
    assert 0.0 <= report['auroc_novelty'] <= 1.0
    assert 0.0 <= report['unknown_recall_at_threshold'] <= 1.0
    assert main(args) == 0                      # the second run reuses the bank
    assert json.loads(capsys.readouterr().out)['auroc_novelty'] == report['auroc_novelty']


def test_eval_json_and_confusion(bank: Path, tree: Path, tmp_path: Path,
                                 capsys: pytest.CaptureFixture) -> None:
    png = tmp_path / 'cm.png'
    assert main(['eval', str(bank), str(tree), '--split', 'test', '--json',
                 '--confusion', str(png)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report['count'] == 12
    assert 0.6 <= report['accuracy'] <= 1.0   # chairs, lamps and airplanes are easy
    assert 0.0 <= report['mean_class_accuracy'] <= 1.0
    assert png.read_bytes()[:4] == b'\x89PNG'
    assert main(['eval', str(bank), str(tree), '--split', 'test']) == 0
    assert 'overall accuracy' in capsys.readouterr().out


def test_fewshot_json(tree: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(['fewshot', str(tree), '--split', 'train', '--ways', '3', '--shots', '3',
                 '--queries', '4', '--episodes', '2', '--json']) == 0
    res = json.loads(capsys.readouterr().out)
    assert res[0]['ways'] == 3 and len(res[0]['accuracies']) == 2


def test_corrupt_bank_is_one_line_exit_2(tmp_path: Path) -> None:
    bad = tmp_path / 'bad.npz'
    bad.write_bytes(b'PK\x03\x04 not really a zip')
    proc = subprocess.run([sys.executable, '-m', 'point_gn_ros.cli', 'bank', 'info', str(bad)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.strip().count('\n') == 0 and 'bad.npz' in proc.stderr
    assert 'Traceback' not in proc.stderr


def test_missing_dataset_is_a_clear_error(tmp_path: Path, bank: Path,
                                          capsys: pytest.CaptureFixture) -> None:
    assert main(['eval', str(bank), str(tmp_path / 'nowhere')]) == 2
    assert 'nowhere' in capsys.readouterr().err


def test_eval_random_yaw(bank: Path, tree: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(['eval', str(bank), str(tree), '--split', 'test', '--json',
                 '--random-yaw', '3']) == 0
    report = json.loads(capsys.readouterr().out)
    assert report['random_yaw_seed'] == 3 and report['count'] == 12


def test_scanobjectnn_bank_uses_sigma_03(tmp_path: Path) -> None:
    import h5py

    xyz, labels, _ = load_modelnet_subset('train', 2)
    keep = labels < 15                  # 15 classes stand in for scans (none may be empty)
    split = tmp_path / 'h5_files' / 'main_split'
    split.mkdir(parents=True)
    for name in ('training_objectdataset.h5', 'test_objectdataset.h5'):
        with h5py.File(split / name, 'w') as f:
            f['data'] = np.concatenate([xyz[keep], xyz[keep]], axis=1)  # 2048 points
            f['label'] = labels[keep].astype(np.int64)
    out = tmp_path / 'sonn.npz'
    assert main(['bank', 'build', str(tmp_path / 'h5_files'), '--variant', 'OBJ_BG',
                 '--folds', '2', '-o', str(out)]) == 0
    from point_gn_ros.bank.store import FeatureBank
    bank = FeatureBank.load(out)
    assert bank.config.sigma == 0.3 and bank.provenance['format'] == 'scanobjectnn_h5'
    assert len(bank.class_names) == 15 and len(bank) == int(keep.sum())


def test_a_closed_pipe_ends_quietly(bank: Path) -> None:
    # `point_gn bank history BANK | head -0`: the reader is gone before anything is printed.
    proc = subprocess.Popen([sys.executable, '-m', 'point_gn_ros.cli', 'bank', 'history',
                             str(bank)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 1 and 'Traceback' not in err and 'Broken pipe' not in err, err
