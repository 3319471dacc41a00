"""Scan protocol of a sensor bank's views, chosen by grouped k-fold CV on train only.

Bank candidates on every 9th ModelNet40 train object (complete object + 4 scans each, same
size): 'hpr_only' (4 hidden-point-removal scans, `make sensor-bank`) and 'mixed' (2 HPR + 2
z-buffer scans, `--view-protocol mixed`). Queries: the held-out objects' 4 HPR scans, 4 z-buffer
scans and complete cloud; folds grouped by object; fixed head (224 dims, whitening 0.1, LDA
0.02, weight 0.3), gamma by inner grouped CV. Never touches the test split.

    python experiments/mixed_protocol_study.py ../shared/datasets/modelnet40_1024 --cache DIR
"""

from __future__ import annotations

import argparse
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

from point_gn_ros.bank.builder import build_bank, encode_dataset
from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.bank.selection import stratified_folds
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.core.views import ZBUFFER_VIEW_CONFIG
from point_gn_ros.datasets import open_dataset
from point_gn_ros.datasets.views import ViewsDataset
from point_gn_ros.recognizer import make_encoder


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('dataset')
    p.add_argument('--cache', required=True)
    p.add_argument('--subset', type=int, default=9, help='every n-th train object')
    args = p.parse_args()
    train = open_dataset(args.dataset, split='train')
    cache = Path(args.cache)
    enc = make_encoder(EncoderConfig(yaw_align=True))
    sub = np.arange(0, len(train), args.subset)
    # HPR rows come from the full sensor-bank feature set (same scans, cached by make sensor-bank).
    hpr = ViewsDataset(train, 4, 0, include_full=True, random_yaw=True)
    rows = np.isin(hpr.groups, sub)
    fh = encode_dataset(hpr, enc, cache_dir=cache)[rows]
    yh, gh, vh = hpr.labels[rows], hpr.groups[rows], hpr.view_index[rows]
    zb = ViewsDataset(train, 4, 0, ZBUFFER_VIEW_CONFIG, include_full=False, random_yaw=True,
                      sources=sub)
    fz = encode_dataset(zb, enc, cache_dir=cache)
    yz, gz, vz = zb.labels, zb.groups, zb.view_index
    res: dict[str, dict[str, list[bool]]] = {
        k: {'hpr': [], 'zbuffer': [], 'complete': []} for k in ('hpr_only', 'mixed')}
    for test_idx in stratified_folds(train.labels[sub], 5):
        th, tz = np.isin(gh, sub[test_idx]), np.isin(gz, sub[test_idx])
        banks = {'hpr_only': (fh[~th], yh[~th], gh[~th]),
                 'mixed': (torch.cat([fh[~th & (vh < 2)], fz[~tz & (vz >= 2)]]),
                           np.concatenate([yh[~th & (vh < 2)], yz[~tz & (vz >= 2)]]),
                           np.concatenate([gh[~th & (vh < 2)], gz[~tz & (vz >= 2)]]))}
        for name, (bf, by, bg) in banks.items():
            ds = SimpleNamespace(labels=by, class_names=train.class_names, path='memory',
                                 split='cv', format='array')
            bank = build_bank(ds, encoder=enc, feats=bf, groups=bg, folds=3, progress=False,
                              standardize_options=('standardize',), dims_options=(224,),
                              alphas=(0.1,), weights=(0.3,), lda_alphas=(0.02,))
            clf = Classifier(bank)
            for q, qf, qy in (('hpr', fh[th & (vh >= 0)], yh[th & (vh >= 0)]),
                              ('zbuffer', fz[tz], yz[tz]),
                              ('complete', fh[th & (vh < 0)], yh[th & (vh < 0)])):
                res[name][q] += (np.asarray(clf.classify(qf).labels) == qy).tolist()
    for name, r in res.items():
        print(name, {q: f'{100 * float(np.mean(v)):.2f} %' for q, v in r.items()})


if __name__ == '__main__':
    main()
