"""`point_gn classify FILE...`: what the node would answer for point files (PCD, PLY, npy, txt).

Each file is one segmented object (the node's input after segmentation): NaN points are
dropped by the reader, then the cloud goes through the same Recognizer as the node. An
unknown answer names the rules that made it so (`Classification.rejected_by`: volume, scene,
fit, size, probability, novelty; docs/SIZE.md).
"""

from __future__ import annotations

import argparse
import json

from point_gn_ros.commands.common import add_up_arg, to_z_up


def register(sub: argparse._SubParsersAction) -> None:
    c = sub.add_parser('classify', help='classify point files (one object each) against a bank')
    c.add_argument('files', nargs='+', metavar='FILE', help='.pcd .ply .npy .txt .xyz files')
    c.add_argument('--bank', default=None, help='bank file (default: the shipped bank)')
    c.add_argument('--top-k', type=int, default=3, help='classes to list per file (default 3)')
    add_up_arg(c)
    c.add_argument('--no-units', action='store_true',
                   help='the files are not in metres (e.g. unit-sphere data): no size evidence')
    c.add_argument('--json', action='store_true', help='print JSON lines')
    c.set_defaults(func=_classify)


def _classify(args: argparse.Namespace) -> int:
    from point_gn_ros.datasets import read_points
    from point_gn_ros.recognizer import Recognizer

    rec = Recognizer.as_node(args.bank, top_k=args.top_k, metric_size=not args.no_units)
    names = rec.class_names
    for path in args.files:
        xyz = to_z_up(read_points(path), args.up)
        res = rec.classify_clouds([xyz])
        top = [(names[int(i)], float(s))
               for i, s in zip(res.topk_ids[0], res.topk_scores[0], strict=True)]
        extent = (xyz.max(axis=0) - xyz.min(axis=0)).tolist() if len(xyz) else [0.0] * 3
        # Two-section banks: how likely the gate thinks this is a single-view scan.
        partial = None if res.partial is None else float(res.partial[0])
        label = names[int(res.labels[0])] if res.labels[0] >= 0 else 'unknown'
        if args.json:
            print(json.dumps({'file': path, 'points': len(xyz), 'extent': extent,
                              'label': label,
                              'rejected_by': res.rejected_by[0],
                              'top': [{'class': n, 'score': s} for n, s in top],
                              'partial': partial}))
        else:
            guesses = ', '.join(f'{n} {s:.2f}' for n, s in top)
            size = ' x '.join(f'{e:.2f}' for e in extent)
            seen = '' if partial is None else f' (single-view scan: {partial:.2f})'
            why = f' [{res.rejected_by[0]}]' if res.labels[0] < 0 else ''
            print(f'{path}: {len(xyz)} points, extent {size}{seen}: {label}{why} ({guesses})')
    return 0
