"""`point_gn bank add|remove|history`: enroll examples into a bank, forget a class, offline.

Same operations and refitting as the node's live enrollment (bank/enroll.py); the bank is
rewritten atomically (in place, or to -o OUT).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from point_gn_ros.commands.common import add_encoder_args, add_up_arg, to_z_up


def register(sub: argparse._SubParsersAction) -> None:
    """Add `add` and `remove` to the `bank` command registered by bank_cmd."""
    bank = sub.choices.get('bank')
    if bank is None:
        return
    bsub = next(a for a in bank._actions if isinstance(a, argparse._SubParsersAction))

    a = bsub.add_parser('add', help='encode point files (or one class of a dataset) and add '
                                    'them to a bank under a class, new or existing')
    a.add_argument('bank', metavar='BANK',
                   help="bank file (.npz) to extend; 'default' = the shipped bank (then -o)")
    a.add_argument('inputs', metavar='DATASET_OR_FILES', nargs='+',
                   help='point files (.pcd .ply .npy .txt .xyz .csv) and/or folders of them; '
                        'or one dataset (h5 folder/file, class-per-folder tree), of which the '
                        'objects of --from-class are taken')
    a.add_argument('--class', dest='class_name', required=True, metavar='NAME',
                   help='class the examples are filed under')
    a.add_argument('--from-class', default=None, metavar='NAME',
                   help='dataset input: the dataset class to take (default: --class)')
    a.add_argument('--split', default='train', help='dataset input: split (default train)')
    a.add_argument('--limit', type=int, default=None, metavar='N',
                   help='take at most the first N examples')
    a.add_argument('--augment', choices=('none', 'mirror', 'rot4', 'd4'), default='none',
                   help="store each example in these frames (core/augment.py): 'd4' = the 8 "
                        'frames the yaw alignment confuses on partial scans (8 entries per '
                        "example); default 'none'")
    add_up_arg(a)
    a.add_argument('--units', choices=('m', 'none'), default='m',
                   help="what the coordinates measure: 'm' metres (sensor data; default): the "
                        "class keeps its examples' sizes (core/size.py, docs/SIZE.md); 'none' "
                        'for data without metric meaning (unit-sphere data sets such as '
                        'ModelNet40): no size model')
    a.add_argument('--fuse-views', action='store_true',
                   help='the inputs are views of ONE object in one fixed frame (odom, map): '
                        'also add their fused cloud and 8 scans simulated from it '
                        '(core/fusion.py); refused if the views do not overlap')
    a.add_argument('--lda-debias', type=_share, default=2.0, metavar='F',
                   help="share of a wide LDA's mean-noise correction for a class this add "
                        'creates (lda_noise_trace): its LDA bias rises by F x '
                        'tr(P Sigma) / (2 n) for its n examples; 0 = none, 0-2; with '
                        '--steal-budget, the most a class gets (default 2: train CV)')
    a.add_argument('--steal-budget', type=_budget, default=0.001, metavar='RHO',
                   help='give a class this add creates the largest share <= --lda-debias '
                        'whose predicted share of built-class examples called it stays <= '
                        'RHO (bank/discriminant.py); 0 = the share itself, 0-0.5 (default 0.001: '
                        'train CV)')
    _common(a)
    a.set_defaults(func=_add)

    r = bsub.add_parser('remove', help='forget a class: drop its entries from a bank')
    r.add_argument('bank', metavar='BANK', help='bank file (.npz)')
    r.add_argument('class_name', metavar='NAME', help='class to remove')
    _common(r)
    r.set_defaults(func=_remove)

    h = bsub.add_parser('history', help='bank version, per-class counts and every enrollment')
    h.add_argument('bank', metavar='BANK', help='bank file (.npz)')
    h.set_defaults(func=_history)


def resolve_bank(name: str, output: str | None = '') -> Path:
    """BANK as given, or the shipped bank for 'default' (a change then needs -o OUT).

    output: '' when the bank is only read; None when a change would rewrite it in place.
    """
    from point_gn_ros.bank.store import default_bank_path
    from point_gn_ros.errors import BankError

    if name != 'default' or Path(name).exists():
        return Path(name)
    if output is None:
        raise BankError("'default' is the shipped bank, which is not rewritten: give -o "
                        'OUT.npz for the changed copy')
    return default_bank_path()


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument('-o', '--output', default=None,
                   help='write the result here (default: rewrite BANK, atomically)')
    p.add_argument('--gamma', choices=('auto', 'keep', 'cv'), default='auto',
                   help="gamma after the change: 'keep', re-choose by k-fold 'cv' on the bank, "
                        "or 'auto' (CV on banks up to 2,000 entries whose classes all have "
                        '>= --folds examples; default)')
    p.add_argument('--calibration', choices=('auto', 'keep', 'recalibrate'), default='auto',
                   help="open-set threshold: 'keep', 'recalibrate' on held-out folds, or "
                        "'auto' (recalibrate when gamma is re-chosen; default)")
    p.add_argument('--min-examples', type=int, default=1,
                   help='classes with fewer examples take no part in the refit (default 1)')
    p.add_argument('--folds', type=int, default=5, help='CV folds for the refit (default 5)')
    # bank/refit.py LDA_PRIORS, spelt out: the parser is built without importing torch
    p.add_argument('--lda-prior', choices=('entries', 'balanced', 'typical'), default='typical',
                   help="LDA class priors of the refitted head: each class's share of the "
                        "entries, 'balanced' (equal: few-example classes are not penalised) "
                        "or 'typical' (default: built classes keep theirs, each enrolled "
                        'class gets the mean of theirs)')
    add_encoder_args(p)


def _policy(args: argparse.Namespace):
    from point_gn_ros.bank.refit import RefitPolicy
    return RefitPolicy(gamma=args.gamma, calibration=args.calibration,
                       min_examples=args.min_examples, folds=args.folds,
                       lda_prior=args.lda_prior,
                       lda_debias=getattr(args, 'lda_debias', 0.0),
                       lda_steal_budget=getattr(args, 'steal_budget', 0.0))


def _in_range(text: str, top: float) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
    if not 0.0 <= value <= top:
        raise argparse.ArgumentTypeError(f'{value:g} must be in [0, {top:g}]')
    return value


def _share(text: str) -> float:
    from point_gn_ros.bank.discriminant import MAX_SHARE
    return _in_range(text, MAX_SHARE)


def _budget(text: str) -> float:
    from point_gn_ros.bank.discriminant import MAX_BUDGET
    return _in_range(text, MAX_BUDGET)



def _read_inputs(args: argparse.Namespace) -> tuple[list, str]:
    """-> (clouds (N_i, 3) float32, a description of the source for the enrollment log)."""
    from point_gn_ros.datasets.open import detect_format
    from point_gn_ros.datasets.points import POINT_EXTENSIONS, read_points
    from point_gn_ros.errors import DatasetError

    paths = [Path(p) for p in args.inputs]
    files: list[Path] = []
    for p in paths:
        if not p.exists():
            raise DatasetError(f'{p}: no such file or folder')
        if p.is_file() and p.suffix.lower() in POINT_EXTENSIONS:
            files.append(p)
        elif len(paths) == 1 and detect_format(p) != 'folder':
            return _read_dataset(args, p)       # an h5 dataset (file or folder)
        elif p.is_dir() and any(f.suffix.lower() in POINT_EXTENSIONS for f in p.iterdir()
                                if f.is_file()):
            files.extend(sorted(f for f in p.rglob('*') if f.is_file()
                                and f.suffix.lower() in POINT_EXTENSIONS
                                and not f.name.startswith('.')))
        elif len(paths) == 1:
            return _read_dataset(args, p)
        else:
            raise DatasetError(f'{p}: neither a point file nor a folder of point files (a '
                               'dataset must be the only input)')
    files = files[:args.limit] if args.limit else files
    clouds = [read_points(f) for f in files]
    return clouds, f'files: {", ".join(str(f) for f in files[:3])}' + (
        f' (+{len(files) - 3})' if len(files) > 3 else '')


def _read_dataset(args: argparse.Namespace, path: Path) -> tuple[list, str]:
    from point_gn_ros.datasets import open_dataset
    from point_gn_ros.errors import DatasetError

    ds = open_dataset(path, split=args.split)
    want = args.from_class or args.class_name
    if want not in ds.class_names:
        raise DatasetError(f'{path}: no class {want!r} in the {args.split} split (classes: '
                           f'{", ".join(ds.class_names)}); pick one with --from-class')
    idx = [i for i, lbl in enumerate(ds.labels) if ds.class_names[lbl] == want]
    idx = idx[:args.limit] if args.limit else idx
    return [ds[i][0] for i in idx], f'dataset {path} [{args.split}] class {want}'


def _add(args: argparse.Namespace) -> int:
    from point_gn_ros.bank.enroll import BankFile, EnrollError, add_examples
    from point_gn_ros.core.size import size_descriptors
    from point_gn_ros.recognizer import encode_clouds, make_encoder

    bf = BankFile.load(resolve_bank(args.bank, args.output))
    clouds, source = _read_inputs(args)
    if args.up != 'z':      # the bank's frame is z up, as `classify --up` and the node's up_axis
        clouds = [to_z_up(c, args.up) for c in clouds]
        source = f'{source} (up {args.up})'
    empty = [i for i, c in enumerate(clouds) if len(c) == 0]
    if not clouds or empty:
        raise EnrollError(f'no usable example: {len(clouds)} input(s), empty: {empty}')
    if args.fuse_views:
        from point_gn_ros.core.fusion import with_fused
        n = len(clouds)
        clouds, note = with_fused(clouds)
        if len(clouds) == n:
            raise EnrollError(f'--fuse-views: {note}')
        source = f'{source}; {note}'
    encoder = make_encoder(bf.bank.config, args.device)
    feats = encode_clouds(clouds, encoder, batch_size=args.batch_size, augment=args.augment)
    sizes = size_descriptors(clouds) if args.units == 'm' else None
    res = add_examples(bf, feats, args.class_name, source=f'point_gn bank add: {source}',
                       policy=_policy(args), augment=args.augment, sizes=sizes)
    return _write(args, res)


def _remove(args: argparse.Namespace) -> int:
    from point_gn_ros.bank.enroll import BankFile, remove_class

    res = remove_class(BankFile.load(resolve_bank(args.bank, args.output)), args.class_name,
                       source='point_gn bank remove', policy=_policy(args))
    return _write(args, res)


def _history(args: argparse.Namespace) -> int:
    from point_gn_ros.bank.enroll import bank_version, class_counts
    from point_gn_ros.bank.store import FeatureBank

    bank = FeatureBank.load(resolve_bank(args.bank))
    print(f'{bank.path}: bank version {bank_version(bank)}, {len(bank)} entries, '
          f'{bank.num_classes} classes')
    print('  ' + ', '.join(f'{c} {n}' for c, n in class_counts(bank).items()))
    for e in bank.enrollments:
        dups = f', {e.near_duplicates} near-duplicate(s)' if e.near_duplicates else ''
        aug = f' ({e.examples} examples, {e.augment})' if e.augment else ''
        print(f'  v{e.version} {e.time} {e.action} {e.class_name!r} x{e.count}'
              f'{aug}{dups} ({e.source})')
    refit = bank.meta.get('refit')
    if refit:
        print(f'  last refit (v{refit["version"]}): gamma {refit["gamma"]:g} '
              f'({refit["gamma_reason"]}); head {refit.get("head", "?")}; threshold '
              f'{refit["calibration_reason"]}')
    return 0


def _write(args: argparse.Namespace, res) -> int:
    path = res.file.save(args.output or args.bank)
    print(res.describe())
    for d in res.duplicates:
        kind = 'same class' if d.same_class else 'OTHER class'
        print(f'  near-duplicate: example #{d.index} ~ {d.other} (cosine {d.cosine:.5f}, {kind})')
    print(f'wrote {path}: {res.bank.summary()}')
    return 0
