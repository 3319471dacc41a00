"""Two-section bank (complete objects | single-view scans) with a gate, by grouped CV on train.

Feasibility study for issue 9: does a bank whose complete objects and scans have separate heads
(each with its own transform, whitening, LDA, gamma), combined by a gate that estimates whether a
query is a partial scan, keep complete-object accuracy while recognising scans? Reads the
cached features of `make sensor-bank` (every train object complete + 4 HPR scans, yaw-aligned);
every `--subset`-th object, 5 folds grouped by object; never touches the test split.

    python experiments/gated_study.py ../shared/datasets/modelnet40_1024 --cache DIR
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from point_gn_ros.bank.builder import encode_dataset
from point_gn_ros.bank.discriminant import fit_head
from point_gn_ros.bank.discriminant import fit_gate
from point_gn_ros.bank.selection import stratified_folds
from point_gn_ros.bank.model import FeatureTransform
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.core.views import VIEW_PROTOCOLS
from point_gn_ros.datasets import open_dataset
from point_gn_ros.datasets.views import ViewsDataset
from point_gn_ros.recognizer import make_encoder
from point_gn_ros.bank.vote import ExactSearch, reference_head


def expert(feats, labels, tr, c, dims, gamma, alpha, lda_alpha, w, t):  # noqa: ANN001, ANN201
    """Fit transform + head on rows tr; return a function rows -> (probability, novelty)."""
    tf = FeatureTransform.fit(feats[tr], 'standardize', dims)
    z = tf(feats[tr])
    lab = torch.from_numpy(labels[tr])
    head = fit_head(z, lab, c, gamma, alpha, lda_alpha, w, t)
    u = head.vote_space(z)
    return lambda q: reference_head(head, tf(q), ExactSearch(u, lab, c))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('dataset')
    p.add_argument('--cache', required=True)
    p.add_argument('--subset', type=int, default=3)
    p.add_argument('--scan-dims', type=int, nargs='+', default=[224])
    p.add_argument('--complete-dims', type=int, default=640)
    p.add_argument('--scan-includes-complete', action='store_true')
    args = p.parse_args()
    torch.set_num_threads(2)
    train = open_dataset(args.dataset, split='train')
    c = len(train.class_names)
    ds = ViewsDataset(train, 4, 0, VIEW_PROTOCOLS['hpr'][0], include_full=True, random_yaw=True)
    feats = encode_dataset(ds, make_encoder(EncoderConfig(yaw_align=True)),
                           cache_dir=Path(args.cache))
    rows = np.flatnonzero(ds.groups % args.subset == 0)
    feats, labels = feats[rows], np.asarray(ds.labels)[rows].astype(np.int64)
    groups, scan = ds.groups[rows], ds.view_index[rows] >= 0
    parts = stratified_folds(labels, 5, 0, groups)
    out: dict[str, np.ndarray] = {}

    def put(name: str, va: np.ndarray, pred: torch.Tensor) -> None:
        out.setdefault(name, np.zeros(len(labels), dtype=bool))[va] = (
            pred.numpy() == labels[va])

    gate_right = np.zeros(len(labels), dtype=bool)
    for fi, va in enumerate(parts):
        tr = np.setdiff1d(np.arange(len(labels)), va)
        q = feats[va]
        one = expert(feats, labels, tr, c, 224, 40.0, 0.1, 0.02, 0.3, 2.93)
        p_one = one(q)[0]
        put('single head (sensor bank recipe)', va, p_one.argmax(1))
        trc = tr[~scan[tr]]
        comp = expert(feats, labels, trc, c, args.complete_dims, 80.0, 0.1, 0.02, 0.2, 3.98)
        p_c = comp(q)[0]
        put('complete expert alone', va, p_c.argmax(1))
        g = fit_gate(feats[tr], scan[tr]).scan_probability(q)
        gate_right[va] = (g.numpy() > 0.5) == scan[va]
        for sd in args.scan_dims:
            trs = tr if args.scan_includes_complete else tr[scan[tr]]
            sc = expert(feats, labels, trs, c, sd, 40.0, 0.1, 0.02, 0.3, 2.93)
            p_s = sc(q)[0]
            put(f'scan expert alone {sd}', va, p_s.argmax(1))
            put(f'gated hard {sd}', va, torch.where((g > 0.5)[:, None], p_s, p_c).argmax(1))
            put(f'gated soft {sd}', va, (g[:, None] * p_s + (1 - g[:, None]) * p_c).argmax(1))
            put(f'oracle gate {sd}', va, torch.where(torch.from_numpy(scan[va])[:, None],
                                                     p_s, p_c).argmax(1))
        print(f'fold {fi} done', flush=True)
    res = {k: {'complete': float(v[~scan].mean()), 'scans': float(v[scan].mean())}
           for k, v in out.items()}
    res['gate accuracy'] = {'complete': float(gate_right[~scan].mean()),
                            'scans': float(gate_right[scan].mean())}
    print(json.dumps(res, indent=1))


if __name__ == '__main__':
    main()
