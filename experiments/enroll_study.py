"""Teach the default bank 10 new objects from 5 single-view scans each; measure what it costs.

Protocol (issue 12 goal):
- Bank: the shipped default (ModelNet40 train, yaw-aligned, 40 classes), untouched by the test
  split until this script.
- New objects: for each ModelNet10 category one test-split object (seeded choice); each becomes a
  NEW class '<category>_object_<index>' (instance-level: "my chair", not "a chair").
- Enrollment: 5 single-view scans per object (core/views.py simulator, evenly spread azimuths,
  seed s; `--view-protocol`: 'hpr', the simulator's default, or round 1's harsher 'zbuffer'),
  encoded (`--augment`: each scan stored in the k frames of core/augment.py, as the node's
  `enroll_augment` does) and added through `LiveBank.add` as the node does, one call per object.
  The refit policy is the node's default ('auto': the 9,843-entry bank keeps its CV-chosen gamma
  and its calibrated threshold, recorded in the bank). `--fuse-views`: each object's scans are
  also fused (core/fusion.py; given in one frame, as with a robot's odometry, each moved by a
  registration error of `--pose-noise`) and the fused cloud and 8 scans of it enrolled too.
- New-object accuracy: 20 OTHER single-view scans of each enrolled object (seed s + 1000, other
  azimuths, noise and dropout), labelled right only as the object's own new class.
- Existing classes: the ModelNet40 test split without the 10 enrolled objects, before and after,
  (a) complete objects at a seeded random yaw, (b) one single-view scan of each (seed 7).
Nothing here is tuned on the test split: the bank's knobs were chosen by CV on train.

Run: python experiments/enroll_study.py [--bank PATH] [--json OUT] [--cache DIR] [--draws K]
     [--augment none|mirror|rot4|d4] [--view-protocol hpr|zbuffer] [--lda-prior balanced]
     [--lda-debias F] [--steal-budget RHO]
     [--cv-augment] [--fuse-views [--pose-noise S]]
"""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path
import sys
import time

import numpy as np
import torch

from point_gn_ros.bank.enroll import BankFile
from point_gn_ros.bank.refit import RefitPolicy
from point_gn_ros.bank.live import LiveBank
from point_gn_ros.core.augment import AUGMENTS
from point_gn_ros.core.config import ENCODER_VERSION
from point_gn_ros.core.fusion import fused_examples
from point_gn_ros.core.sampling import rotate_z
from point_gn_ros.core.views import (SIMULATOR_VERSION, VIEW_PROTOCOLS, simulate_view,
                                     simulate_views)
from point_gn_ros.datasets import open_dataset
from point_gn_ros.recognizer import Recognizer, encode_clouds, make_encoder

MODELNET = Path(__file__).resolve().parents[2] / 'shared' / 'datasets' / 'modelnet40_1024'
MODELNET10 = ('bathtub', 'bed', 'chair', 'desk', 'dresser', 'monitor', 'night_stand', 'sofa',
              'table', 'toilet')


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--bank', default=None, help='bank (default: the shipped default bank)')
    p.add_argument('--data', default=str(MODELNET), help='ModelNet40 h5 folder')
    p.add_argument('--enroll-views', type=int, default=5)
    p.add_argument('--query-views', type=int, default=20)
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--draws', type=int, default=1,
                   help='repeat the study for seeds --seed .. --seed + DRAWS - 1 (other '
                        'objects, views and yaws each) and report the mean and spread')
    p.add_argument('--augment', choices=tuple(AUGMENTS), default='none',
                   help='frames each enrolled scan is stored in (core/augment.py)')
    p.add_argument('--lda-prior', choices=('entries', 'balanced', 'typical'), default='entries',
                   help="LDA class priors after each enrollment's refit (RefitPolicy)")
    p.add_argument('--lda-debias', type=float, default=0.0, metavar='F',
                   help="share of a wide LDA's mean-noise correction for the enrolled classes "
                        '(RefitPolicy.lda_debias; chosen by experiments/instance_cv.py --debias)')
    p.add_argument('--steal-budget', type=float, default=0.0, metavar='RHO',
                   help='RefitPolicy.lda_steal_budget (bank/discriminant.py; chosen by '
                        'experiments/instance_cv.py --budgets)')
    p.add_argument('--cv-augment', action='store_true',
                   help='also choose --augment by leave-one-scan-out CV on the enrolled scans '
                        'alone (no query scan read): accuracy per option')
    p.add_argument('--view-protocol', choices=('hpr', 'zbuffer'), default='hpr',
                   help='view simulator setting for every scan (default hpr)')
    p.add_argument('--fuse-views', action='store_true',
                   help="also enroll what core/fusion.py draws from each object's enrolled "
                        'scans fused (given in one frame, as a robot with odometry gives '
                        'them): the fused cloud and 8 simulated scans of it')
    p.add_argument('--pose-noise', type=float, default=1.0, metavar='S',
                   help='with --fuse-views, each enrolled scan is moved before fusing by a '
                        'registration error: yaw N(0, 2 S deg), shift N(0, 0.01 S radius) per '
                        'axis (default S = 1)')
    p.add_argument('--json', default=None, help='write the figures here')
    p.add_argument('--cache', default=None, metavar='DIR',
                   help='reuse the encoded clouds (keyed by encoder configuration and seeds)')
    args = p.parse_args(argv)
    if args.draws < 1:
        p.error('--draws must be >= 1')
    bf = BankFile.load(args.bank)
    encoder = make_encoder(bf.bank.config)
    draws = [study(argparse.Namespace(**{**vars(args), 'seed': args.seed + d}), bf, encoder)
             for d in range(args.draws)]
    out = draws[0] if args.draws == 1 else {'draws': draws, 'summary': summary(draws)}
    print(json.dumps(out, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2) + '\n')
    return 0


def summary(draws: list[dict]) -> dict:
    """Mean, sample std and range over draws of the goal's three figures."""
    figures = {'new_objects_accuracy': [d['new_objects_accuracy'] for d in draws]}
    for kind in ('complete', 'single_view'):
        figures[f'existing_drop_points_{kind}'] = [d['existing_drop_points'][kind]
                                                   for d in draws]
    return {'seeds': [d['seed'] for d in draws],
            **{k: {'mean': float(np.mean(v)), 'std': float(np.std(v, ddof=1)),
                   'min': float(np.min(v)), 'max': float(np.max(v)), 'per_draw': v}
               for k, v in figures.items()}}


def study(args: argparse.Namespace, bf: BankFile, encoder) -> dict:
    """One draw of the protocol (module docstring) for args.seed -> its figures."""
    test = open_dataset(args.data, split='test')
    rng = np.random.default_rng(args.seed)
    chosen = {c: int(rng.choice(np.flatnonzero(test.labels == test.class_names.index(c))))
              for c in MODELNET10}
    rest = np.setdiff1d(np.arange(len(test)), list(chosen.values()))

    view_cfg = VIEW_PROTOCOLS[args.view_protocol][0]

    def encode(clouds: list[np.ndarray], augment: str = 'none'):
        return encode_clouds(clouds, encoder, batch_size=64, augment=augment)  # type: ignore

    def enrollment_scans(i: int) -> list[np.ndarray]:
        return [v.points for v in simulate_views(test[i][0], args.enroll_views,
                                                 seed=args.seed + i, cfg=view_cfg)]

    t0 = time.perf_counter()
    # The hpr key is the one used before --view-protocol existed (same cached features).
    protocol_key = () if args.view_protocol == 'hpr' else (args.view_protocol,)
    key = hashlib.sha1(repr((bf.bank.config.to_dict(), ENCODER_VERSION, SIMULATOR_VERSION,
                             args.seed, args.enroll_views, args.query_views, *protocol_key)
                            ).encode()).hexdigest()[:16]
    cache = Path(args.cache) / f'enroll_study_{key}.npz' if args.cache else None
    if cache is not None and cache.is_file():
        with np.load(cache, allow_pickle=False) as z:
            arrays = {k: torch.from_numpy(z[k]) for k in z.files}
    else:
        full = [rotate_z(test[i][0], float(rng.uniform(0, 2 * np.pi))) for i in rest]
        one_view = [simulate_view(test[i][0], np.random.default_rng([7, int(i)]),
                                  view_cfg).points for i in rest]
        arrays = {'full': encode(full), 'view': encode(one_view)}
        for c, i in chosen.items():
            obj = test[i][0]
            arrays[f'enroll_{c}'] = encode(enrollment_scans(i))
            arrays[f'query_{c}'] = encode([v.points for v in simulate_views(
                obj, args.query_views, seed=args.seed + 1000 + i, cfg=view_cfg)])
        if cache is not None:
            cache.parent.mkdir(parents=True, exist_ok=True)
            np.savez(cache, **{k: v.numpy() for k, v in arrays.items()})
    f_full, f_view = arrays['full'], arrays['view']
    truth = test.labels[rest]
    if args.augment != 'none':   # the cache holds the canonical frame only
        for c, i in chosen.items():
            arrays[f'enroll_{c}'] = encode(enrollment_scans(i), args.augment)
    if args.fuse_views:
        for c, i in chosen.items():
            arrays[f'enroll_{c}'] = torch.cat([arrays[f'enroll_{c}'], encode(
                fused_examples(misregistered(enrollment_scans(i), test[i][0],
                                             args.pose_noise, args.seed + i),
                               seed=args.seed + i), args.augment)])
    print(f'encoded {len(rest)} test objects twice in {time.perf_counter() - t0:.0f} s',
          file=sys.stderr)
    policy = RefitPolicy(gamma='auto', lda_prior=args.lda_prior,
                         lda_debias=args.lda_debias, lda_steal_budget=args.steal_budget)
    cv = None
    if args.cv_augment:
        scans = {f'{c}_object_{i}': enrollment_scans(i) for c, i in chosen.items()}
        cv = {a: augment_cv(bf, encoder, scans, a, policy) for a in AUGMENTS}
        print(f'leave-one-scan-out CV on the enrolled scans: {cv}', file=sys.stderr)

    live = LiveBank(bf, lambda active: Recognizer(active, encoder=encoder),
                    policy)

    def accuracy(feats, labels) -> float:
        pred = live.current().model.classifier.classify(feats).labels
        return float((pred == labels).mean())

    before = {'complete': accuracy(f_full, truth), 'single_view': accuracy(f_view, truth)}
    queries, query_labels, enroll_s, dups = [], [], [], 0
    for c, i in chosen.items():
        name = f'{c}_object_{i}'
        t = time.perf_counter()
        res = live.add(arrays[f'enroll_{c}'], name, source=f'enroll_study: '
                       f'{args.enroll_views} views of test object {i}',
                       augment=args.augment)
        enroll_s.append(time.perf_counter() - t)
        dups += res.duplicate_count
        cid = live.current().class_names.index(name)
        queries.append(arrays[f'query_{c}'])
        query_labels += [cid] * len(arrays[f'query_{c}'])
    t = time.perf_counter()
    ridge_wait_s = time.perf_counter() - t      # a kernel ridge term's full refit (live.py)
    snap = live.current()
    q_pred = snap.model.classifier.classify(torch.cat(queries)).labels
    q_true = np.asarray(query_labels)
    per_object = {snap.class_names[c]: float((q_pred[q_true == c] == c).mean())
                  for c in np.unique(q_true)}
    as_category = float(np.mean([snap.class_names[p].split('_object_')[0] == MODELNET10[k]
                                 for k, p in zip(np.repeat(np.arange(10), args.query_views),
                                                 q_pred, strict=True)]))
    after = {'complete': accuracy(f_full, truth), 'single_view': accuracy(f_view, truth)}
    # Existing-class queries now called one of the new classes (where the drop goes).
    new_ids = np.unique(q_true)
    taken = {k: {snap.class_names[c]: int(n) for c, n in zip(*np.unique(
        pred[np.isin(pred, new_ids)], return_counts=True), strict=True)}
        for k, pred in (('complete', snap.model.classifier.classify(f_full).labels),
                        ('single_view', snap.model.classifier.classify(f_view).labels))}
    out = {
        'seed': args.seed,
        'bank': str(bf.bank.path), 'bank_version': snap.version, 'gamma': snap.bank.gamma,
        'augment': args.augment, 'view_protocol': args.view_protocol,
        'lda_prior': args.lda_prior,
        'lda_debias': args.lda_debias,
        'lda_steal_budget': args.steal_budget,
        'fuse_views': args.fuse_views, 'pose_noise': args.pose_noise if args.fuse_views
        else None,
        'refit': snap.bank.meta['refit'], 'objects': chosen,
        'new_objects_accuracy': float((q_pred == q_true).mean()),
        'new_objects_misses_to_another_new_class': float(
            np.isin(q_pred[q_pred != q_true], np.unique(q_true)).mean())
        if (q_pred != q_true).any() else 0.0,
        'new_objects_per_object': per_object,
        'new_objects_right_category_or_instance': as_category,
        'existing_before': before, 'existing_after': after,
        'existing_drop_points': {k: 100 * (before[k] - after[k]) for k in before},
        'existing_called_new_class': taken,
        'enroll_seconds_per_object_max': max(enroll_s),
        'ridge_refit_wait_seconds': ridge_wait_s,
        'near_duplicates': dups,
    }
    if cv is not None:
        out['augment_cv_on_enrolled_scans'] = cv
    return out


def misregistered(views: list[np.ndarray], obj: np.ndarray, scale: float, seed: int
                  ) -> list[np.ndarray]:
    """Each view moved by its own registration error (an odometry-like pose error).

    views: (N_i, 3) scans in the object's frame; obj: (N, 3) the object (its radius sets the
    shift's scale) -> the views, each turned about z by N(0, 2 scale) degrees around the
    object's centre and shifted by N(0, 0.01 scale radius) per axis; scale 0: unchanged.
    """
    rng = np.random.default_rng([seed, 0x9E6])
    centre = obj.mean(axis=0)
    radius = float(np.linalg.norm(obj - centre, axis=1).max())
    out = []
    for v in views:
        yaw = float(np.deg2rad(rng.normal(0.0, 2.0 * scale)))
        shift = rng.normal(0.0, 0.01 * scale * radius, 3)
        out.append((rotate_z(v - centre, yaw) + centre + shift).astype(np.float32))
    return out


def augment_cv(bf: BankFile, encoder, scans: dict[str, list[np.ndarray]], augment: str,
               policy: RefitPolicy) -> float:
    """Leave-one-scan-out accuracy of an augmentation, on the enrolled scans only.

    scans: class name -> its M enrollment scans. Fold j enrolls every class's scans but the
    j-th (augmented) and classifies the j-th scans (one canonical encoding each, as queries).
    """
    k = len(AUGMENTS[augment])
    feats = {n: encode_clouds(s, encoder, augment=augment) for n, s in scans.items()}  # type: ignore
    m = min(len(s) for s in scans.values())
    right = 0
    for j in range(m):
        live = LiveBank(bf, lambda active: Recognizer(active, encoder=encoder), policy)
        held, ids = [], []
        for name, f in feats.items():
            keep = torch.ones(len(f), dtype=torch.bool)
            keep[j * k:(j + 1) * k] = False
            live.add(f[keep], name, source='cv', augment=augment)
            held.append(f[j * k:j * k + 1])
            ids.append(live.current().class_names.index(name))
        pred = live.current().model.classifier.classify(torch.cat(held)).labels
        right += int((pred == np.asarray(ids)).sum())
    return right / (m * len(feats))


if __name__ == '__main__':
    sys.exit(main())
