"""The object-level test of taught classes (bank/model.py): fit, shift, file, enrollment."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.bank.discriminant import fit_object_test
from point_gn_ros.bank.enroll import BankFile, add_examples, remove_class
from point_gn_ros.bank.model import ObjectShift, ObjectTest
from point_gn_ros.bank.store import FeatureBank, objects_arrays, objects_from_arrays
from point_gn_ros.bank.model import FeatureTransform
from point_gn_ros.cli import main
from point_gn_ros.errors import BankError
from point_gn_ros.recognizer import encode_clouds, make_encoder

D, SCANS = 48, 6


def _scans(centre: torch.Tensor, g: torch.Generator, n: int = SCANS) -> torch.Tensor:
    """Unit rows (n, D) of one object: its own offset from the class centre, then scan noise."""
    obj = centre + 0.6 * torch.randn(D, generator=g)
    return torch.nn.functional.normalize(obj + 0.25 * torch.randn(n, D, generator=g), dim=1)


def _synthetic() -> tuple[ObjectTest, dict[str, torch.Tensor]]:
    """3 classes x 12 built objects; one more object of class 0 is the taught one."""
    g = torch.Generator().manual_seed(0)
    centres = 2.0 * torch.randn(3, D, generator=g)
    rows, groups, labels = [], [], []
    for o in range(36):
        rows.append(_scans(centres[o % 3], g))
        groups += [o] * SCANS
        labels += [o % 3] * SCANS
    test = fit_object_test(torch.cat(rows), np.array(groups), np.array(labels),
                          ['a', 'b', 'c'], rank=12, alpha=0.01)
    taught = _scans(centres[0], g, 15)
    other = _scans(centres[0], g, 10)          # an unseen object of the same category
    return test, {'taught': taught, 'enrolled': taught[:5], 'queries': taught[5:],
                  'other': other, 'built': torch.cat(rows)[:SCANS]}


def _shift(test: ObjectTest, enrolled: torch.Tensor, lam: float, theta: float) -> ObjectShift:
    w = test.projection.double()
    r = float(test.rank)
    return ObjectShift(FeatureTransform.identity(D), w, test.means.double(),
                       r / test.counts.double(), torch.tensor([3]),
                       enrolled.double().mean(0, keepdim=True) @ w.T,
                       torch.tensor([r / len(enrolled)], dtype=torch.float64), lam, theta)


def test_fit_whitens_the_scatter_of_scans_around_their_object() -> None:
    test, _ = _synthetic()
    assert test.projection.shape == (12, D) and test.means.shape == (36, 12)
    assert test.counts.tolist() == [SCANS] * 36 and test.labels.tolist() == [0, 1, 2] * 12
    with pytest.raises(ValueError, match='2 scans'):
        fit_object_test(torch.randn(4, D), np.arange(4), np.zeros(4), ['a'])


def test_scans_of_the_taught_object_are_boosted_other_objects_damped() -> None:
    test, s = _synthetic()
    shift = _shift(test, s['enrolled'], lam=0.2, theta=0.0)
    assert float((shift.gaps(s['queries']) < 0).float().mean()) >= 0.9
    assert float((shift.gaps(s['other']) > 0).float().mean()) >= 0.9
    assert float((shift.gaps(s['built']) > 0).float().mean()) == 1.0
    # probabilities: 4 classes, the taught one (id 3) even with the rest
    prob = torch.full((10, 4), 0.25)
    mine, theirs = shift(prob, s['queries']), shift(prob, s['other'])
    np.testing.assert_allclose(mine.sum(1).numpy(), 1.0, atol=1e-6)
    assert bool((mine[:, 3] > 0.5).float().mean() >= 0.9)
    assert bool((theirs[:, 3] < 0.1).float().mean() >= 0.9)
    # built classes keep their ratios; no slope, no offset: nothing moves
    np.testing.assert_allclose((theirs[:, 0] / theirs[:, 1]).numpy(), 1.0, rtol=1e-6)
    still = _shift(test, s['enrolled'], lam=0.0, theta=0.0)(prob, s['other'])
    np.testing.assert_allclose(still.numpy(), prob.numpy(), atol=1e-7)


def test_arrays_round_trip_and_refuse_what_does_not_fit() -> None:
    test, _ = _synthetic()
    back = objects_from_arrays(objects_arrays(test), D)
    for name in ('projection', 'means', 'labels', 'counts'):
        assert torch.equal(getattr(back, name), getattr(test, name))
    assert (back.class_names, back.lam, back.theta) == (test.class_names, test.lam, test.theta)
    with pytest.raises(ValueError, match='do not fit'):
        objects_from_arrays(objects_arrays(test), D + 1)
    bad = dict(objects_arrays(test), objects_labels=np.full(36, 7, np.int32))
    with pytest.raises(ValueError, match='out of range'):
        objects_from_arrays(bad, D)
    with pytest.raises(ValueError, match='missing'):
        objects_from_arrays({k: v for k, v in objects_arrays(test).items()
                                if k != 'objects_counts'}, D)


@pytest.fixture(scope='module')
def sections_bank(three_class_tree: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A two-section bank whose scan section's CV picks the wide LDA (2 PCA dims lose)."""
    path = tmp_path_factory.mktemp('objects') / 'sections.npz'
    assert main(['bank', 'build', str(three_class_tree), '--split', 'train', '--folds', '2',
                 '--yaw-align', '--views', '3', '--sections', '--dtype', 'int8', '--dims', '8',
                 '--views-dims', '2', '--wide-lda', 'scans', '-o', str(path)]) == 0
    return path


def test_built_bank_holds_the_test_and_without_taught_classes_nothing_moves(
        sections_bank: Path, three_class_tree: Path) -> None:
    bank = FeatureBank.load(sections_bank)
    assert bank.objects is not None and bank.meta['format_version'] == 6
    assert len(bank.objects.means) == 18 and bank.objects.counts.tolist() == [3] * 18
    assert bank.meta['object_test']['objects'] == 18
    clouds = [np.load(f) for f in sorted((three_class_tree / 'test').glob('*/*.npy'))]
    feats = encode_clouds(clouds, make_encoder(bank.config))
    clf = Classifier(bank)
    assert clf.object_shift is None
    plain = Classifier(replace(bank, objects=None))
    assert torch.equal(clf.scores(feats), plain.scores(feats))
    assert torch.equal(clf.scores(feats[:1]), plain.scores(feats[:1]))    # the lone path


def test_taught_class_is_shifted_survives_save_and_removals(
        sections_bank: Path, three_class_tree: Path, tmp_path: Path) -> None:
    bf = BankFile.load(sections_bank)
    clouds = [np.load(f) for f in sorted((three_class_tree / 'test' / 'lamp').glob('*.npy'))]
    feats = encode_clouds(clouds, make_encoder(bf.bank.config))
    taught = add_examples(bf, feats[:3], 'my_lamp', source='test').file
    clf = Classifier(taught.bank)
    assert clf.object_shift is not None and clf.object_shift.taught.tolist() == [3]
    assert len(clf.object_shift.built) == 18
    plain = Classifier(replace(taught.bank, objects=None))
    shifted, head = clf.scores(feats), plain.scores(feats)
    off = Classifier(taught.bank, object_test=False)      # the node's object_test: false
    assert off.object_shift is None and torch.equal(off.scores(feats), head)
    assert not torch.equal(shifted, head)
    np.testing.assert_allclose(shifted.sum(1).numpy(), 1.0, atol=1e-5)
    # its own examples are nearer the taught object than any built one: boosted
    assert bool((shifted[:3, 3] >= head[:3, 3]).all())
    path = taught.save(tmp_path / 'taught.npz')
    again = Classifier(FeatureBank.load(path))
    assert torch.equal(again.scores(feats), shifted)
    assert torch.equal(again.scores(feats[:1]), shifted[:1])
    # a removed built class's objects leave the minimum; the taught class gone: no shift
    less = remove_class(taught, 'lamp', source='test').file
    assert len(Classifier(less.bank).object_shift.built) == 12
    gone = remove_class(taught, 'my_lamp', source='test').file
    assert Classifier(gone.bank).object_shift is None


def test_object_arrays_outside_format_6_are_refused(sections_bank: Path, tmp_path: Path) -> None:
    with np.load(sections_bank) as z:
        arrays = {k: z[k] for k in z.files}
    bad = tmp_path / 'bad.npz'
    np.savez(bad, **{k: v for k, v in arrays.items() if not k.startswith('objects_')})
    with pytest.raises(BankError, match='object test comes with format 6'):
        FeatureBank.load(bad)
