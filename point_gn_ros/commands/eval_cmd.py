"""`point_gn eval` and `point_gn fewshot`: offline accuracy figures."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from point_gn_ros.commands.common import add_dataset_args, add_encoder_args


def register(sub: argparse._SubParsersAction) -> None:
    e = sub.add_parser('eval', help='classify a dataset split against a bank and report accuracy')
    e.add_argument('bank', metavar='BANK', help='bank file (.npz)')
    add_dataset_args(e, 'test')
    add_encoder_args(e)
    e.add_argument('--json', action='store_true', help='print the report as JSON')
    e.add_argument('--confusion', default=None, metavar='PNG',
                   help='write the confusion matrix here')
    e.add_argument('--gamma', type=float, default=None,
                   help="override the bank's gamma (for comparisons only)")
    e.add_argument('--search', choices=('auto', 'exact', 'indexed'), default='auto',
                   help="bank search: 'exact' (every entry votes), 'indexed' (two-stage: int8 "
                        "coarse scan, exact rescoring; each query alone) or 'auto' (indexed "
                        'from 20,000 entries; default)')
    e.add_argument('--unknown-threshold', type=float, default=None,
                   help='open-set threshold on the top score (<0: the bank calibration)')
    e.add_argument('--random-yaw', type=int, default=None, metavar='SEED',
                   help='rotate every object by a random angle about z (seeded): how the bank '
                        'copes with objects seen from any side')
    e.add_argument('--single-view', action='store_true',
                   help='classify one simulated single-view scan of every object instead '
                        '(hidden points removed, noise, random yaw; core/views.py)')
    e.add_argument('--seed', type=int, default=0,
                   help='seed of the --single-view scans (default 0)')
    e.add_argument('--view-protocol', choices=('hpr', 'zbuffer'), default='hpr',
                   help="scans of --single-view: 'hpr' hidden point removal (~470 of 1,024 "
                        "points; default) or 'zbuffer' (harsher "
                        'scans: z-buffer, dropout, range falloff, ~180 points)')
    e.add_argument('--open-set', default=None, metavar='N_OR_CLASSES',
                   help='open-set run: build BANK (or reuse it if it holds exactly these '
                        'classes) from the train split of N classes drawn with --open-set-seed '
                        '(or the comma-separated class names), query the whole split, report '
                        'novelty AUROC (unseen vs known), known accuracy and unknown recall '
                        "at the bank's default threshold")
    e.add_argument('--open-set-seed', type=int, default=0, help='seed of the known classes')
    e.add_argument('--ridge', action='store_true',
                   help='--open-set: let CV also weigh a kernel ridge term in the bank it '
                        'builds (bank build --ridge)')
    e.set_defaults(func=_eval)

    f = sub.add_parser('fewshot', help='N-way K-shot episodes (default: the paper settings)')
    add_dataset_args(f, 'test')
    add_encoder_args(f)
    f.add_argument('--ways', type=int, default=None, help='classes per episode')
    f.add_argument('--shots', type=int, default=None, help='support objects per class')
    f.add_argument('--queries', type=int, default=20, help='query objects per class')
    f.add_argument('--episodes', type=int, default=10, help='seeded episodes per setting')
    f.add_argument('--seed', type=int, default=0, help='episode seed')
    f.add_argument('--json', action='store_true', help='print results as JSON')
    f.add_argument('--bank', default=None, metavar='BANK',
                   help="teach-and-query protocol instead of episodes: teach --shots scans "
                        "(default 5) of every class into BANK ('default': the shipped bank) as "
                        '`bank add` does, query the rest, over --draws draws; reports mean class '
                        'accuracy, the share answered with a class the data set lacks, the '
                        'open-set AUROC with one class left out, and the nearest-mean and '
                        'geometry baselines (evaluation/teach.py)')
    f.add_argument('--draws', type=int, default=5, help='--bank: random draws (default 5)')
    f.add_argument('--no-units', action='store_true',
                   help='--bank: the clouds have no metric meaning (unit-sphere data): skip '
                        'metric size')
    f.add_argument('--fit-threshold', type=float, default=None, metavar='F',
                   help='--bank: the unknown rule whose reject rates are reported (default: '
                        "the node's default, bank/taught.py DEFAULT_FIT_THRESHOLD)")
    f.add_argument('--volume-threshold', type=float, default=None, metavar='V',
                   help='--bank: the volume rule counted in the reject rates (default: the '
                        "node's, core/surface.py DEFAULT_VOLUME_THRESHOLD; 1 = off)")
    f.add_argument('--scene-threshold', type=float, default=None, metavar='S',
                   help='--bank: the scene rule counted in the reject rates (default: the '
                        "node's, core/surface.py DEFAULT_SCENE_THRESHOLD; 1 = off)")
    f.set_defaults(func=_fewshot)


def _eval(args: argparse.Namespace) -> int:
    import torch

    from point_gn_ros.bank.store import FeatureBank
    from point_gn_ros.bank.builder import encode_dataset
    from point_gn_ros.bank.classifier import Classifier
    from point_gn_ros.commands.common import open_dataset_from_args
    from point_gn_ros.core.views import VIEW_PROTOCOLS
    from point_gn_ros.datasets.views import ViewsDataset
    from point_gn_ros.errors import DatasetError
    from point_gn_ros.evaluation.metrics import accuracy_report, format_report, plot_confusion
    from point_gn_ros.recognizer import make_encoder

    if args.open_set:
        return _eval_open_set(args)
    bank = FeatureBank.load(args.bank)
    ds = open_dataset_from_args(args)
    # A bank enlarged by enrollment may hold more classes than the data set: its labels are
    # mapped to the bank's ids, and answers with the extra classes count as wrong.
    missing = sorted(set(ds.class_names) - set(bank.class_names))
    if missing:
        raise DatasetError(f"{ds.path}: classes the bank lacks: {', '.join(missing[:10])} "
                           f'({len(ds.class_names)} vs {len(bank.class_names)} classes)')
    true = np.array([bank.class_names.index(ds.class_names[int(y)]) for y in ds.labels])
    enc = make_encoder(bank.config, args.device)
    source = ds
    if args.single_view:
        # One scan per object, turned by a random yaw as well (seeded by --seed).
        source = ViewsDataset(ds, 1, args.seed, VIEW_PROTOCOLS[args.view_protocol][0],
                              include_full=False, random_yaw=True)
    elif args.random_yaw is not None:
        # The complete objects, each turned by a seeded random yaw (cached like the rest).
        source = ViewsDataset(ds, 0, args.random_yaw, include_full=True, random_yaw=True)
    feats = encode_dataset(source, enc, args.batch_size, progress=not args.json,
                           cache_dir=Path(args.cache) if args.cache else None)
    clf = Classifier(bank, args.device, args.unknown_threshold, gamma=args.gamma,
                     search=args.search)
    res = clf.classify(torch.as_tensor(feats), top_k=1)
    report = accuracy_report(true, res.labels, bank.class_names)
    report.update(bank=str(bank.path), dataset=str(ds.path), split=ds.split,
                  gamma=clf.gamma, search=clf.search_kind, random_yaw_seed=args.random_yaw,
                  single_view_seed=args.seed if args.single_view else None,
                  view_protocol=args.view_protocol if args.single_view else None)
    if args.confusion:
        plot_confusion(report['confusion'], bank.class_names, args.confusion,
                       f'{Path(ds.path).name} [{ds.split}]: {100 * report["accuracy"]:.2f} %')
    if args.json:
        print(json.dumps({k: v for k, v in report.items() if k != 'confusion'}, indent=2))
    else:
        what = (f' single-view scans ({args.view_protocol}, seed {args.seed})'
                if args.single_view else '')
        print(format_report(report, f'{Path(ds.path).name} [{ds.split}]{what} vs '
                                    f'{bank.path.name} ({clf.search_kind} search)'))
    return 0


def _eval_open_set(args: argparse.Namespace) -> int:
    """Known classes' bank from the train split (CV on it only), then the query split once."""
    import copy

    import torch

    from point_gn_ros.bank.builder import build_bank, encode_dataset
    from point_gn_ros.bank.classifier import Classifier
    from point_gn_ros.bank.store import FeatureBank
    from point_gn_ros.commands.common import open_dataset_from_args
    from point_gn_ros.core.config import EncoderConfig
    from point_gn_ros.errors import BankError
    from point_gn_ros.evaluation.openset import KnownSubset, choose_known, open_set_report
    from point_gn_ros.recognizer import make_encoder

    ds = open_dataset_from_args(args)
    known = choose_known(args.open_set, list(ds.class_names), args.open_set_seed)
    names = [ds.class_names[i] for i in known]
    cache = Path(args.cache) if args.cache else None
    try:
        bank = FeatureBank.load(args.bank)
        if bank.class_names != names:
            raise BankError(f'{args.bank}: holds other classes; rebuilding')
        enc = make_encoder(bank.config, args.device)
    except BankError as exc:
        if Path(args.bank).exists():
            print(f'{exc}')
        train_args = copy.copy(args)
        train_args.split = 'train'
        train = open_dataset_from_args(train_args)
        enc = make_encoder(EncoderConfig(), args.device)
        f_train = encode_dataset(train, enc, args.batch_size, progress=not args.json,
                                 cache_dir=cache)
        sub = KnownSubset(train, known)
        bank = build_bank(sub, encoder=enc, feats=f_train[torch.from_numpy(sub.index)],
                          progress=not args.json, ridge=args.ridge)
        bank.save(args.bank, dtype='float32' if args.ridge else 'float16')
    feats = encode_dataset(ds, enc, args.batch_size, progress=not args.json, cache_dir=cache)
    clf = Classifier(bank, args.device, unknown_threshold=-1)
    res = clf.classify(torch.as_tensor(feats), top_k=1)
    report = open_set_report(np.asarray(ds.labels), known, res.labels, res.novelty, res.scores,
                             res.topk_ids[:, 0])
    report.update(bank=str(args.bank), dataset=str(ds.path), split=ds.split,
                  known_classes=names, unknown_rule=bank.meta.get('unknown_calibration'),
                  head=bank.meta.get('head'))
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(f'## open set: {len(known)} known classes (bank {args.bank}), '
              f'{len(ds.class_names) - len(known)} unseen; {Path(ds.path).name} [{ds.split}]')
        for key in ('known_objects', 'unseen_objects'):
            print(f'- {key.replace("_", " ")}: {report[key]}')
        for key in ('auroc_novelty', 'auroc_top_probability'):
            print(f'- {key.replace("_", " ")}: {report[key]:.4f}')
        for key in ('known_accuracy_closed_set', 'known_accuracy_at_threshold',
                    'known_false_reject_rate', 'unknown_recall_at_threshold'):
            print(f'- {key.replace("_", " ")}: {100 * report[key]:.2f} %')
    return 0


def _fewshot(args: argparse.Namespace) -> int:
    import numpy as np
    import torch

    if args.bank:
        return _teach(args)
    from point_gn_ros.commands.common import open_dataset_from_args
    from point_gn_ros.core.config import EncoderConfig
    from point_gn_ros.evaluation.fewshot import PAPER_SETTINGS, run_fewshot
    from point_gn_ros.recognizer import encode_clouds, make_encoder

    ds = open_dataset_from_args(args)
    enc = make_encoder(EncoderConfig(), args.device)
    labels = np.asarray(ds.labels)
    settings = PAPER_SETTINGS if args.ways is None and args.shots is None else (
        (args.ways or 5, args.shots or 10),)
    cached: dict[int, torch.Tensor] = {}

    def encode(idx: np.ndarray) -> torch.Tensor:
        todo = [int(i) for i in idx if int(i) not in cached]
        if todo:
            feats = encode_clouds([ds[i][0] for i in todo], enc, batch_size=args.batch_size,
                                  progress=None if args.json else 'encoding')
            cached.update(zip(todo, feats, strict=True))
        return torch.stack([cached[int(i)] for i in idx])

    results = [run_fewshot(labels, encode, w, s, args.queries, args.episodes, args.seed)
               for w, s in settings]
    if args.json:
        print(json.dumps(results, indent=2))
    else:
        print('| setting | accuracy (mean ± std over episodes) |\n|---|---|')
        for r in results:
            print(f'| {r["ways"]}-way {r["shots"]}-shot | {100 * r["mean"]:.1f} ± '
                  f'{100 * r["std"]:.1f} % |')
    return 0


def _teach(args: argparse.Namespace) -> int:
    """`point_gn fewshot DATASET --bank BANK`: the teach-and-query protocol."""
    import sys

    from point_gn_ros.bank.enroll import BankFile
    from point_gn_ros.bank.refit import RefitPolicy
    from point_gn_ros.bank.taught import DEFAULT_FIT_THRESHOLD
    from point_gn_ros.commands.common import open_dataset_from_args
    from point_gn_ros.core.size import size_descriptors
    from point_gn_ros.core.surface import (DEFAULT_SCENE_THRESHOLD, DEFAULT_VOLUME_THRESHOLD,
                                           scene_rule, structure_unknown, volume_rule)
    from point_gn_ros.evaluation.teach import run_teach_protocol
    from point_gn_ros.recognizer import encode_clouds, make_encoder

    ds = open_dataset_from_args(args)
    bf = BankFile.load(None if args.bank == 'default' else args.bank)
    clouds = [ds[i][0] for i in range(len(ds))]
    enc = make_encoder(bf.bank.config, args.device)
    feats = encode_clouds(clouds, enc, batch_size=args.batch_size,
                          progress=None if args.json else 'encoding')
    sizes = None if args.no_units else size_descriptors(clouds)
    # `bank add`'s policy (a kernel ridge term is refitted in full, as every published
    # version has it)
    policy = RefitPolicy(lda_prior='typical', lda_debias=2.0, lda_steal_budget=0.001)
    fit = DEFAULT_FIT_THRESHOLD if args.fit_threshold is None else args.fit_threshold
    vol = volume_rule(DEFAULT_VOLUME_THRESHOLD if args.volume_threshold is None
                      else args.volume_threshold)
    scene = scene_rule(DEFAULT_SCENE_THRESHOLD if args.scene_threshold is None
                       else args.scene_threshold)
    rep = run_teach_protocol(bf, list(ds.class_names), np.asarray(ds.labels), feats, sizes,
                             args.shots or 5, args.draws, args.seed, policy, fit,
                             progress=None if args.json else
                             lambda m: print(m, file=sys.stderr, flush=True),
                             structural=structure_unknown(clouds, vol, scene))
    rep.update(bank=str(bf.bank.path), dataset=str(ds.path), split=ds.split)
    if args.json:
        print(json.dumps(rep, indent=2))
        return 0
    print(f'## teach-and-query: {Path(ds.path).name} [{ds.split}], {len(ds.class_names)} classes, '
          f'{rep["shots"]} scans a class taught into {Path(rep["bank"]).name}, '
          f'{rep["draws"]} draws (seed {rep["seed"]}), metric size '
          f'{"on" if rep["metric_size"] else "off"}, fit threshold {fit:g}, volume '
          f'threshold {"off" if vol is None else f"{vol:g}"}, scene threshold '
          f'{"off" if scene is None else f"{scene:g}"}')
    print('| figure | mean ± std over draws |\n|---|---|')
    for key, v in rep['summary'].items():
        pct = not key.startswith('auroc')
        scale, unit = (100, ' %') if pct else (1, '')
        print(f'| {key.replace("_", " ")} | {scale * v["mean"]:.{1 if pct else 3}f} ± '
              f'{scale * v["std"]:.{1 if pct else 3}f}{unit} |')
    return 0
