"""Small helpers shared by the single-file readers."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from point_gn_ros.errors import DatasetError

PathLike = str | Path


def read_bytes(path: PathLike) -> bytes:
    """Whole file as bytes; OS errors become DatasetError naming the file."""
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise DatasetError(f'{path}: cannot read file ({exc.strerror or exc})') from exc


def stack_xyz(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Three (N,) numeric arrays -> (N, 3) float32 (float64 values are rounded)."""
    xyz = np.empty((x.shape[0], 3), dtype=np.float32)
    with np.errstate(over='ignore', invalid='ignore'):
        for j, col in enumerate((x, y, z)):
            xyz[:, j] = col
    return xyz


def with_xyz(path: PathLike, fields: dict[str, np.ndarray],
             drop_nan: bool) -> dict[str, np.ndarray]:
    """Add 'xyz' (N, 3) float32 built from the x/y/z fields; drop non-finite points.

    fields: name -> (N,) or (N, k) arrays. Raises DatasetError if x, y or z is
    missing or is not a single numeric column.
    """
    missing = [c for c in 'xyz' if c not in fields]
    if missing:
        raise DatasetError(f'{path}: missing {"/".join(missing)} field(s); '
                           f'fields present: {", ".join(fields) or "none"}')
    for c in 'xyz':
        if fields[c].ndim != 1 or fields[c].dtype.kind not in 'fiu':
            raise DatasetError(f'{path}: field {c!r} must be one numeric value per point')
    xyz = stack_xyz(fields['x'], fields['y'], fields['z'])
    out = dict(fields)
    out['xyz'] = xyz
    if drop_nan:
        keep = np.isfinite(xyz).all(axis=1)
        if not keep.all():
            out = {name: arr[keep] for name, arr in out.items()}
    return out
