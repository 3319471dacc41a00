#!/usr/bin/env python3
"""Augmented copies of the bank's objects under the discriminant head, by CV (issue 8 study).

Does the head gain when each training object also contributes augmented copies, either as
vote entries and covariance samples ("bank") or only as samples for the standardisation,
whitening and LDA fit ("fit")? Train split only, never the test split: 5 stratified folds of
the original objects; an object's copies always sit in its own fold, and only originals are
scored. Every variant takes the best of the same small head grid.

  aligned: complete objects as stored; copies by anisotropic scale (0.8-1.25 per axis) and
           0.5 % jitter ('scale'), or a random 75 % of the points resampled back ('drop')
  scans:   the default bank's scan section (4 HPR scans per object); copies are 4 more
           scans of each object per copy (other view seeds); folds grouped by object
  yaw:     yaw-aligned complete objects; copies are the canonical frame's other heading
           conventions ('d4': the 7 other rotations/reflections of the x-y square; 'sign':
           the 3 other sign choices of x and y), the ambiguities canonical_yaw resolves by
           moments

    python experiments/bank_augment_study.py ../shared/datasets/modelnet40_1024 \
        --cache DIR --setting aligned --aug scale --copies 2

`--quant LEVELS` stores the fold bank's vote entries as integers (127: int8, 7: int4), the
reference row at int8; `--quant-only` compares float, int8 and int4 without copies.
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import json
from pathlib import Path

import numpy as np
import torch

from point_gn_ros.bank.discriminant import CovarianceFit
from point_gn_ros.bank.vote import log_vote_shares
from point_gn_ros.bank.selection import stratified_folds
from point_gn_ros.bank.model import FeatureTransform
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.core.sampling import canonical_yaw, normalize, resample
from point_gn_ros.datasets import open_dataset
from point_gn_ros.recognizer import encode_clouds, make_encoder

GAMMAS = (40.0, 80.0, 160.0)
ALPHAS = (0.1, 0.2, 0.4)
LDA_ALPHAS = (0.01, 0.02)
WEIGHTS = (0.1, 0.2, 0.3)

# The 8 maps of the x-y square, as (swap x/y, sign x, sign y); the first is the identity.
D4 = [(s, a, b) for s in (False, True) for a in (1, -1) for b in (1, -1)]


def _cached(path: Path, make) -> np.ndarray:  # noqa: ANN001
    if not path.is_file():
        np.save(path, make())
    return np.load(path, allow_pickle=False)


def _key(*parts: object) -> str:
    return hashlib.sha1(repr(parts).encode()).hexdigest()[:16]


def _augment(xyz: np.ndarray, kind: str, rng: np.random.Generator) -> np.ndarray:
    if kind == 'scale':
        out = xyz * rng.uniform(0.8, 1.25, 3).astype(np.float32)
        return out + rng.normal(0, 0.005, out.shape).astype(np.float32)
    if kind == 'drop':
        return xyz[np.sort(rng.choice(len(xyz), int(0.75 * len(xyz)), replace=False))]
    raise ValueError(kind)


def _frame(xyz: np.ndarray, swap: bool, sx: int, sy: int) -> np.ndarray:
    out = xyz.copy()
    if swap:
        out[:, [0, 1]] = out[:, [1, 0]]
    out[:, 0] *= sx
    out[:, 1] *= sy
    return out


def features(args: argparse.Namespace, clouds: list[np.ndarray]) -> tuple[np.ndarray, list]:
    """-> originals (N, D), [copies (N, D)] in copy order (cached under /cache)."""
    cache, n = Path(args.cache), len(clouds)
    if args.setting == 'aligned':
        enc = make_encoder(EncoderConfig())
        base = _cached(cache / f'augstudy_{_key("aligned", n)}.npy',
                       lambda: encode_clouds(clouds, enc, progress='originals').numpy())
        copies = []
        for c in range(args.copies):
            def make(c: int = c) -> np.ndarray:
                aug = (_augment(x, args.aug, np.random.default_rng([c, i, 0xA06]))
                       for i, x in enumerate(clouds))
                return encode_clouds(aug, enc, total=n, progress=f'copy {c}').numpy()
            copies.append(_cached(cache / f'augstudy_{_key("aligned", n, args.aug, c)}.npy',
                                  make))
        return base, copies
    if args.setting == 'scans':
        return _scan_features(args)
    # yaw: prepare as the yaw-aligned bank does, then re-map the canonical frame and encode
    # without re-canonicalising (the encoder's own prepare is then a no-op up to rounding).
    enc = make_encoder(EncoderConfig(yaw_align=False))
    canon = [canonical_yaw(normalize(resample(x, 1024, 'fps', 0))) for x in clouds]
    maps = D4[1:] if args.aug == 'd4' else [m for m in D4 if not m[0]][1:]
    base = _cached(cache / f'augstudy_{_key("yaw", n)}.npy',
                   lambda: encode_clouds(canon, enc, progress='originals').numpy())
    copies = [_cached(cache / f'augstudy_{_key("yaw", n, m)}.npy',
                      lambda m=m: encode_clouds([_frame(x, *m) for x in canon], enc,
                                                progress=f'frame {m}').numpy())
              for m in maps]
    return base, copies


def _scan_features(args: argparse.Namespace) -> tuple[np.ndarray, list]:
    """The default bank's scan section and args.copies more sets of scans.

    4 HPR scans per object, view seed 0 (the shipped section), then view seeds 1, 2, ...;
    each (4N, D), rows object-major.
    """
    from point_gn_ros.bank.builder import encode_dataset
    from point_gn_ros.core.views import VIEW_PROTOCOLS
    from point_gn_ros.datasets.views import ViewsDataset
    train = open_dataset(args.dataset, split='train')
    enc = make_encoder(EncoderConfig(yaw_align=True))
    hpr = VIEW_PROTOCOLS['hpr'][0]
    sets = []
    for seed in range(args.copies + 1):
        ds = ViewsDataset(train, 4, seed, hpr, include_full=seed == 0, random_yaw=True)
        f = encode_dataset(ds, enc, cache_dir=Path(args.cache), progress=True).numpy()
        sets.append(f[np.asarray(ds.view_index) >= 0])
    return sets[0], sets[1:]


def quantize(u: torch.Tensor, levels: int) -> torch.Tensor:
    """Unit rows stored as signed integers up to +-levels (per-row scale), re-normalised."""
    if not levels:
        return u
    q = torch.round(u / u.abs().amax(1, keepdim=True) * levels)
    return torch.nn.functional.normalize(q, dim=1)


def cv(orig: torch.Tensor, copies: list[torch.Tensor], labels: np.ndarray, mode: str,
       dims: int | None, groups: np.ndarray | None, scans: bool, levels: int = 0
       ) -> tuple[float, dict, np.ndarray]:
    """Pooled CV accuracy of the best grid point on the originals, its knobs, correctness."""
    lab = torch.from_numpy(labels)
    n, k = len(labels), len(copies)
    parts = stratified_folds(labels, 5, 0, groups)
    gammas, alphas = ((10.0, 20.0, 40.0), (0.1,)) if scans else (GAMMAS, ALPHAS)
    grid = list(itertools.product(alphas, gammas, LDA_ALPHAS, WEIGHTS))
    votes = {(a, g): torch.zeros(n, 40) for a in alphas for g in gammas}
    ldas = {a: torch.zeros(n, 40) for a in LDA_ALPHAS}
    for val in parts:
        tr = np.setdiff1d(np.arange(n), val)
        fit_x = torch.cat([orig[tr]] + [c[tr] for c in copies]) if k else orig[tr]
        fit_y = lab[torch.from_numpy(np.tile(tr, k + 1))]
        bank_x, bank_y = (fit_x, fit_y) if mode == 'bank' else (orig[tr], lab[tr])
        tf = FeatureTransform.fit(fit_x, 'standardize', dims)
        fit = CovarianceFit.fit(tf(fit_x), fit_y, 40)
        c_bank, c_val = fit.coords(tf(bank_x)), fit.coords(tf(orig[val]))
        vi = torch.from_numpy(val)
        for a in LDA_ALPHAS:
            ldas[a][vi] = torch.log_softmax(fit.lda_logits(c_val, a), 1).float()
        for a in alphas:
            u_b = quantize(torch.nn.functional.normalize(fit.whitened(c_bank, a), dim=1),
                           levels)
            u_v = torch.nn.functional.normalize(fit.whitened(c_val, a), dim=1)
            for g in gammas:
                lv = log_vote_shares(u_v @ u_b.T, bank_y, 40, g)
                votes[(a, g)][vi] = lv
    best = (-1.0, None, None)
    for a, g, la, w in grid:
        pred = (votes[(a, g)] + w * ldas[la]).argmax(1)
        acc = float((pred == lab).double().mean())
        if acc > best[0] + 1e-12:
            best = (acc, dict(alpha=a, gamma=g, lda_alpha=la, weight=w),
                    (pred == lab).numpy().astype(float))
    return best


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('dataset')
    p.add_argument('--cache', required=True)
    p.add_argument('--setting', choices=('aligned', 'yaw', 'scans'), default='aligned')
    p.add_argument('--aug', default='scale', help='aligned: scale | drop; yaw: d4 | sign')
    p.add_argument('--copies', type=int, default=2, help='aligned: copies per object')
    p.add_argument('--subset', type=int, default=1, help='every N-th object')
    p.add_argument('--dims', type=int, default=0, help='PCA width (0: all)')
    p.add_argument('--quant', type=int, default=0, metavar='LEVELS',
                   help='store the vote entries as integers up to +-LEVELS per row '
                        '(127: int8, 7: int4; 0: float)')
    p.add_argument('--quant-only', action='store_true',
                   help='no copies: the originals with entries stored as float, int8, int4')
    args = p.parse_args()
    torch.set_num_threads(2)
    train = open_dataset(args.dataset, split='train')
    clouds = [train[i][0] for i in range(len(train))]
    labels_all = np.asarray(train.labels, dtype=np.int64)
    base, copies = features(args, clouds)
    scans = args.setting == 'scans'
    per = 4 if scans else 1                     # rows per object, object-major
    rows = np.flatnonzero(np.arange(len(base)) // per % args.subset == 0)
    orig = torch.from_numpy(base[rows]).float()
    cps = [torch.from_numpy(c[rows]).float() for c in copies]
    labels = np.repeat(labels_all, per)[rows]
    groups = rows // per if scans else None
    dims = args.dims or None
    if args.quant_only:              # stored precision alone, no copies: float, int8, int4
        ref = None
        for levels in (0, 127, 7):
            acc, knobs, ok = cv(orig, [], labels, 'fit', dims, groups, scans, levels)
            ref = ok if ref is None else ref
            d = ok - ref
            print(json.dumps({'variant': f'quant {levels}', 'cv': acc, 'diff': float(d.mean()),
                              'se': float(d.std(ddof=1) / np.sqrt(len(d))), **knobs}),
                  flush=True)
        return
    ref_acc, ref_knobs, ref_ok = cv(orig, [], labels, 'fit', dims, groups, scans,
                                    127 if args.quant else 0)
    print(json.dumps({'variant': 'none' + (' int8' if args.quant else ''), 'cv': ref_acc,
                      **ref_knobs}), flush=True)
    for mode in ('fit', 'bank'):
        acc, knobs, ok = cv(orig, cps, labels, mode, dims, groups, scans, args.quant)
        d = ok - ref_ok
        kind = 'views' if scans else args.aug
        print(json.dumps({'variant': f'{kind} x{len(cps)} {mode} quant {args.quant}', 'cv': acc,
                          'diff': float(d.mean()), 'se': float(d.std(ddof=1) / np.sqrt(len(d))),
                          **knobs}), flush=True)


if __name__ == '__main__':
    main()
