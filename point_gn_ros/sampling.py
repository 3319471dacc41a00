"""Resampling any cloud to a fixed point count, and normalising it to the unit sphere."""

from __future__ import annotations

from typing import Literal

import numpy as np

ResampleMethod = Literal['fps', 'random']

# FPS is O(N * n); beyond this many input points a seeded random subset is taken
# first, so a 1M-point cloud costs milliseconds, not seconds.
FPS_MAX_INPUT = 16384


def fps_indices(xyz: np.ndarray, m: int) -> np.ndarray:
    """Farthest point sampling, same definition as the oracle encoder's FPS.

    xyz: (N, 3) float32, m <= N -> (m,) int64. Starts at the point farthest from
    the centroid; ties go to the lowest index.
    """
    c = xyz.mean(axis=0, dtype=np.float32)
    d = xyz - c
    cur = int(np.argmax(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]))
    min_d = np.full(xyz.shape[0], np.inf, dtype=np.float32)
    idx = np.empty(m, dtype=np.int64)
    for i in range(m):
        idx[i] = cur
        d = xyz - xyz[cur]
        np.minimum(min_d, d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2], out=min_d)
        cur = int(np.argmax(min_d))
    return idx


def resample(xyz: np.ndarray, n: int, method: ResampleMethod = 'fps', seed: int = 0) -> np.ndarray:
    """Any number of points -> exactly n points.

    xyz: (N, 3) float32 with N >= 1 and finite values -> (n, 3) float32.
    More points: FPS (default) or a seeded random subset. Fewer points: every
    point kept, then points repeated in order (never zero padding).
    """
    xyz = np.ascontiguousarray(xyz, dtype=np.float32)
    count = xyz.shape[0]
    if count == n:
        return xyz
    if count < n:
        return xyz[np.arange(n) % count]
    rng = np.random.default_rng(seed)
    if method == 'random':
        return xyz[np.sort(rng.choice(count, n, replace=False))]
    if method != 'fps':
        raise ValueError(f"resample method must be 'fps' or 'random', got {method!r}")
    if count > FPS_MAX_INPUT:
        xyz = xyz[np.sort(rng.choice(count, FPS_MAX_INPUT, replace=False))]
    return xyz[fps_indices(xyz, n)]


def normalize(xyz: np.ndarray) -> np.ndarray:
    """Centre on the mean and scale into the unit sphere: (N, 3) -> (N, 3) float32.

    A cloud in metres in a sensor frame then looks like a dataset cloud. A cloud
    of identical points maps to the origin (no division by zero).
    """
    xyz = np.asarray(xyz, dtype=np.float32)
    centred = xyz - xyz.mean(axis=0, dtype=np.float64).astype(np.float32)
    radius = float(np.sqrt((centred.astype(np.float64) ** 2).sum(axis=1).max()))
    return (centred / radius).astype(np.float32) if radius > 1e-12 else centred * 0.0


def prepare(xyz: np.ndarray, n: int = 1024, method: ResampleMethod = 'fps',
            seed: int = 0) -> np.ndarray:
    """Resample then normalise: what every cloud goes through before the encoder."""
    return normalize(resample(xyz, n, method, seed))
