#!/usr/bin/env python3
"""Full ModelNet40 accuracy study: the discriminant head against the vote (benchmarks/).

Everything is chosen by k-fold CV on the train split (transform, head, gamma,
temperature, unknown threshold); the test split is encoded and scored once with the
chosen settings. The plain kernel vote row uses the best plain-vote row of the same CV
table. Optional: test objects at a random yaw (seeded, as `point_gn eval --random-yaw`),
an open-set run (bank of N known classes, all test classes queried), the point-order
check.

usage: experiments/accuracy_study.py [--data ../shared/datasets/modelnet40_1024] [--cache DIR]
       [--yaw-align] [--yawed-test] [--open-set 30] [--dims 0 512] [--out result.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import time

import numpy as np
import torch

from point_gn_ros.bank.builder import build_bank, encode_dataset, fit_selected
from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.core.sampling import rotate_z
from point_gn_ros.datasets import open_dataset
from point_gn_ros.evaluation.metrics import accuracy_report
from point_gn_ros.evaluation.openset import KnownSubset, choose_known, open_set_report
from point_gn_ros.recognizer import encode_clouds, make_encoder
from point_gn_ros.bank.vote import ExactSearch, reference_head


def _figures(true: np.ndarray, pred: np.ndarray, names: list[str]) -> dict:
    rep = accuracy_report(true, pred, names)
    return {k: rep[k] for k in ('accuracy', 'mean_class_accuracy')}


def _vote_baseline(bank, f_train: torch.Tensor, labels: np.ndarray) -> tuple:
    """The best plain-vote row of the bank's own CV table, fitted on all of train."""
    from point_gn_ros.bank.selection import Selection
    rows = [r for r in bank.meta['selection']['table'] if r['whiten_alpha'] is None]
    best = max(rows, key=lambda r: r['vote_accuracy'])
    sel = Selection(gamma=best['gamma'], standardize=best['standardize'], dims=best['dims'],
                    cv_accuracy=best['vote_accuracy'])
    tf, head, feats = fit_selected(f_train, labels, bank.num_classes, sel)
    return tf, head, feats, best


def _encode_yawed(ds, enc, seed: int, cache: Path, tag: str) -> torch.Tensor:
    """Every object turned by a seeded random yaw (the same angles as eval --random-yaw)."""
    path = cache / f'yawed_{tag}_seed{seed}_{ds.split}_{len(ds)}.npy'
    if path.is_file():
        return torch.from_numpy(np.load(path, allow_pickle=False))
    angles = np.random.default_rng(seed).uniform(0, 2 * np.pi, len(ds))
    feats = encode_clouds((rotate_z(ds[i][0], angles[i]) for i in range(len(ds))), enc,
                          total=len(ds), progress='encoding (random yaw)')
    np.save(path, feats.numpy())
    return feats


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--data', default=str(Path(__file__).resolve().parents[2] / 'shared' /
                                          'datasets' / 'modelnet40_1024'))
    ap.add_argument('--cache', default='cache')
    ap.add_argument('--dims', type=int, nargs='+', default=[0])
    ap.add_argument('--standardize', nargs='+', default=['standardize'])
    ap.add_argument('--lda-alphas', type=float, nargs='+', default=None,
                    help='LDA shrinkage grid (default: the builder default)')
    ap.add_argument('--sigma', type=float, default=None, help='encoder sigma (default 0.4)')
    ap.add_argument('--k', type=int, default=None, help='encoder neighbours (default 120)')
    ap.add_argument('--yaw-align', action='store_true', help='yaw-canonical encoder config')
    ap.add_argument('--yawed-test', action='store_true',
                    help='also score every test object at a random yaw (seed 0)')
    ap.add_argument('--open-set', default=None, metavar='N_OR_CLASSES',
                    help='also an open-set run with this many known classes (seed 0)')
    ap.add_argument('--open-set-only', action='store_true',
                    help='only the open-set run (skips the closed-set bank and its CV)')
    ap.add_argument('--shuffle-check', action='store_true')
    ap.add_argument('--out', default=None, help='write the JSON summary here')
    args = ap.parse_args()

    overrides = {k: v for k, v in (('sigma', args.sigma), ('k', args.k)) if v is not None}
    cfg = EncoderConfig(yaw_align=args.yaw_align, **overrides)
    enc = make_encoder(cfg)
    enc.warmup()
    cache = Path(args.cache)
    train = open_dataset(args.data, split='train')
    test = open_dataset(args.data, split='test')
    t0 = time.perf_counter()
    f_train = encode_dataset(train, enc, cache_dir=cache)
    f_test = encode_dataset(test, enc, cache_dir=cache)
    print(f'encoded {len(train)} + {len(test)} clouds in {time.perf_counter() - t0:.0f} s')
    y_train, y_test = np.asarray(train.labels), np.asarray(test.labels)
    names = list(test.class_names)

    dims = tuple(None if d == 0 else d for d in args.dims)
    result: dict = {'encoder': cfg.to_dict()}
    if args.open_set:
        known = choose_known(args.open_set, names, 0)
        sub = KnownSubset(train, known)
        obank = build_bank(sub, encoder=enc, feats=f_train[torch.from_numpy(sub.index)],
                           progress=False, standardize_options=tuple(args.standardize),
                           dims_options=dims)
        ores = Classifier(obank, unknown_threshold=-1).classify(f_test, top_k=1)
        result['open_set'] = open_set_report(y_test, known, ores.labels, ores.novelty,
                                             ores.scores, ores.topk_ids[:, 0])
        result['open_set'].update(known_classes=obank.class_names, head=obank.meta['head'],
                                  unknown_rule=obank.meta['unknown_calibration'])
        print(f'open set ({len(known)} known): {json.dumps(result["open_set"])}', flush=True)
    if args.open_set_only:
        if args.out:
            Path(args.out).write_text(json.dumps(result, indent=2))
        return
    t0 = time.perf_counter()
    extra = {'lda_alphas': tuple(args.lda_alphas)} if args.lda_alphas else {}
    bank = build_bank(train, encoder=enc, feats=f_train, progress=False,
                      standardize_options=tuple(args.standardize), dims_options=dims, **extra)
    sel, head = bank.meta['selection'], bank.meta['head']
    print(f'CV on train took {time.perf_counter() - t0:.0f} s: {json.dumps(head)}; '
          f'standardize={sel["standardize"]} dims={sel["dims"]} gamma={sel["gamma"]:g} '
          f'cv={100 * sel["cv_accuracy"]:.2f} %')
    clf = Classifier(bank)
    res = clf.classify(f_test, top_k=1)
    result.update(selection={k: v for k, v in sel.items() if k != 'table'}, head=head,
                  test_head=_figures(y_test, res.labels, names))
    tf, vhead, vfeats, vrow = _vote_baseline(bank, f_train, y_train)
    vote_pred = reference_head(vhead, tf(f_test), ExactSearch(vfeats, bank.labels, 40)
                               )[0].argmax(1).numpy()
    result['test_vote'] = {**_figures(y_test, vote_pred, names), 'cv': vrow}
    print(f'HEAD test OA {100 * result["test_head"]["accuracy"]:.2f} % mAcc '
          f'{100 * result["test_head"]["mean_class_accuracy"]:.2f} %; plain vote (gamma '
          f'{vrow["gamma"]:g}) OA {100 * result["test_vote"]["accuracy"]:.2f} % mAcc '
          f'{100 * result["test_vote"]["mean_class_accuracy"]:.2f} %')
    nll = -np.log(np.clip(res.probability[np.arange(len(y_test)), y_test], 1e-12, 1)).mean()
    result['test_log_loss'] = float(nll)
    if args.yawed_test:
        f_yaw = _encode_yawed(test, enc, 0, cache, f'{cfg.yaw_align}_{cfg.sigma}_{cfg.k}')
        result['yawed_test_head'] = _figures(y_test, clf.classify(f_yaw, top_k=1).labels,
                                             names)
        vp = reference_head(vhead, tf(f_yaw), ExactSearch(vfeats, bank.labels, 40)
                            )[0].argmax(1).numpy()
        result['yawed_test_vote'] = _figures(y_test, vp, names)
        print(f'random-yaw test: head {json.dumps(result["yawed_test_head"])}, vote '
              f'{json.dumps(result["yawed_test_vote"])}')
    if args.shuffle_check:
        rng = np.random.default_rng(0)
        shuffled = (test[i][0][rng.permutation(len(test[i][0]))] for i in range(len(test)))
        f_shuf = encode_clouds(shuffled, enc, total=len(test), progress='shuffled test')
        changed = int((clf.classify(f_shuf, top_k=1).labels != res.labels).sum())
        print(f'point-order check: {changed} of {len(test)} labels changed after shuffling')
        result['shuffle_changed_labels'] = changed
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=2))


if __name__ == '__main__':
    main()
