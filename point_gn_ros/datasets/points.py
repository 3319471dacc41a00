"""Any supported single-cloud file -> (N, 3) float32 xyz, chosen by extension."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from point_gn_ros.datasets._common import PathLike, read_bytes
from point_gn_ros.datasets.pcd import read_pcd
from point_gn_ros.datasets.ply import read_ply
from point_gn_ros.errors import DatasetError

POINT_EXTENSIONS = ('.pcd', '.ply', '.npy', '.txt', '.xyz', '.csv')


def read_npy(path: PathLike) -> np.ndarray:
    """.npy with a numeric (N, >=3) array -> (N, 3) float32 (first three columns)."""
    try:
        arr = np.load(path, allow_pickle=False)
    except OSError as exc:
        raise DatasetError(f'{path}: cannot read file ({exc.strerror or exc})') from exc
    except ValueError as exc:  # pickled object arrays, bad magic, truncated data
        raise DatasetError(f'{path}: not a readable .npy array ({exc})') from exc
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in 'fiu':
        raise DatasetError(f'{path}: .npy must hold a numeric array')
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise DatasetError(f'{path}: .npy array has shape {arr.shape}, expected (N, >=3)')
    return np.ascontiguousarray(arr[:, :3], dtype=np.float32)


def read_text(path: PathLike) -> np.ndarray:
    """.txt/.xyz/.csv: one point per line, whitespace or comma separated -> (N, 3) float32.

    The first three columns are x y z; further columns are ignored. Blank lines
    and lines starting with '#' or '//' are skipped.
    """
    try:
        text = read_bytes(path).decode('utf-8')
    except UnicodeDecodeError:
        raise DatasetError(f'{path}: text point file is not UTF-8 text') from None
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or s.startswith(('#', '//')):
            continue
        cols = s.replace(',', ' ').split()
        if len(cols) < 3:
            raise DatasetError(f'{path}: line {lineno} has {len(cols)} values, expected >= 3')
        rows.append(cols[:3])
    try:
        xyz = np.array(rows, dtype=np.float64).reshape(-1, 3)
    except ValueError:
        bad = next(i for i, r in enumerate(rows) if not _is_numeric(r))
        raise DatasetError(f'{path}: non-numeric value in data row {bad + 1}: '
                           f'{" ".join(rows[bad])!r}') from None
    return xyz.astype(np.float32)


def _is_numeric(row: list[str]) -> bool:
    try:
        [float(v) for v in row]
    except ValueError:
        return False
    return True


def read_points(path: PathLike, drop_nan: bool = True) -> np.ndarray:
    """Point file (.pcd .ply .npy .txt .xyz .csv) -> (N, 3) float32.

    With drop_nan (default) rows with a non-finite coordinate are removed, so the
    result is finite; N may be 0. Raises DatasetError naming the file.
    """
    ext = Path(path).suffix.lower()
    if ext == '.pcd':
        return read_pcd(path, drop_nan)['xyz']
    if ext == '.ply':
        return read_ply(path, drop_nan)['xyz']
    if ext == '.npy':
        xyz = read_npy(path)
    elif ext in ('.txt', '.xyz', '.csv'):
        xyz = read_text(path)
    else:
        raise DatasetError(f'{path}: unsupported point file extension {ext!r} '
                           f'(supported: {", ".join(POINT_EXTENSIONS)})')
    return xyz[np.isfinite(xyz).all(axis=1)] if drop_nan else xyz
