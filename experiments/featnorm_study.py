#!/usr/bin/env python3
"""Elementwise / per-block transforms of the raw encoder features before the head, by CV.

Issue 8 follow-up: does power normalisation (sign(x)|x|^a), log compression or a per-block
normalisation of the 1,620-dim Point-GN features (4 stages x [max block, mean block]) help
the discriminant head? Every variant re-chooses the whole head (`selection.select`) by
k-fold CV on the SAME folds as the baseline (identity); train split only, never the test
split. Prints CV accuracy per variant, the paired difference to the baseline and its
standard error (per-object correctness, same folds).

  aligned: complete train objects, encoder as shipped without yaw alignment
           (accuracy_study grid: standardise, full width, every shrinkage / weight)
  yaw:     yaw-aligned complete train objects (the default bank's complete section and its
           `make default-bank` grid: dims 512 640, whitening 0.1, weights 0.1-0.3)
  scans:   the default bank's scan section (4 HPR scans per object, yaw-aligned), folds
           grouped by object, its grid: dims 224 320, whitening 0.1, weights 0.1-0.3

    python experiments/featnorm_study.py ../shared/datasets/modelnet40_1024 --cache DIR \
        --setting aligned --subset 3 --variants base pow0.5 blockl2

Two-encoder concatenation (issue 8): a variant `cat:KEY=VAL,...` appends the raw features
of the same objects encoded by a second EncoderConfig (the setting's config with these
overrides, e.g. `cat:sigma=0.5`, `cat:k=60,sigma=0.4`, `cat:init_dim=18,stages=3`) to the
base features; `only:KEY=VAL,...` uses the second encoder's features alone.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
import json
from pathlib import Path
import time
from unittest import mock

import numpy as np
import torch

from point_gn_ros.bank import selection
from point_gn_ros.bank.builder import encode_dataset
from point_gn_ros.bank.model import FeatureTransform
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.datasets import open_dataset
from point_gn_ros.core.sampling import rotate_z
from point_gn_ros.recognizer import encode_clouds, make_encoder


def block_slices(cfg: EncoderConfig) -> list[slice]:
    """The encoder's output blocks, in order: per stage its max block, then its mean block."""
    out, off = [], 0
    for d in cfg.stage_dims:
        for _ in range(2):
            out.append(slice(off, off + d))
            off += d
    return out


def _power(a: float) -> Callable[[torch.Tensor], torch.Tensor]:
    return lambda x: x.sign() * x.abs().pow(a)


def _log(c: float) -> Callable[[torch.Tensor], torch.Tensor]:
    return lambda x: x.sign() * torch.log1p(c * x.abs())


def _block_l2(blocks: list[slice]) -> Callable[[torch.Tensor], torch.Tensor]:
    def f(x: torch.Tensor) -> torch.Tensor:
        return torch.cat([torch.nn.functional.normalize(x[:, s], dim=1) for s in blocks], 1)
    return f


def _block_z(blocks: list[slice]) -> Callable[[torch.Tensor], torch.Tensor]:
    def f(x: torch.Tensor) -> torch.Tensor:
        return torch.cat([torch.nn.functional.normalize(x[:, s] - x[:, s].mean(1, keepdim=True),
                                                        dim=1) for s in blocks], 1)
    return f


def _rank_gauss(x: torch.Tensor) -> torch.Tensor:
    """Each dimension through its empirical CDF and the normal quantile.

    Exploration only: the ranks use every row given, held-out folds included (label-free).
    """
    r = (x.argsort(0).argsort(0).double() + 0.5) / x.shape[0]
    return (torch.special.ndtri(r)).float()


def _row_l2(x: torch.Tensor) -> torch.Tensor:
    return torch.nn.functional.normalize(x, dim=1)


def variants(cfg: EncoderConfig) -> dict[str, Callable[[torch.Tensor], torch.Tensor]]:
    """Name -> elementwise / per-row map of raw features (N, 1620) -> (N, 1620)."""
    blocks = block_slices(cfg)
    bl2 = _block_l2(blocks)
    return {'base': lambda x: x, 'pow0.75': _power(0.75), 'pow0.5': _power(0.5),
            'pow0.25': _power(0.25), 'pow1.5': _power(1.5), 'pow2': _power(2.0),
            'blockz': _block_z(blocks), 'rankgauss': _rank_gauss,
            'log1': _log(1.0), 'log100': _log(100.0),
            'rowl2': _row_l2, 'blockl2': bl2,
            'blockl2+pow0.5': lambda x: bl2(_power(0.5)(x)),
            'blockeq': lambda x: x,      # weighting after standardisation: see _block_weights
            'sqrtwidth': lambda x: x}


def _block_weights(name: str, blocks: list[slice], d: int) -> torch.Tensor | None:
    """Per-dimension weights applied after standardisation (None: none).

    blockeq: every block the same total energy (a standardised block of width w has w);
    sqrtwidth: halfway (energy ~ sqrt(w)).
    """
    if name not in ('blockeq', 'sqrtwidth'):
        return None
    w = torch.ones(d)
    for s in blocks:
        width = s.stop - s.start
        w[s] = width ** (-0.5 if name == 'blockeq' else -0.25)
    return w


class _Weighted(FeatureTransform):
    """FeatureTransform.fit whose standardised dims are then weighted (scale / weight)."""

    weights: torch.Tensor | None = None

    @classmethod
    def fit(cls, feats: torch.Tensor, standardize='standardize', dims=None):  # noqa: ANN001, ANN206
        if cls.weights is None:
            return FeatureTransform.fit(feats, standardize, dims)
        base = FeatureTransform.fit(feats, standardize, None)
        scale = base.scale / cls.weights
        z = (feats.float() - base.mean) / scale
        proj = None
        if dims is not None and dims < feats.shape[1]:
            _, _, v = torch.linalg.svd(z - z.mean(0), full_matrices=False)
            proj = v[:dims].T.contiguous()
        return FeatureTransform(base.mean, scale, proj)


def paired_diff(a: np.ndarray, b: np.ndarray, groups: np.ndarray | None) -> tuple[float, float]:
    """Mean of a - b (per-entry 0/1 correctness, same folds) and its standard error.

    groups: (N,) or None; an object's scans are not independent, so with groups the error is
    the cluster-robust one (the differences summed per object).
    """
    d = a - b
    if groups is None:
        return float(d.mean()), float(d.std(ddof=1) / np.sqrt(len(d)))
    _, inv = np.unique(groups, return_inverse=True)
    per = np.bincount(inv, weights=d)
    size = np.bincount(inv).astype(float)
    g, mean = len(per), d.mean()
    var = g / (g - 1) * float(((per - size * mean) ** 2).sum()) / len(d) ** 2
    return float(mean), float(np.sqrt(var))


def parse_overrides(spec: str) -> dict[str, int | float]:
    """'k=60,sigma=0.4' -> {'k': 60, 'sigma': 0.4} (EncoderConfig keys)."""
    out: dict[str, int | float] = {}
    for item in spec.split(','):
        key, val = item.split('=')
        out[key] = float(val) if key == 'sigma' else int(val)
    return out


def second_features(args: argparse.Namespace, cfg: EncoderConfig, spec: str,
                    sources: np.ndarray, rows: np.ndarray) -> torch.Tensor:
    """The setting's rows encoded by cfg + overrides: -> (M, D2).

    sources (M,): the complete train object of each row; rows (M,): for scans, the rows of
    the scan section's ViewsDataset (its scans encoded again, cached by encode_dataset).

    aligned: the stored objects (encode_dataset's cache); yaw: each object at the same random
    yaw as ViewsDataset(random_yaw=True, seed 0) gives its complete item (first angle of its
    draw), cached here under the config's hash.
    """
    from dataclasses import replace
    cfg2 = replace(cfg, **parse_overrides(spec))
    train = open_dataset(args.dataset, split='train')
    if args.setting == 'aligned':
        feats = encode_dataset(train, make_encoder(cfg2), cache_dir=Path(args.cache),
                               progress=False)
        return feats[torch.from_numpy(sources)]
    if args.setting == 'scans':
        from point_gn_ros.core.views import VIEW_PROTOCOLS
        from point_gn_ros.datasets.views import ViewsDataset
        ds = ViewsDataset(train, 4, 0, VIEW_PROTOCOLS['hpr'][0], include_full=True,
                          random_yaw=True)
        feats = encode_dataset(ds, make_encoder(cfg2), cache_dir=Path(args.cache),
                               progress=False)
        return feats[torch.from_numpy(rows)]
    import hashlib
    key = hashlib.sha1(repr(('concat_yaw_full', len(train), sorted(cfg2.to_dict().items()))
                            ).encode()).hexdigest()[:16]
    path = Path(args.cache) / f'concat_study_{key}.npy'
    if not path.is_file():
        def clouds():  # noqa: ANN202
            for i in range(len(train)):
                # ViewsDataset draws one angle per item; item 0 is the complete object
                a = np.random.default_rng([0, i, 0xA11]).uniform(0, 2 * np.pi, 5)[0]
                yield rotate_z(train[i][0], a)
        np.save(path, encode_clouds(clouds(), make_encoder(cfg2), total=len(train)).numpy())
    return torch.from_numpy(np.load(path, allow_pickle=False))[torch.from_numpy(sources)]


def load_setting(args: argparse.Namespace) -> tuple[torch.Tensor, np.ndarray, np.ndarray | None,
                                                     EncoderConfig, dict, np.ndarray,
                                                     np.ndarray]:
    """Features of one setting.

    -> raw features (M, D), labels (M,), groups (M,) or None, encoder config, select grid,
    source train object of each row (M,), the rows taken from the encoded dataset (M,).
    """
    train = open_dataset(args.dataset, split='train')
    cache = Path(args.cache)
    if args.setting == 'aligned':
        cfg = EncoderConfig()
        feats = encode_dataset(train, make_encoder(cfg), cache_dir=cache, progress=False)
        rows = np.arange(0, len(train), args.subset)
        grid = dict(dims_options=tuple(d or None for d in (args.dims or [0])))
        return (feats[torch.from_numpy(rows)], np.asarray(train.labels)[rows], None, cfg, grid,
                rows, rows)
    from point_gn_ros.core.views import VIEW_PROTOCOLS
    from point_gn_ros.datasets.views import ViewsDataset
    cfg = EncoderConfig(yaw_align=True)
    ds = ViewsDataset(train, 4, 0, VIEW_PROTOCOLS['hpr'][0], include_full=True, random_yaw=True)
    feats = encode_dataset(ds, make_encoder(cfg), cache_dir=cache, progress=False)
    scan = np.asarray(ds.view_index) >= 0
    keep = (np.asarray(ds.groups) % args.subset == 0) & (scan if args.setting == 'scans'
                                                         else ~scan)
    rows = np.flatnonzero(keep)
    grid = dict(alphas=(0.1,), weights=(0.1, 0.2, 0.3),
                dims_options=tuple(args.dims or ((224, 320) if args.setting == 'scans'
                                                 else (512, 640))))
    groups = np.asarray(ds.groups)[rows] if args.setting == 'scans' else None
    return (feats[torch.from_numpy(rows)], np.asarray(ds.labels)[rows].astype(np.int64),
            groups, cfg, grid, np.asarray(ds.groups)[rows], rows)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('dataset')
    p.add_argument('--cache', required=True)
    p.add_argument('--setting', choices=('aligned', 'yaw', 'scans'), default='aligned')
    p.add_argument('--subset', type=int, default=3, help='every N-th object (default 3)')
    p.add_argument('--dims', type=int, nargs='+', default=None,
                   help='PCA widths to choose from (aligned: 0 = all, the default)')
    p.add_argument('--alphas', type=float, nargs='+', default=None,
                   help="whitening shrinkage grid (default: the setting's)")
    p.add_argument('--variants', nargs='+', default=['base', 'pow0.5'])
    p.add_argument('--out', default=None, help='append one JSON line per variant here')
    args = p.parse_args()
    torch.set_num_threads(1)
    feats, labels, groups, cfg, grid, sources, rows = load_setting(args)
    if args.alphas:
        grid['alphas'] = tuple(args.alphas)
    table = variants(cfg)
    base_correct = None
    print(f'{args.setting}: {len(labels)} entries, grid {grid}', flush=True)
    for name in args.variants:
        t0 = time.process_time()
        if name.startswith(('cat:', 'only:')):
            kind, spec = name.split(':', 1)
            f2 = second_features(args, cfg, spec, sources, rows).float()
            x = torch.cat([feats.float(), f2], 1) if kind == 'cat' else f2
        else:
            x = table[name](feats.float())
        _Weighted.weights = _block_weights(name, block_slices(cfg), feats.shape[1])
        with mock.patch.object(selection, 'FeatureTransform', _Weighted):
            sel = selection.select(x, labels, 40, standardize_options=('standardize',),
                                   groups=groups, **grid)
        correct = sel.heldout_correct.astype(float)
        row = {'setting': args.setting, 'subset': args.subset, 'n': len(labels),
               'variant': name, 'cv_accuracy': sel.cv_accuracy,
               'vote_cv_accuracy': sel.vote_cv_accuracy, 'dims': sel.dims,
               'gamma': sel.gamma, 'alpha': sel.alpha, 'lda_alpha': sel.lda_alpha,
               'weight': sel.fusion_weight, 'cpu_s': round(time.process_time() - t0, 1)}
        if name == 'base':
            base_correct = correct
        elif base_correct is not None:
            diff, se = paired_diff(correct, base_correct, groups)
            row.update(diff=diff, diff_se=se)
        print(json.dumps(row), flush=True)
        if args.out:
            np.save(f'{args.out}.{name}.npy', correct)    # per-entry correctness, for re-use
            with open(args.out, 'a') as fh:
                fh.write(json.dumps(row) + '\n')


if __name__ == '__main__':
    main()
