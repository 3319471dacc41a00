"""`point_gn bank build --views`, `eval --single-view`, `classify` as a user runs them."""

import json
from pathlib import Path

import numpy as np
import pytest

from point_gn_ros.cli import main
from point_gn_ros.datasets import write_pcd

@pytest.fixture(scope='module')
def tree(three_class_tree: Path) -> Path:
    return three_class_tree


def test_views_bank_single_view_eval_and_classify(tree: Path, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture) -> None:
    bank = tmp_path / 'views.npz'
    assert main(['bank', 'build', str(tree), '--split', 'train', '--folds', '2', '--yaw-align',
                 '--views', '2', '--cv-every', '2', '-o', str(bank)]) == 0
    capsys.readouterr()
    assert main(['bank', 'info', str(bank), '--json']) == 0
    meta = json.loads(capsys.readouterr().out)
    assert meta['provenance']['count'] == 18 * 3          # each object whole + 2 scans
    assert meta['views']['views_per_object'] == 2 and meta['views']['rotation'] == 'yaw_align'
    assert meta['views']['protocol'] == 'hpr'                 # issue 9's protocol by default
    assert meta['views']['view_config']['visibility'] == 'hpr'
    assert meta['selection']['cv_grouped'] and meta['selection']['cv_entries'] == 9 * 3
    reports = []
    for extra in (['--single-view', '--seed', '3'], ['--single-view', '--seed', '3'],
                  ['--random-yaw', '1'], ['--single-view', '--seed', '3', '--view-protocol',
                                          'zbuffer']):
        assert main(['eval', str(bank), str(tree), '--split', 'test', '--json', *extra]) == 0
        reports.append(json.loads(capsys.readouterr().out))
    assert reports[0]['single_view_seed'] == 3 and reports[0]['count'] == 12
    assert reports[0]['accuracy'] == reports[1]['accuracy']       # seeded scans
    assert reports[2]['random_yaw_seed'] == 1 and reports[2]['single_view_seed'] is None
    assert reports[0]['view_protocol'] == 'hpr' and reports[3]['view_protocol'] == 'zbuffer'
    assert reports[2]['view_protocol'] is None
    # classify: one object per file, optical frame turned upright
    cloud = np.load(next((tree / 'test' / 'chair').glob('*.npy')))
    optical = np.stack([cloud[:, 0], -cloud[:, 2], cloud[:, 1]], axis=1)   # z up -> y down
    pcd = tmp_path / 'chair.pcd'
    o = optical.astype(np.float32)
    write_pcd(pcd, {'x': o[:, 0], 'y': o[:, 1], 'z': o[:, 2]})
    assert main(['classify', str(pcd), '--bank', str(bank), '--up=-y', '--json']) == 0
    line = json.loads(capsys.readouterr().out)
    assert line['points'] == len(cloud) and len(line['top']) == 3
    np.testing.assert_allclose(line['extent'], np.ptp(cloud, axis=0), rtol=1e-5)
