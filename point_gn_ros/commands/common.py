"""Argument helpers shared by the sub-commands."""

from __future__ import annotations

import argparse

DATASET_FORMATS = ('modelnet40_h5', 'scanobjectnn_h5', 'folder')


def add_dataset_args(p: argparse.ArgumentParser, default_split: str) -> None:
    p.add_argument('dataset', metavar='DATASET',
                   help='dataset path: ModelNet40 h5 folder, ScanObjectNN h5 folder or file, '
                        'or a folder tree <class>/<file> (.pcd .ply .npy .txt .xyz)')
    p.add_argument('--split', default=default_split,
                   help=f'split to read (default {default_split})')
    p.add_argument('--format', choices=DATASET_FORMATS, default=None,
                   help='dataset kind (default: detected)')
    p.add_argument('--variant', default=None,
                   help='ScanObjectNN variant: OBJ_BG, OBJ_ONLY or PB_T50_RS')


def add_encoder_args(p: argparse.ArgumentParser) -> None:
    p.add_argument('--device', default='cpu', help='torch device: cpu or cuda (default cpu)')
    p.add_argument('--batch-size', type=int, default=64, help='clouds per encoder batch')
    p.add_argument('--cache', default=None, metavar='DIR',
                   help='reuse encoded features cached in DIR (keyed by data and encoder)')


def open_dataset_from_args(args: argparse.Namespace):
    from point_gn_ros.datasets import open_dataset
    kwargs = {'split': args.split, 'format': args.format}
    if getattr(args, 'variant', None):
        kwargs['variant'] = args.variant
    return open_dataset(args.dataset, **kwargs)
