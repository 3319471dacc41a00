"""`point_gn bank build|info`: make a feature bank from a dataset, or describe one."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from point_gn_ros.bank.selection import DEFAULT_ALPHAS, DEFAULT_WEIGHTS
from point_gn_ros.commands.common import add_dataset_args, add_encoder_args
from point_gn_ros.core.config import UPSAMPLE_METHODS

# The paper's GPE width for real scans (ScanObjectNN); 0.4 (the default) for CAD models.
SCANOBJECTNN_SIGMA = 0.3


def register(sub: argparse._SubParsersAction) -> None:
    bank = sub.add_parser('bank', help='build or inspect a feature bank')
    bsub = bank.add_subparsers(dest='bank_command', required=True, metavar='ACTION')

    b = bsub.add_parser('build', help='encode a dataset split into a bank; knobs chosen by '
                                      'k-fold cross-validation on that split only')
    add_dataset_args(b, 'train')
    add_encoder_args(b)
    b.add_argument('-o', '--output', required=True, help='bank file to write (.npz)')
    b.add_argument('--sigma', type=float, default=None,
                   help='GPE sigma (default: 0.3 for ScanObjectNN, else 0.4, as in the '
                        'paper)')
    b.add_argument('--k', type=int, default=None, help='neighbours per centre (default 120)')
    b.add_argument('--extra-sigmas', type=float, nargs='+', default=[], metavar='SIGMA',
                   help='multi-scale features: also encode every cloud with these GPE sigmas '
                        'and concatenate (e.g. 0.25: +0.4 points CV on ModelNet40 at ~2x the '
                        "encoder's cost per cloud)")
    b.add_argument('--upsample', choices=UPSAMPLE_METHODS, default='midpoint',
                   help='how clouds with fewer points than the encoder takes are filled up: '
                        'midpoint (default: new points between neighbouring points; +2-3 '
                        'points on single-view scans by grouped CV) or repeat '
                        '(points repeated)')
    b.add_argument('--yaw-align', action='store_true',
                   help='rotate every cloud into a canonical heading about z before encoding '
                        '(yaw-invariant bank, for upright objects seen from any side)')
    b.add_argument('--views', type=int, default=0, metavar='K',
                   help='sensor-realistic bank: add K simulated single-view scans of every '
                        'object (core/views.py), every entry at a random yaw; CV folds keep an '
                        'object and its views together. Without --yaw-align this is yaw '
                        'augmentation (no canonical frame)')
    b.add_argument('--view-seed', type=int, default=0, help='seed of the --views scans')
    b.add_argument('--view-protocol', choices=('hpr', 'zbuffer', 'mixed'), default='hpr',
                   help='how the --views scans are simulated (as in eval --single-view); '
                        'mixed: half hidden point removal, half z-buffer scans')
    b.add_argument('--cv-every', type=int, default=1, metavar='N',
                   help='cross-validate on every N-th object (with its views) only, then fit '
                        'the chosen knobs on all (CV cost grows with the square of the bank)')
    b.add_argument('--dtype', choices=('float16', 'float32', 'int8', 'int4'), default='float16',
                   help='stored feature precision (default float16; int8: a quarter of '
                        'float32, cosines within ~1e-3; int4: an eighth, cosines off by ~1e-2 '
                        'on average, no loss measured by CV on scans)')
    b.add_argument('--matrix-dtype', choices=('float32', 'float16'), default='float32',
                   help='precision of the fitted PCA projection, whitening and wide-LDA '
                        'precision (float16: about half their bytes; the fit uses the rounded '
                        'values; format 5, which older readers refuse: bank/store.py)')
    b.add_argument('--sections', action='store_true',
                   help='with --views: keep complete objects and scans as two sections, each '
                        'with its own knobs chosen by CV (complete: --dims; scans: '
                        '--views-dims, CV on every --cv-every-th object), mixed at query time '
                        'by a gate that tells complete objects from scans (bank/builder.py)')
    b.add_argument('--views-dims', type=int, nargs='+', default=None,
                   help='with --sections: candidate PCA dims of the scan section (default: '
                        'as --dims)')
    b.add_argument('--dims', type=int, nargs='+', default=None,
                   help='candidate PCA dimensions to choose from by CV (0 = all dims)')
    b.add_argument('--standardize', nargs='+', default=['none', 'standardize'],
                   choices=('none', 'centre', 'standardize'),
                   help='candidate feature standardisations to choose from by CV')
    b.add_argument('--folds', type=int, default=5, help='cross-validation folds (default 5)')
    b.add_argument('--alphas', type=float, nargs='+', default=None,
                   help='candidate covariance shrinkages of the discriminant head, chosen by '
                        f'CV (default {" ".join(map(str, DEFAULT_ALPHAS))})')
    b.add_argument('--weights', type=float, nargs='+', default=None,
                   help='candidate LDA fusion weights, chosen by CV (0 = vote only; default '
                        f'{" ".join(map(str, DEFAULT_WEIGHTS))})')
    b.add_argument('--wide-lda', choices=('none', 'scans', 'all'), default='none',
                   help="let CV also weigh the head's LDA on every standardised encoder dim "
                        'instead of the PCA dims (bank/model.py; stores a D x D precision for '
                        'enrollment, 5.2 MB at 1,620 dims): none, scans (the --sections scan '
                        'section only) or all')
    b.add_argument('--ridge', choices=('none', 'complete', 'all'), default='none',
                   help='let CV also weigh a kernel ridge term in the head (bank/discriminant.py; '
                        'per-entry coefficients, an (N, N) solve at build, banks or sections '
                        'of at most 16,000 entries): none, complete (the --sections complete '
                        'section, or a bank without sections) or all')
    b.add_argument('--vote-only', action='store_true',
                   help="no discriminant head: the paper's plain kernel vote")
    b.add_argument('--false-reject-rate', type=float, default=0.05,
                   help='open-set calibration target (default 0.05)')
    b.add_argument('--strict', action='store_true',
                   help='fail when any file of the dataset is skipped (unreadable, empty, '
                        'unsupported); by default they are listed and left out')
    b.add_argument('--default-bank', action='store_true',
                   help='settings of the shipped default bank (float16, standardised, PCA '
                        'dims chosen by CV among 512 and 640, which fit 20 MB with the head)')
    b.set_defaults(func=_build)

    pa = bsub.add_parser('path', help="print the shipped bank's path ('default' as BANK)")
    pa.set_defaults(func=lambda args: print(_default_path()) or 0)

    i = bsub.add_parser('info', help='print a bank summary')
    i.add_argument('bank', metavar='BANK', help='bank file (.npz)')
    i.add_argument('--json', action='store_true', help='print the metadata as JSON')
    i.set_defaults(func=_info)


def _build(args: argparse.Namespace) -> int:
    from point_gn_ros.bank.builder import build_bank
    from point_gn_ros.commands.common import open_dataset_from_args
    from point_gn_ros.core.config import EncoderConfig

    ds = open_dataset_from_args(args)
    if args.sigma is None and ds.format == 'scanobjectnn_h5':
        args.sigma = SCANOBJECTNN_SIGMA
    overrides = {k: v for k, v in (('sigma', args.sigma), ('k', args.k)) if v is not None}
    overrides['yaw_align'] = args.yaw_align
    overrides['extra_sigmas'] = tuple(args.extra_sigmas)
    overrides['upsample'] = args.upsample
    cfg = EncoderConfig(**overrides)
    dims = [None if d == 0 else d for d in (args.dims or [0])]
    if args.sections and not args.views:
        raise SystemExit('bank build: --sections needs --views K')
    if args.default_bank:
        args.dtype = args.dtype if args.dtype in ('int8', 'int4') else 'float16'
        dims = args.dims and dims or [512, 640]
        args.standardize = ['standardize']
    print(f'{ds.format} {ds.split}: {len(ds)} objects, {len(ds.class_names)} classes')
    _report_input(ds, cfg, args, dims)
    groups, views_meta = None, None
    if args.views:
        from point_gn_ros.core.views import VIEW_PROTOCOLS
        from point_gn_ros.datasets.views import ViewsDataset
        cfgs = VIEW_PROTOCOLS[args.view_protocol]
        ds = ViewsDataset(ds, args.views, args.view_seed, cfgs if len(cfgs) > 1 else cfgs[0],
                          include_full=True, random_yaw=True)
        groups = ds.groups
        views_meta = {**ds.describe(), 'protocol': args.view_protocol,
                      'rotation': 'yaw_align' if args.yaw_align else 'yaw_augment'}
        print(f'+ {args.views} simulated views per object: {len(ds)} entries '
              f'({views_meta["rotation"]})')
    alphas = () if args.vote_only else tuple(args.alphas or DEFAULT_ALPHAS)
    import numpy as np

    cv_subset = None
    if args.cv_every > 1:
        source = groups if groups is not None else np.arange(len(ds))
        cv_subset = np.flatnonzero(source % args.cv_every == 0)
    common = dict(standardize_options=tuple(args.standardize), folds=args.folds,
                  stored_dtype=args.dtype, matrix_dtype=args.matrix_dtype,
                  false_reject_rate=args.false_reject_rate, alphas=alphas,
                  weights=tuple(args.weights or DEFAULT_WEIGHTS))
    cache = Path(args.cache) if args.cache else None
    if args.sections:
        bank = _build_sections(ds, cfg, args, dims, cv_subset, cache, common)
    else:
        bank = build_bank(ds, cfg, args.device, dims_options=tuple(dims), cache_dir=cache,
                          groups=groups, cv_subset=cv_subset, wide_lda=args.wide_lda != 'none',
                          ridge=args.ridge != 'none', **common)
    if views_meta is not None:
        bank.meta['views'] = views_meta
    path = bank.save(args.output, dtype=args.dtype)
    print(f'chosen by {args.folds}-fold CV on {ds.split}:')
    print('\n'.join(describe_selection(bank.meta)))
    print(f'wrote {path} ({path.stat().st_size / 1e6:.1f} MB): {len(bank)} entries')
    return 0


def _build_sections(ds, cfg, args: argparse.Namespace, dims: list,  # noqa: ANN001
                    cv_subset, cache: Path | None, common: dict):  # noqa: ANN001, ANN202
    """A two-section bank (bank/builder.py) from a views dataset, encoded once."""
    import numpy as np
    import torch

    from point_gn_ros.bank.builder import build_bank, encode_dataset
    from point_gn_ros.bank.builder import RowsDataset, combine_sections
    from point_gn_ros.recognizer import make_encoder

    feats = encode_dataset(ds, make_encoder(cfg, args.device), cache_dir=cache)
    scan = np.asarray(ds.view_index) >= 0
    views_dims = [None if d == 0 else d for d in args.views_dims] if args.views_dims else dims
    print(f'section 1, complete objects: {int((~scan).sum())} entries, CV on all of them')
    complete = build_bank(RowsDataset(ds, ~scan, 'complete'), cfg, args.device,
                          feats=feats[torch.from_numpy(~scan)], dims_options=tuple(dims),
                          wide_lda=args.wide_lda == 'all', ridge=args.ridge != 'none',
                          **common)
    print('\n'.join(describe_selection(complete.meta)))
    sub = None if cv_subset is None else np.flatnonzero(np.isin(
        np.flatnonzero(scan), cv_subset))
    print(f'section 2, single-view scans: {int(scan.sum())} entries, CV grouped by object'
          + ('' if sub is None else f' on {len(sub)} of them'))
    views = build_bank(RowsDataset(ds, scan, 'scans'), cfg, args.device,
                       feats=feats[torch.from_numpy(scan)], dims_options=tuple(views_dims),
                       groups=np.asarray(ds.groups)[scan], cv_subset=sub,
                       wide_lda=args.wide_lda != 'none', ridge=args.ridge == 'all', **common)
    print('\n'.join(describe_selection(views.meta)))
    return combine_sections(complete, views, feats, scan, groups=np.asarray(ds.groups))


def _report_input(ds, cfg, args: argparse.Namespace, dims: list) -> None:  # noqa: ANN001
    """Print the settings in use; list skipped files; warn on classes too small for the folds.

    Raises DatasetError under --strict when files were skipped.
    """
    import sys
    from collections import Counter

    from point_gn_ros.errors import DatasetError

    skipped = list(getattr(ds, 'skipped', []))
    for where, why in skipped[:_MAX_LISTED]:
        print(f'skipped {where}: {why}', file=sys.stderr)
    if len(skipped) > _MAX_LISTED:
        print(f'skipped ... and {len(skipped) - _MAX_LISTED} more file(s)', file=sys.stderr)
    if skipped:
        print(f'warning: {len(skipped)} file(s) skipped, not in the bank', file=sys.stderr)
        if args.strict:
            raise DatasetError(f'{ds.path}: {len(skipped)} file(s) could not be used '
                               f'(--strict), first: {skipped[0][0]}: {skipped[0][1]}')
    counts = Counter(int(label) for label in ds.labels)
    empty = [name for c, name in enumerate(ds.class_names) if not counts.get(c)]
    if empty:   # the bank would be refused on load (bank/store.py): say so now
        raise DatasetError(f'{ds.path}: {len(empty)} class(es) have no examples in split '
                           f'{ds.split!r}: {", ".join(empty[:10])}'
                           + (' ...' if len(empty) > 10 else ''))
    small = [(ds.class_names[c], counts.get(c, 0)) for c in range(len(ds.class_names))
             if counts.get(c, 0) < args.folds]
    if small:
        listed = ', '.join(f'{name} ({n})' for name, n in small[:10])
        print(f'warning: {len(small)} class(es) have fewer examples than --folds '
              f'{args.folds}, so some CV folds hold none of them and the chosen settings and '
              f'CV accuracy are less reliable: {listed}' + (' ...' if len(small) > 10 else ''),
              file=sys.stderr)
    c = cfg.to_dict()
    print('settings: ' + ' '.join(f'{k}={v}' for k, v in c.items())
          + f' dtype={args.dtype} matrix_dtype={args.matrix_dtype} folds={args.folds}'
          + f' dims={[d or "all" for d in dims]} standardize={list(args.standardize)}'
          + f' false_reject_rate={args.false_reject_rate:g}')


_MAX_LISTED = 20   # skipped files listed one per line, then counted


def describe_selection(meta: dict) -> list[str]:
    """Lines describing a bank's CV choices, head and calibration (build and info)."""
    lines = []
    sel, head = meta.get('selection', {}), meta.get('head', {})
    if meta.get('matrix_dtype', 'float32') != 'float32':
        lines.append(f'  fitted matrices stored as {meta["matrix_dtype"]} (bank/store.py)')
    if sel:
        lines.append(f'  transform: standardize={sel.get("standardize")} '
                     f'dims={sel.get("dims") or "all"}; gamma={sel.get("gamma"):g}; '
                     f'{sel.get("cv_folds")}-fold CV'
                     f'{" (grouped)" if sel.get("cv_grouped") else ""} accuracy '
                     f'{100 * sel.get("cv_accuracy", float("nan")):.2f} %')
    if head.get('folds_used') is not None or head.get('fallback'):
        space = 'plain'
        if head.get('whiten_vote'):
            space = f'whitened (shrinkage {head["alpha"]:g})'
        lda = f'{head.get("fusion_weight", 0):g} x LDA log-probabilities'
        if head.get('lda_alpha') is not None and head.get('fusion_weight'):
            lda += (f' (shrinkage {head["lda_alpha"]:g}'
                    f'{", on every standardised dim" if head.get("lda_wide") else ""})')
        loss = head.get('cv_log_loss')
        lines.append(f'  head: kernel vote on {space} features + {lda}; temperature '
                     f'{head.get("temperature", 1):.3g}'
                     + (f', CV log-loss {loss:.3f}' if loss is not None else ''))
        ridge = head.get('ridge')
        if ridge and ridge.get('weight'):
            lines.append(f'  + {ridge["weight"]:g} x kernel ridge scores (kernel gamma '
                         f'{ridge["gamma"]:g}, lambda {ridge["lambda"]:g}; bank/discriminant.py)')
        elif ridge:
            lines.append('  kernel ridge term weighed by CV, not kept (no held-out gain)')
        vote = head.get('vote_cv_accuracy')
        if vote is not None:
            lines.append(f'  plain kernel vote on the same folds: CV accuracy {100 * vote:.2f} %')
        if head.get('fallback'):
            lines.append(f'  CV fallback: {head["fallback"]}')
    elif meta.get('format_version', 2) == 1:
        lines.append('  head: none (format 1: plain kernel vote; rebuild for the head)')
    nov = meta.get('novelty_calibration')
    if nov:
        lines.append(f'  novelty threshold at the same false-reject rate: {nov["threshold"]:.4f} '
                     '(Classifier novelty_threshold)')
    cal = meta.get('unknown_calibration')
    if cal:
        what = ('novelty above' if cal.get('measure') == 'novelty'
                else 'top-1 probability below')
        lines.append(f'  default unknown rule: {what} {cal["threshold"]:.4f} '
                     f'(false-reject rate {100 * cal["false_reject_rate"]:.0f} % on held-out '
                     'folds)')
    return lines


def _default_path() -> Path:
    from point_gn_ros.bank.store import default_bank_path
    return default_bank_path()


def _info(args: argparse.Namespace) -> int:
    from point_gn_ros.bank.store import FeatureBank

    from point_gn_ros.commands.enroll_cmd import resolve_bank
    bank = FeatureBank.load(resolve_bank(args.bank))
    if args.json:
        print(json.dumps(bank.file_meta(), indent=2, sort_keys=True))
        return 0
    print(f'{bank.path}: {bank.summary()}')
    print('\n'.join(describe_selection(bank.meta)))
    if bank.views is not None:
        g = bank.meta.get('gate', {})
        print(f'  single-view section: {len(bank.views)} entries')
        print('\n'.join('  ' + line for line in describe_selection(bank.views.meta)))
        print(f'  gate (complete vs scan): LDA on {g.get("dims") or "all"} dims, shrinkage '
              f'{g.get("shrinkage")}, {g.get("priors")} priors; routes '
              f'{100 * g.get("train_routing_complete", float("nan")):.1f} % of complete '
              f'objects and {100 * g.get("train_routing_scans", float("nan")):.1f} % of '
              f'scans right on the bank itself')
    if bank.objects is not None:
        o = bank.objects
        print(f'  object test of taught classes (bank/model.py): {len(o.means)} built '
              f'objects, rank {o.rank}, shrinkage {o.alpha:g}, slope {o.lam:g}, offset '
              f'{o.theta:g}')
    from point_gn_ros.bank.classifier import Classifier
    path = Classifier(bank).path
    print(f'  query path (CPU): {path["head"]} head, lone queries {path["lone"]}, '
          f'{path["search"]} search')
    prov = bank.provenance
    print(f'  created {prov.get("created", "?")}; classes: {", ".join(bank.class_names)}')
    return 0
