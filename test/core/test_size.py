"""Metric size (core/size.py), the taught-class layer (bank/taught.py) and `fewshot --bank`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from point_gn_ros.bank.taught import (DEFAULT_FIT_THRESHOLD, KEY, TaughtLayer, fit_rule,
                                      plausible_scale, size_prior)
from point_gn_ros.core.size import SIZE_DIM, size_descriptor

from conftest import SHARED

TABLETOP = SHARED / 'datasets' / 'restaurant_kinectsim' / 'all'


def _box(rng: np.random.Generator, dims: tuple[float, float, float], n: int = 3000) -> np.ndarray:
    return (rng.uniform(-0.5, 0.5, (n, 3)) * np.asarray(dims)).astype(np.float32)


def test_size_descriptor_measures_a_box_in_metres_whatever_its_yaw_place_and_density() -> None:
    rng = np.random.default_rng(0)
    box = _box(rng, (2.0, 0.5, 1.2))
    s = size_descriptor(box)
    assert s.shape == (SIZE_DIM,)
    # height 1.2, length 2.0, width 0.5: percentiles 2-98 keep 96 % of each extent
    assert np.allclose(np.exp(s[:3]), [1.2 * 0.96, 2.0 * 0.96, 0.5 * 0.96], rtol=0.03)
    c, si = np.cos(0.7), np.sin(0.7)
    turned = box @ np.array([[c, -si, 0], [si, c, 0], [0, 0, 1]]).T + [5.0, -3.0, 1.0]
    assert np.allclose(size_descriptor(turned), s, atol=0.02)
    assert np.allclose(size_descriptor(box[::10]), s, atol=0.08)      # a tenth of the points
    stray = np.vstack([box, [[40.0, 40.0, 40.0]]])                     # one outlier
    assert np.allclose(size_descriptor(stray)[:3], s[:3], atol=0.02)
    assert np.isfinite(size_descriptor(box[:1])).all()


def test_size_prior_covers_modelnet40_and_scales_demo_objects_into_its_ranges() -> None:
    prior = size_prior()
    assert len(prior) == 40 and all(r.shape == (3, 2) and (r[:, 0] < r[:, 1]).all()
                                    for r in prior.values())
    unit = _box(np.random.default_rng(1), (1.2, 1.2, 1.2))
    s = plausible_scale(unit, 'cup')
    assert 0.03 < s < 0.2                       # a cup is about 10 cm, not 1.2 m
    assert plausible_scale(unit, 'no_such_class') == 1.0
    assert fit_rule(-10.0) is None and fit_rule(DEFAULT_FIT_THRESHOLD) == DEFAULT_FIT_THRESHOLD


def _layer(meta: dict, names: list[str]) -> TaughtLayer:
    z = torch.nn.functional.normalize(torch.eye(4)[[0, 0, 1, 1, 2, 3]] + 0.01, dim=1)
    return TaughtLayer.build(meta, names, z, torch.tensor([0, 0, 1, 1, 2, 3]))


def test_taught_block_is_redivided_by_prototype_and_size_and_built_classes_by_the_prior() -> None:
    from point_gn_ros.bank.taught import add_taught
    names = ['cup', 'wardrobe', 'thing_a', 'thing_b']
    small, big = np.log([0.1, 0.1, 0.1, 0.03, 0.03, 0.03]), np.log([1.0, 1.0, 1.0, .3, .3, .3])
    meta = add_taught({}, 'thing_a', torch.nn.functional.normalize(torch.eye(4)[[2, 2]], dim=1),
                      np.stack([small, small]))
    meta = add_taught(meta, 'thing_b', torch.nn.functional.normalize(
        torch.tensor([[0.0, 0.0, 1.0, 0.2]]), dim=1), big[None])
    assert meta[KEY]['thing_a']['n'] == 2 and meta[KEY]['thing_a']['sn'] == 2
    layer = _layer(json.loads(json.dumps(meta)), names)      # survives the JSON round trip
    assert layer.active and sorted(layer.taught.tolist()) == [2, 3]
    prob = torch.full((1, 4), 0.25)
    z = torch.nn.functional.normalize(torch.tensor([[0.0, 0.0, 1.0, 0.1]]), dim=1)
    # nearly the same shape cosine to both taught classes: the size decides
    p_small, _, _ = layer.apply(prob, z, small[None])
    p_big, _, _ = layer.apply(prob, z, big[None])
    assert p_small[0, 2] > 0.9 * (p_small[0, 2] + p_small[0, 3])
    assert p_big[0, 3] > 0.9 * (p_big[0, 2] + p_big[0, 3])
    # a 10 cm object is a plausible cup and an implausible wardrobe
    assert p_small[0, 0] > 10 * p_small[0, 1]
    # without sizes the taught block is re-divided by the prototypes only, built ones kept
    p_none, fit, _ = layer.apply(prob, torch.nn.functional.normalize(
        torch.tensor([[0.0, 0.0, 1.0, -0.2]]), dim=1), None)
    assert p_none[0, 2] > p_none[0, 3] and torch.allclose(p_none[0, :2], prob[0, :2])
    assert fit.shape == (1,)
    # a query unlike every taught mean keeps the head's division of the taught block
    head = torch.tensor([[0.1, 0.1, 0.2, 0.6]])
    p_far, _, _ = layer.apply(head, torch.eye(4)[[0]], None)
    assert torch.allclose(p_far, head, atol=1e-3)


def test_an_answer_outside_its_classs_size_region_is_flagged_and_the_region_widens() -> None:
    from point_gn_ros.bank.taught import KEPT_SIZES, REGION_CHI2, add_taught
    names = ['cup', 'wardrobe', 'carton', 'bin']
    rng = np.random.default_rng(7)
    carton = np.log([0.15, 0.08, 0.06, 0.04, 0.02, 0.015]) + rng.normal(0, 0.05, (5, SIZE_DIM))
    meta = add_taught({}, 'carton', torch.nn.functional.normalize(torch.eye(4)[[2] * 5], dim=1),
                      carton)
    # a bin taught from scans whose sizes vary far more than the prior's 14 %
    bins = np.log([0.6, 0.4, 0.3, 0.2, 0.1, 0.08]) + rng.normal(0, 0.5, (6, SIZE_DIM))
    meta = add_taught(meta, 'bin', torch.nn.functional.normalize(torch.eye(4)[[3] * 6], dim=1),
                      bins)
    layer = _layer(json.loads(json.dumps(meta)), names)
    carton_id, bin_id = 2, 3
    assert layer.region[0] == REGION_CHI2                 # built: the chi-square radius
    assert layer.region[bin_id] > 1.1 * REGION_CHI2       # widened by the bin's examples,
    assert layer.region[carton_id] == layer.region[bin_id]   # pooled over taught classes
    alone = _layer(json.loads(json.dumps(add_taught({}, 'carton', torch.nn.functional.normalize(
        torch.eye(4)[[2] * 5], dim=1), carton))), names)
    assert alone.region[carton_id] == REGION_CHI2         # its examples agree with the prior
    # 5 examples say little about their own spread: the carton's variance is shrunk towards
    # the taught classes' pooled one (the same sensor), widened here by the bin's
    assert (layer.size_var[carton_id] > alone.size_var[carton_id]).all()
    prob = torch.tensor([[0.05, 0.05, 0.85, 0.05]])
    z = torch.nn.functional.normalize(torch.eye(4)[[2]], dim=1)
    _, _, inside = layer.apply(prob, z, carton.mean(0)[None])
    _, _, far = layer.apply(prob, z, (carton.mean(0) + np.log(100.0))[None])   # 15 m
    assert inside[0] <= 1.0 < far[0]
    assert layer.apply(prob, z, None)[2] is None          # no sizes: no size region
    # a bin-sized query answered 'carton' by the head: moved to the bin, inside its region
    p, _, flag = layer.apply(prob, z, bins.mean(0)[None])
    assert p.argmax().item() == bin_id and flag[0] <= 1.0
    many = add_taught(meta, 'carton', torch.nn.functional.normalize(
        torch.eye(4)[[2] * 30], dim=1), np.repeat(carton, 6, axis=0))
    assert len(many[KEY]['carton']['sizes']) == KEPT_SIZES


def test_a_metric_query_like_a_taught_class_takes_it_from_the_built_one_the_head_prefers() -> None:
    from point_gn_ros.bank.taught import add_taught
    names = ['person', 'lamp', 'pedestrian', 'pole']
    rng = np.random.default_rng(3)
    walker = np.log([1.7, 0.6, 0.4, 0.45, 0.15, 0.1]) + rng.normal(0, 0.05, (5, SIZE_DIM))
    mast = np.log([4.0, 0.3, 0.25, 1.1, 0.08, 0.06]) + rng.normal(0, 0.05, (5, SIZE_DIM))
    scans = torch.nn.functional.normalize(torch.tensor([[0.3, 0.0, 1.0, 0.0]] * 5), dim=1)
    meta = add_taught({}, 'pedestrian', scans, walker)
    meta = add_taught(meta, 'pole', torch.nn.functional.normalize(
        torch.tensor([[0.0, 0.3, 0.0, 1.0]] * 5), dim=1), mast)
    layer = _layer(json.loads(json.dumps(meta)), names)
    # the head, fitted on CAD rows, gives a pedestrian's scan to the built 'person'
    head = torch.tensor([[0.9, 0.04, 0.03, 0.03]])
    z = torch.nn.functional.normalize(torch.tensor([[0.35, 0.0, 1.0, 0.05]]), dim=1)
    p, fit, _ = layer.apply(head, z, walker.mean(0)[None])
    assert p.argmax().item() == 2 and p[0, 2] > 0.6
    # without sizes (unit-sphere data) the head's share of the taught block stays
    p_none, _, _ = layer.apply(head, z, None)
    assert p_none.argmax().item() == 0
    assert abs(float(p_none[0, 2:].sum()) - 0.06) < 1e-4
    # a metric query unlike both taught classes (a lamp-shaped 80 cm thing) is judged
    # against the taught classes only: its fit to every class would pass the default threshold
    odd = torch.nn.functional.normalize(torch.tensor([[0.2, 1.0, 0.0, 0.0]]), dim=1)
    lamp = np.log([0.8, 0.4, 0.3, 0.2, 0.1, 0.08])[None]
    _, fit_odd, _ = layer.apply(head, odd, lamp)
    every = layer.fit(odd.double().numpy(), layer.plausibility(lamp))
    assert fit_odd[0] < DEFAULT_FIT_THRESHOLD < every[0]
    assert fit[0] > DEFAULT_FIT_THRESHOLD
    # judged against taught classes, the whole size distance counts: of two scans of the
    # same shape, both inside the pedestrian's size region, the one of its typical size fits
    # better (the region-clipped fit, which the lead uses, ties them)
    sd = np.sqrt(layer.size_var[2])
    near, off = walker.mean(0), walker.mean(0) + sd
    assert (-2 * layer.plausibility(off[None])[0, 2]) < layer.region[2]
    _, fits, _ = layer.apply(head.repeat(2, 1), z.repeat(2, 1), np.stack([near, off]))
    assert fits[0] > fits[1] + 0.05
    clipped = layer.fits(z.repeat(2, 1).double().numpy(),
                         layer.plausibility(np.stack([near, off])))[:, 2]
    assert clipped[0] == clipped[1]


@pytest.fixture(scope='module')
def default_recognizer():
    from point_gn_ros.recognizer import Recognizer
    return Recognizer.from_bank(None)


def test_garbage_and_impossible_sizes_are_unknown_at_the_default_rule(default_recognizer) -> None:
    from point_gn_ros.recognizer import Recognizer
    rec = Recognizer(default_recognizer.bank, encoder=default_recognizer.encoder,
                     fit_threshold=fit_rule(DEFAULT_FIT_THRESHOLD))
    rng = np.random.default_rng(0)
    garbage = rng.normal(size=(500, 3)).astype('>f4').view('<f4').astype(np.float32)
    garbage = garbage[np.isfinite(garbage).all(1)]
    huge = _box(rng, (300.0, 200.0, 150.0), 800)
    res = rec.classify_clouds([garbage, huge])
    assert (res.labels == -1).all(), res.fit
    # the same rule keeps a plausibly sized object
    from point_gn_ros.clients.node_client import load_demo_objects, place_in_sensor_frame
    objs = load_demo_objects()
    i = objs.class_names.index('chair')
    chair = place_in_sensor_frame(objs.xyz[int(np.flatnonzero(objs.labels == i)[0])], rng,
                                  class_name='chair')
    assert rec.classify_clouds([chair]).labels[0] != -1


def test_fewshot_bank_runs_the_teach_and_query_protocol(tmp_path: Path, capsys) -> None:
    if not TABLETOP.is_dir():
        pytest.skip(f'{TABLETOP} absent (the shared tabletop data set)')
    from point_gn_ros.cli import main
    for name in ('fork', 'plate', 'cocacola'):
        (tmp_path / name).mkdir()
        for f in sorted((TABLETOP / name).glob('*.npy'))[:8]:
            (tmp_path / name / f.name).write_bytes(f.read_bytes())
    assert main(['fewshot', str(tmp_path), '--bank', 'default', '--shots', '3', '--draws', '2',
                 '--json']) == 0
    rep = json.loads(capsys.readouterr().out)
    summ = rep['summary']
    assert rep['metric_size'] and rep['shots'] == 3 and len(rep['per_draw']) == 2
    for key in ('accuracy', 'built_share', 'nearest_mean', 'geometry', 'auroc_fit', 'auroc_size',
                'auroc_top_probability', 'unseen_rejected', 'taught_rejected',
                'structure_rejected'):
        assert 0.0 <= summ[key]['mean'] <= 1.0, key
    # views are surfaces of one object: only fork_13, its handle and tines raised apart above
    # its low middle, is measured as parts (3 of the 1,200 tabletop views; docs/SIZE.md)
    assert summ['structure_rejected']['mean'] <= 1 / 15
    # three distinct objects, sizes in metres: taught they are told apart
    assert summ['accuracy']['mean'] >= 0.8


def test_bank_add_keeps_measured_sizes_in_metres_and_none_without_units(
        small_bank_path: Path, tmp_path: Path) -> None:
    from point_gn_ros.bank.enroll import BankFile
    from point_gn_ros.cli import main
    rng = np.random.default_rng(3)
    folder = tmp_path / 'carton'
    folder.mkdir()
    for i in range(3):                           # a 10 x 5 x 20 cm carton, anywhere
        np.save(folder / f'{i}.npy', _box(rng, (0.1, 0.05, 0.2), 600) + rng.normal(size=3))
    out_m, out_none = tmp_path / 'm.npz', tmp_path / 'none.npz'
    assert main(['bank', 'add', str(small_bank_path), str(folder), '--class', 'carton',
                 '-o', str(out_m)]) == 0
    rec = BankFile.load(out_m).bank.meta[KEY]['carton']
    assert rec['n'] == 3 and rec['sn'] == 3
    assert np.allclose(np.exp(rec['smean'][:3]), [0.2 * 0.96, 0.1 * 0.96, 0.05 * 0.96],
                       rtol=0.1)
    assert main(['bank', 'add', str(small_bank_path), str(folder), '--class', 'carton',
                 '--units', 'none', '-o', str(out_none)]) == 0
    rec = BankFile.load(out_none).bank.meta[KEY]['carton']
    assert rec['n'] == 3 and 'sn' not in rec


def test_node_enrollment_engine_keeps_the_recognizers_measured_sizes(tmp_path: Path) -> None:
    from point_gn_ros.bank.enroll import BankFile
    from point_gn_ros.bank.live import LiveBank
    from point_gn_ros.bank.store import FeatureBank
    from point_gn_ros.bank.model import FeatureTransform
    from point_gn_ros.core.config import EncoderConfig
    from point_gn_ros.core.size import size_descriptors
    from point_gn_ros.node.enroll_engine import EnrollEngine

    dim = EncoderConfig().feature_dim

    class Rec:                                   # the Recognizer's encode / sizes contract
        def __init__(self, metric: bool) -> None:
            self.metric = metric

        def encode(self, clouds: list[np.ndarray], augment: str = 'none') -> torch.Tensor:
            return torch.stack([torch.full((dim,), float(c[0, 0])) + torch.arange(dim)
                                for c in clouds])

        def sizes(self, clouds: list[np.ndarray]) -> np.ndarray | None:
            return size_descriptors(clouds) if self.metric else None

    raw = torch.randn(12, dim, generator=torch.Generator().manual_seed(0))
    tf = FeatureTransform.fit(raw, 'none')
    bank = FeatureBank(features=tf(raw), labels=torch.arange(12) % 3, class_names=['a', 'b', 'c'],
                       config=EncoderConfig(), transform=tf, gamma=10.0)
    rng = np.random.default_rng(4)
    clouds = [_box(rng, (0.3, 0.1, 0.5), 200) for _ in range(5)]
    for metric in (True, False):
        live = LiveBank(BankFile.of(bank, 'float32'), lambda active: active.num_classes)
        eng = EnrollEngine(live, lambda snap, res: None, log=lambda text: None,
                           warn=lambda key, text: None, chunk=2, max_pending=100,
                           capture_max=5, min_points=4)
        assert eng.submit('bin', clouds, 'test')[0]
        while eng.step(Rec(metric)):              # three steps of <= 2 clouds
            pass
        eng.flush(10.0)
        rec = live.current().bank.meta[KEY]['bin']
        eng.close()
        assert rec['n'] == 5
        if metric:
            assert rec['sn'] == 5 and np.allclose(rec['smean'],
                                                  size_descriptors(clouds).mean(0), atol=1e-5)
        else:
            assert 'sn' not in rec


def test_the_classifiers_fit_rule_makes_an_answer_outside_its_size_region_unknown() -> None:
    from point_gn_ros.bank.classifier import Classifier
    from point_gn_ros.bank.enroll import BankFile, add_examples
    from point_gn_ros.bank.store import FeatureBank
    from point_gn_ros.bank.model import FeatureTransform
    from point_gn_ros.core.config import EncoderConfig
    from point_gn_ros.core.size import size_descriptors

    dim = EncoderConfig().feature_dim
    gen = torch.Generator().manual_seed(1)
    raw = torch.randn(30, dim, generator=gen)
    tf = FeatureTransform.fit(raw, 'none')
    bank = FeatureBank(features=tf(raw), labels=torch.arange(30) % 3,
                       class_names=['chair', 'desk', 'lamp'], config=EncoderConfig(),
                       transform=tf, gamma=10.0)
    rng = np.random.default_rng(5)
    cartons = [_box(rng, (0.1, 0.06, 0.15), 400) for _ in range(5)]
    feats = torch.randn(1, dim, generator=gen) + 0.05 * torch.randn(5, dim, generator=gen)
    taught = add_examples(BankFile.of(bank, 'float32'), feats, 'carton',
                          sizes=size_descriptors(cartons)).file.bank
    query = feats[:2]
    at_size = size_descriptors(cartons[:2])
    ten_times = size_descriptors([c * 10 for c in cartons[:2]])
    ruled = Classifier(taught, fit_threshold=-5.0)        # a fit rule that never fires itself
    carton = taught.class_names.index('carton')
    res = ruled.classify(query, top_k=1, sizes=at_size)
    assert (res.labels == carton).all() and (res.size_misfit <= 1).all()
    res = ruled.classify(query, top_k=1, sizes=ten_times)
    assert (res.labels == -1).all() and (res.size_misfit > 1).all()
    # no fit rule: the same answers stand, the misfit still reported
    res = Classifier(taught).classify(query, top_k=1, sizes=ten_times)
    assert (res.labels >= 0).all() and (res.size_misfit > 1).all()
