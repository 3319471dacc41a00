"""Resampling any cloud to a fixed point count, and normalising it to the unit sphere."""

from __future__ import annotations

from typing import Literal

import numpy as np

ResampleMethod = Literal['fps', 'random']

# FPS is O(N * n); beyond this many input points a seeded random subset is taken
# first, so a 1M-point cloud costs milliseconds, not seconds.
FPS_MAX_INPUT = 16384


def _compiled_fps():
    """kernels.fps_from when the compiled kernels load, else None (numpy loop below)."""
    from point_gn_ros.core import kernels
    return kernels.fps_from if kernels.load() is not None else None


def fps_indices(xyz: np.ndarray, m: int) -> np.ndarray:
    """Farthest point sampling, same definition as the oracle encoder's FPS.

    xyz: (N, 3) float32, m <= N -> (m,) int64. Starts at the point farthest from
    the centroid; ties go to the lowest index.
    """
    c = xyz.mean(axis=0, dtype=np.float32)
    d = xyz - c
    cur = int(np.argmax(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]))
    fast = _compiled_fps() if xyz.dtype == np.float32 and 1 <= m <= xyz.shape[0] else None
    if fast is not None:
        # Same loop compiled (point_gn_ros.core.kernels): identical indices, ~30x faster.
        return fast(xyz, m, cur)
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
    # float64 throughout: finite float32 input near +-3e38 must not overflow to inf.
    xyz = np.asarray(xyz, dtype=np.float64)
    centred = xyz - xyz.mean(axis=0)
    radius = float(np.sqrt((centred ** 2).sum(axis=1).max()))
    out = centred / radius if radius > 1e-12 and np.isfinite(radius) else centred * 0.0
    return out.astype(np.float32)


def rotate_z(xyz: np.ndarray, angle: float) -> np.ndarray:
    """Rotate points by `angle` radians about z: (N, 3) -> (N, 3) float32."""
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return (np.asarray(xyz, dtype=np.float64) @ rot.T).astype(np.float32)


def canonical_yaw(xyz: np.ndarray) -> np.ndarray:
    """Rotate a normalised cloud about z so its heading no longer depends on its yaw.

    xyz: (N, 3) float32, centred -> (N, 3) float32. The principal axis of the x-y
    spread goes to +x; the signs of x and y are fixed by the third moments, so a
    cloud and any yawed copy of it map to the same points (up to rounding), except
    for objects whose x-y spread is rotationally symmetric, where any heading is as
    good as another.
    """
    xy = xyz[:, :2].astype(np.float64)
    cov = np.cov(xy.T) if len(xy) > 1 else np.eye(2)
    _, vecs = np.linalg.eigh(cov)
    major = vecs[:, 1]                                 # eigenvalues ascend
    c, s = major[0], major[1]
    xy = xy @ np.array([[c, -s], [s, c]])              # major axis -> x
    signs = np.sign((xy ** 3).mean(axis=0))
    signs[signs == 0] = 1.0
    out = xyz.copy()
    out[:, :2] = xy * signs
    return out.astype(np.float32)


def prepare(xyz: np.ndarray, n: int = 1024, method: ResampleMethod = 'fps',
            seed: int = 0, yaw_align: bool = False) -> np.ndarray:
    """Resample, normalise (and optionally yaw-align): every cloud before the encoder."""
    out = normalize(resample(xyz, n, method, seed))
    return canonical_yaw(out) if yaw_align else out
