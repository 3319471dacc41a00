"""A sensor-realistic bank beats a complete-object bank on single-view scans (CI-sized subset)."""

from conftest import ArrayDataset, load_modelnet_subset
import numpy as np

from point_gn_ros.bank.builder import build_bank
from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.bank.builder import RowsDataset, combine_sections
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.datasets.views import ViewsDataset
from point_gn_ros.recognizer import encode_clouds, make_encoder


def test_views_bank_beats_complete_bank_on_single_view_scans() -> None:
    # 10 train objects per class; queries: one single-view scan (noise, random yaw) of each of
    # 5 held-out test objects per class. Both banks yaw-aligned, knobs by CV on the bank.
    train_xyz, train_y, names = load_modelnet_subset('train', 10)
    test_xyz, test_y, _ = load_modelnet_subset('test', 5)
    enc = make_encoder(EncoderConfig(yaw_align=True))
    views = ViewsDataset(ArrayDataset(train_xyz, train_y, names), 2, seed=0, random_yaw=True)
    feats = encode_clouds((views[i][0] for i in range(len(views))), enc, total=len(views))
    full = views.view_index < 0
    complete_bank = build_bank(ArrayDataset(train_xyz, train_y, names), encoder=enc, folds=3,
                               feats=feats[full], progress=False)
    views_bank = build_bank(views, encoder=enc, folds=3, feats=feats, groups=views.groups,
                            progress=False)
    assert views_bank.meta['selection']['cv_grouped']
    scans = ViewsDataset(ArrayDataset(test_xyz, test_y, names), 1, seed=1, include_full=False,
                         random_yaw=True)
    q = encode_clouds((scans[i][0] for i in range(len(scans))), enc, total=len(scans))
    scan_only = build_bank(RowsDataset(views, ~full, 'scans'), encoder=enc, folds=3,
                           feats=feats[~full], groups=views.groups[~full], progress=False)
    sections = combine_sections(complete_bank, scan_only, feats, ~full)
    banks = (('complete', complete_bank), ('views', views_bank), ('sections', sections))
    acc = {name: float((Classifier(bank).classify(q).labels == test_y).mean())
           for name, bank in banks}
    whole = ViewsDataset(ArrayDataset(test_xyz, test_y, names), 0, seed=1, random_yaw=True)
    qc = encode_clouds((whole[i][0] for i in range(len(whole))), enc, total=len(whole))
    acc_c = {name: float((Classifier(bank).classify(qc).labels == test_y).mean())
             for name, bank in banks}
    # Measured on this subset (hidden point removal, simulator version 3): complete 0.325,
    # views 0.620 (200 scans; chance 0.025); the margin asserted leaves room for noise (one
    # scan is 0.005; z-buffer scans of round 1 measured 0.140 vs 0.335).
    assert acc['views'] >= acc['complete'] + 0.20, acc
    # The two-section bank keeps both: measured here scans SCANS, complete objects at a random
    # yaw COMPLETE (complete-object bank CBANK, one-head views bank VBANK).
    assert acc['sections'] >= acc['complete'] + 0.15, acc
    assert acc_c['sections'] >= acc_c['complete'] - 0.06, acc_c
    assert np.all(views_bank.labels.numpy() == np.repeat(train_y, 3))


def test_midpoint_fill_beats_repeated_points_on_single_view_scans() -> None:
    # Scan-only banks (2 scans of each of 10 train objects per class) that differ only in how
    # a sparse scan is filled up to 1024 points (EncoderConfig.upsample); queries: two scans of
    # each of 10 held-out test objects per class. Knobs by grouped CV on each bank.
    train_xyz, train_y, names = load_modelnet_subset('train', 10)
    test_xyz, test_y, _ = load_modelnet_subset('test', 10)
    views = ViewsDataset(ArrayDataset(train_xyz, train_y, names), 2, seed=0,
                         include_full=False, random_yaw=True, memoize=True)
    scans = ViewsDataset(ArrayDataset(test_xyz, test_y, names), 2, seed=1, include_full=False,
                         random_yaw=True, memoize=True)
    acc = {}
    for upsample in ('repeat', 'midpoint'):
        enc = make_encoder(EncoderConfig(yaw_align=True, upsample=upsample))
        feats = encode_clouds((views[i][0] for i in range(len(views))), enc, total=len(views))
        bank = build_bank(views, encoder=enc, folds=3, feats=feats, groups=views.groups,
                          progress=False)
        assert bank.config.upsample == upsample
        q = encode_clouds((scans[i][0] for i in range(len(scans))), enc, total=len(scans))
        acc[upsample] = float((Classifier(bank).classify(q).labels == scans.labels).mean())
    # Measured on this subset: repeat 0.565, midpoint 0.6125 (800 scans; one scan is
    # 0.00125); the margin asserted is half the measured one.
    assert acc['midpoint'] >= acc['repeat'] + 0.024, acc
