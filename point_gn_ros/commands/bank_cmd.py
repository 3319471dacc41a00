"""`point_gn bank build|info`: make a feature bank from a dataset, or describe one."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from point_gn_ros.commands.common import add_dataset_args, add_encoder_args

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
    b.add_argument('--yaw-align', action='store_true',
                   help='rotate every cloud into a canonical heading about z before encoding '
                        '(yaw-invariant bank, for upright objects seen from any side)')
    b.add_argument('--dtype', choices=('float16', 'float32'), default='float16',
                   help='stored feature precision (default float16)')
    b.add_argument('--dims', type=int, nargs='+', default=None,
                   help='candidate PCA dimensions to choose from by CV (0 = all dims)')
    b.add_argument('--standardize', nargs='+', default=['none', 'standardize'],
                   choices=('none', 'centre', 'standardize'),
                   help='candidate feature standardisations to choose from by CV')
    b.add_argument('--folds', type=int, default=5, help='cross-validation folds (default 5)')
    b.add_argument('--false-reject-rate', type=float, default=0.05,
                   help='open-set calibration target (default 0.05)')
    b.add_argument('--strict', action='store_true',
                   help='fail when any file of the dataset is skipped (unreadable, empty, '
                        'unsupported); by default they are listed and left out')
    b.add_argument('--default-bank', action='store_true',
                   help='settings of the shipped default bank (float16, dims chosen among '
                        'those fitting 20 MB)')
    b.set_defaults(func=_build)

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
    cfg = EncoderConfig(**overrides)
    dims = [None if d == 0 else d for d in (args.dims or [0])]
    if args.default_bank:
        args.dtype = 'float16'
        dims = args.dims and dims or [256, 384, 512]
    print(f'{ds.format} {ds.split}: {len(ds)} objects, {len(ds.class_names)} classes')
    _report_input(ds, cfg, args, dims)
    bank = build_bank(ds, cfg, args.device, standardize_options=tuple(args.standardize),
                      dims_options=tuple(dims), folds=args.folds,
                      false_reject_rate=args.false_reject_rate,
                      cache_dir=Path(args.cache) if args.cache else None)
    path = bank.save(args.output, dtype=args.dtype)
    sel = bank.meta['selection']
    print(f'chosen by {args.folds}-fold CV on {ds.split}: standardize={sel["standardize"]} '
          f'dims={sel["dims"] or "all"} gamma={sel["gamma"]:g} '
          f'(CV accuracy {100 * sel["cv_accuracy"]:.2f} %)')
    print(f'wrote {path} ({path.stat().st_size / 1e6:.1f} MB): {len(bank)} entries')
    return 0


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
    if empty:   # the bank would be refused on load (bank/validate.py): say so now
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
          + f' dtype={args.dtype} folds={args.folds}'
          + f' dims={[d or "all" for d in dims]} standardize={list(args.standardize)}'
          + f' false_reject_rate={args.false_reject_rate:g}')


_MAX_LISTED = 20   # skipped files listed one per line, then counted


def _info(args: argparse.Namespace) -> int:
    from point_gn_ros.bank.store import FeatureBank

    bank = FeatureBank.load(args.bank)
    if args.json:
        print(json.dumps(bank.meta, indent=2, sort_keys=True))
        return 0
    print(f'{bank.path}: {bank.summary()}')
    sel = bank.meta.get('selection', {})
    if sel:
        print(f'  selection ({sel.get("cv_folds")}-fold CV on the bank): '
              f'standardize={sel.get("standardize")} dims={sel.get("dims") or "all"} '
              f'gamma={sel.get("gamma"):g} cv_accuracy={100 * sel.get("cv_accuracy", 0):.2f} %')
    cal = bank.meta.get('unknown_calibration')
    if cal:
        print(f'  unknown threshold {cal["threshold"]:.4f} '
              f'(false-reject rate {100 * cal["false_reject_rate"]:.0f} %)')
    prov = bank.meta.get('provenance', {})
    print(f'  created {prov.get("created", "?")}; classes: {", ".join(bank.class_names)}')
    return 0
