#!/usr/bin/env python3
"""How sparse clusters are brought up to 1,024 points, chosen by grouped CV on scans.

A single-view scan keeps ~340 of an object's 1,024 points; `sampling.resample` repeats every
point about 3 times to reach 1,024, so the encoder's 120 neighbours of a centre are ~40
distinct points. This study encodes the same simulated HPR scans (every N-th train object,
4 scans each, random yaw, yaw-aligned encoder: the default bank's scan section) with other
ways of filling the missing points, and re-chooses the scan section's head by 5-fold CV
grouped by object for each (the same folds): train split only, the test split is not read.

  repeat   every point kept, then points repeated in (x, y, z) order (today)
  midpoint `sampling.midpoint_fill` (EncoderConfig.upsample='midpoint'): every point kept,
           then midpoints of each point and its r-th nearest neighbour (r = 1, 2, ...):
           new points on the surface between neighbours
  unique   (study only) midpoint without repeated pairs: a pair of mutual neighbours gives
           one midpoint, the next pairs by neighbour rank fill the rest
  jitter   (study only) repeated points displaced by Gaussian noise of `--jitter` x the median
           nearest-neighbour distance, seeded by the point's coordinates (order-free)

    python experiments/upsample_study.py ../shared/datasets/modelnet40_1024 --subset 6 \
        --variants repeat midpoint jitter
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from point_gn_ros.bank import selection
from point_gn_ros.core import sampling
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.core.views import VIEW_PROTOCOLS
from point_gn_ros.datasets import open_dataset
from point_gn_ros.datasets.views import ViewsDataset
from point_gn_ros.recognizer import encode_clouds, make_encoder

_REPEAT = sampling.resample


def jitter_fill(xyz: np.ndarray, n: int, scale: float) -> np.ndarray:
    """Repeated points moved by seeded noise of `scale` x the median neighbour spacing."""
    out = _REPEAT(xyz, n)
    count = len(xyz)
    if count < 2:
        return out
    spacing = float(np.median(np.sqrt(((xyz[:, None] - xyz[None]) ** 2).sum(-1)
                                      + np.eye(count) * 1e30).min(1)))
    seed = int(np.ascontiguousarray(xyz, np.float32).view(np.uint32).sum(dtype=np.uint64))
    noise = np.random.default_rng(seed).normal(0, scale * spacing, out.shape)
    noise[:count] = 0.0
    return (out + noise).astype(np.float32)


def unique_midpoint_fill(xyz: np.ndarray, n: int) -> np.ndarray:
    """midpoint_fill without repeated pairs (a and b each other's neighbour give one midpoint).

    Pairs are taken by neighbour rank, then by a coordinate hash of the point (study only).
    """
    from scipy.spatial import cKDTree
    xyz = xyz[sampling.canonical_order(xyz)]
    count = len(xyz)
    if count < 2:
        return xyz[np.arange(n) % count]
    k = min(count - 1, 2 * -(-(n - count) // count) + 2)
    _, nb = cKDTree(xyz).query(xyz, k=k + 1)
    rank = np.empty(count, np.int64)
    rank[sampling.hashed_subset(xyz, count)] = np.arange(count)
    seen, pairs = set(), []
    for r in range(1, k + 1):
        for i in np.argsort(rank):
            a, b = sorted((int(i), int(nb[i, r])))
            if a != b and (a, b) not in seen:
                seen.add((a, b))
                pairs.append((a, b))
        if len(pairs) >= n - count:
            break
    while len(pairs) < n - count:          # tiny clouds: cycle
        pairs += pairs[:n - count - len(pairs)]
    p = np.asarray(pairs[:n - count])
    return np.concatenate([xyz, (xyz[p[:, 0]] + xyz[p[:, 1]]) * np.float32(0.5)]).astype(
        np.float32)


def make_resample(jitter: float, fill=None):
    """sampling.resample with the 'repeat' fill replaced by `jitter_fill` (study only)."""
    def resample(xyz, n, method='fps', seed=0, upsample='repeat'):  # noqa: ANN001, ANN202
        xyz = np.ascontiguousarray(xyz, dtype=np.float32)
        if len(xyz) >= n:
            return _REPEAT(xyz, n, method, seed)
        return fill(xyz, n) if fill is not None else jitter_fill(xyz, n, jitter)
    return resample


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('dataset')
    p.add_argument('--subset', type=int, default=6)
    p.add_argument('--views', type=int, default=4)
    p.add_argument('--dims', type=int, nargs='+', default=[320])
    p.add_argument('--jitter', type=float, default=0.5)
    p.add_argument('--variants', nargs='+', default=['repeat', 'midpoint', 'jitter'])
    p.add_argument('--out', default=None)
    args = p.parse_args()
    torch.set_num_threads(1)
    train = open_dataset(args.dataset, split='train')
    sources = np.arange(0, len(train), args.subset)
    ds = ViewsDataset(train, args.views, 0, VIEW_PROTOCOLS['hpr'][0], include_full=False,
                      random_yaw=True, memoize=True, sources=sources)
    labels = np.asarray(ds.labels).astype(np.int64)
    groups = np.asarray(ds.groups)
    encoders = {u: make_encoder(EncoderConfig(yaw_align=True, upsample=u))
                for u in ('repeat', 'midpoint')}
    grid = dict(alphas=(0.1,), weights=(0.1, 0.2, 0.3), dims_options=tuple(args.dims))
    base = None
    for variant in args.variants:
        t0 = time.time()
        if variant == 'jitter':
            sampling.resample = make_resample(args.jitter)
        if variant == 'unique':
            sampling.resample = make_resample(args.jitter, unique_midpoint_fill)
        try:
            feats = encode_clouds((ds[i][0] for i in range(len(ds))),
                                  encoders['midpoint' if variant == 'midpoint' else 'repeat'],
                                  total=len(ds))
        finally:
            sampling.resample = _REPEAT
        t1 = time.time()
        sel = selection.select(feats, labels, 40, standardize_options=('standardize',),
                               groups=groups, **grid)
        correct = sel.heldout_correct.astype(float)
        row = {'variant': variant, 'n': len(labels), 'cv_accuracy': sel.cv_accuracy,
               'vote_cv_accuracy': sel.vote_cv_accuracy, 'gamma': sel.gamma,
               'weight': sel.fusion_weight, 'encode_s': round(t1 - t0), 'cv_s':
               round(time.time() - t1)}
        if base is None:
            base = correct
        else:
            # paired difference, its standard error over source objects
            per_obj = np.bincount(np.unique(groups, return_inverse=True)[1],
                                  weights=correct - base)
            row['diff'] = float((correct - base).mean())
            row['diff_se'] = float(per_obj.std(ddof=1) * np.sqrt(len(per_obj)) / len(correct))
        print(json.dumps(row), flush=True)
        if args.out:
            with open(args.out, 'a') as fh:
                fh.write(json.dumps(row) + '\n')


if __name__ == '__main__':
    main()
