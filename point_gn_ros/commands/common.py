"""Argument helpers shared by the sub-commands."""

from __future__ import annotations

import argparse

import numpy as np

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


# Proper rotations taking the named axis to +z (rows: new x, y, z as old coordinates).
UP_AXES = {'z': np.eye(3), 'y': np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
           '-y': np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])}


def add_up_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument('--up', choices=tuple(UP_AXES), default='z',
                   help="the files' up axis: z (ROS body frames, datasets), -y (camera optical "
                        'frames: y down, z forward), y (e.g. the Stanford scans); banks hold '
                        'upright objects, z up')


def to_z_up(xyz: np.ndarray, up: str) -> np.ndarray:
    """xyz: (N, 3) in a frame whose `up` axis points up -> (N, 3) float32 with z up."""
    return (np.asarray(xyz, dtype=np.float64) @ UP_AXES[up].T).astype(np.float32)
