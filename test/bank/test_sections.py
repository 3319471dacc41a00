"""Two-section banks (complete objects | single-view scans, mixed by a gate) and int8 banks."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.bank.discriminant import fit_gate
from point_gn_ros.bank.enroll import BankFile, add_examples, remove_class
from point_gn_ros.bank.store import FeatureBank, gate_arrays, gate_from_arrays, to_stored
from point_gn_ros.cli import main
from point_gn_ros.errors import BankError
from point_gn_ros.recognizer import encode_clouds, make_encoder

def test_int8_rows_round_trip_and_keep_cosines() -> None:
    u = torch.nn.functional.normalize(torch.randn(50, 64), dim=1)
    q = to_stored(u, 'int8')
    assert q.dtype == np.int8 and (np.abs(q).max(axis=1) == 127).all()
    back = torch.nn.functional.normalize(torch.from_numpy(q.astype(np.float32)), dim=1)
    # stored again: identical values (save after load is exact)
    np.testing.assert_array_equal(to_stored(torch.from_numpy(q.astype(np.float32)), 'int8'), q)
    assert float((back * u).sum(1).min()) > 0.999
    with pytest.raises(ValueError, match='dtype'):
        to_stored(u, 'int2')


def test_gate_tells_two_populations_apart_and_validates_its_arrays() -> None:
    g = torch.Generator().manual_seed(0)
    a = torch.randn(200, 20, generator=g)
    b = torch.randn(200, 20, generator=g) + torch.linspace(0, 2, 20)
    feats = torch.cat([a, b])
    is_scan = np.r_[np.zeros(200, bool), np.ones(200, bool)]
    gate = fit_gate(feats, is_scan, dims=None)
    p = gate.scan_probability(feats).numpy()
    assert ((p > 0.5) == is_scan).mean() > 0.95
    again = gate_from_arrays(gate_arrays(gate), 20)
    np.testing.assert_allclose(again.scan_probability(feats).numpy(), p, atol=1e-6)
    bad = dict(gate_arrays(gate), gate_coef=np.zeros((3, 20), np.float32))
    with pytest.raises(ValueError, match='gate_coef'):
        gate_from_arrays(bad, 20)
    with pytest.raises(ValueError, match='complete objects and scans'):
        fit_gate(feats, np.zeros(400, bool))


def test_sections_bank_cli_build_info_eval_enroll(three_class_tree: Path, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture) -> None:
    path = tmp_path / 'sections.npz'
    assert main(['bank', 'build', str(three_class_tree), '--split', 'train', '--folds', '2',
                 '--yaw-align', '--views', '2', '--sections', '--dtype', 'int8', '--dims', '8',
                 '--views-dims', '6', '-o', str(path)]) == 0
    capsys.readouterr()
    assert main(['bank', 'info', str(path)]) == 0
    out = capsys.readouterr().out
    assert 'single-view section: 36 entries' in out and 'gate (complete vs scan)' in out
    bank = FeatureBank.load(path)
    assert len(bank) == 18 and bank.views is not None and len(bank.views) == 36
    assert bank.features.shape[1] == 8 and bank.views.features.shape[1] == 6
    assert bank.meta['format_version'] == 3 and bank.meta['stored_dtype'] == 'int8'
    with np.load(path) as z:
        assert z['features'].dtype == np.int8 and z['views_features'].dtype == np.int8
    assert bank.views.meta['selection']['cv_grouped']
    for extra in (['--single-view', '--seed', '3'], ['--random-yaw', '1']):
        assert main(['eval', str(path), str(three_class_tree), '--split', 'test', '--json',
                     *extra]) == 0
        assert json.loads(capsys.readouterr().out)['count'] == 12
    # probabilities are a mixture of the sections: rows sum to 1
    enc = make_encoder(bank.config)
    clouds = [np.load(f) for f in sorted((three_class_tree / 'test' / 'lamp').glob('*.npy'))]
    feats = encode_clouds(clouds, enc)
    prob = Classifier(bank).scores(feats)
    np.testing.assert_allclose(prob.sum(1).numpy(), 1.0, atol=1e-5)
    # enrollment reaches both sections; save + load is exact; removal leaves both
    bf = BankFile.load(path)
    res = add_examples(bf, feats[:3], 'my_lamp', source='test')
    b2 = res.bank
    assert b2.class_names[-1] == 'my_lamp' and b2.views.class_names == b2.class_names
    assert int((b2.labels == 3).sum()) == 3 == int((b2.views.labels == 3).sum())
    saved = res.file.save(tmp_path / 'taught.npz')
    back = FeatureBank.load(saved)
    assert torch.equal(back.features, b2.features)
    assert torch.equal(back.views.features, b2.views.features)
    np.testing.assert_array_equal(Classifier(back).classify(feats).labels,
                                  Classifier(b2).classify(feats).labels)
    gone = remove_class(res.file, 'my_lamp').bank
    assert gone.class_names == bank.class_names == gone.views.class_names
    # a views section without its gate is refused with the reason
    with np.load(saved) as z:
        arrays = {k: z[k] for k in z.files if not k.startswith('gate_')}
    np.savez(tmp_path / 'nogate.npz', **arrays)
    with pytest.raises(BankError, match='come together'):
        FeatureBank.load(tmp_path / 'nogate.npz')


def test_a_section_the_gate_all_but_excludes_is_not_searched(three_class_tree: Path) -> None:
    """Rows with a gate weight < GATE_SKIP skip that section; the mixture moves by < 1e-6."""
    from point_gn_ros.bank.classifier import GATE_SKIP
    from point_gn_ros.core.views import simulate_view

    bank = FeatureBank.load(None)                  # the shipped two-section default
    clf = Classifier(bank)
    clouds = [np.load(f) for f in sorted((three_class_tree / 'test').glob('*/*.npy'))]
    scans = [simulate_view(c, seed=i).points for i, c in enumerate(clouds)]
    feats = encode_clouds(clouds + scans, make_encoder(bank.config))
    p_scan = clf.gate.scan_probability(feats)
    skip_v, skip_c = p_scan <= GATE_SKIP, p_scan >= 1 - GATE_SKIP
    assert skip_v.any() and skip_c.any()           # both cases occur on real objects
    seen: list[int] = []
    section = clf.views.evaluate
    clf.views.evaluate = lambda f: (seen.append(len(f)), section(f))[1]
    prob, novelty = clf.evaluate(feats)
    assert seen == [int((~skip_v).sum())]          # only the rows that need the scan section
    with torch.no_grad():                          # the full mixture, both sections everywhere
        pc, nc = clf._section(feats)
        pv, nv = section(feats)
    g = p_scan[:, None]
    # The skip moves a probability by < 1e-6; the sections' GEMMs round by the batch's shape
    # (a subset here, all rows there): up to 7e-6 apart with 2 MKL threads on Intel CPUs.
    torch.testing.assert_close(prob, (1 - g) * pc + g * pv, atol=2e-5, rtol=0)
    torch.testing.assert_close(novelty, (1 - p_scan) * nc + p_scan * nv, atol=4e-6, rtol=0)
