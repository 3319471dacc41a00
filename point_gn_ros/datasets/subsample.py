"""Fixing the point count of dataset clouds: 'first' N points or farthest point sampling."""

from __future__ import annotations

from typing import Literal

import numpy as np

from point_gn_ros.core.sampling import FPS_MAX_INPUT, fps_indices, resample

Subsample = Literal['first', 'fps']
SUBSAMPLE_METHODS = ('first', 'fps')
_FPS_CHUNK = 64  # clouds per vectorised FPS pass: 64 x 2048 float32 stays in cache


def subsample(xyz: np.ndarray, n: int, method: Subsample = 'first') -> np.ndarray:
    """(N, 3) float32 -> (n, 3) float32.

    'first' keeps the first n points (dataset files store points in random order);
    'fps' is sampling.resample(method='fps'), i.e. xyz[fps_indices(xyz, n)] for
    N <= FPS_MAX_INPUT. Fewer than n points: all points, repeated in order.
    """
    if xyz.shape[0] == n:
        return xyz
    if method == 'fps':
        return resample(xyz, n, 'fps')
    if xyz.shape[0] > n:
        return xyz[:n]
    return xyz[np.arange(n) % xyz.shape[0]]


def fps_indices_batch(xyz: np.ndarray, m: int) -> np.ndarray:
    """FPS on many clouds at once: (B, N, 3) float32, m <= N -> (B, m) int64.

    Same float32 operations in the same order as sampling.fps_indices, so each
    row equals fps_indices(xyz[b], m) exactly; only the Python loop is shared.
    """
    b, n, _ = xyz.shape
    x, y, z = (np.ascontiguousarray(xyz[:, :, j]) for j in range(3))
    # Per-cloud mean: the same call as fps_indices, so the start point matches bit for bit.
    c = np.stack([np.ascontiguousarray(cloud).mean(axis=0, dtype=np.float32) for cloud in xyz])
    d2 = _sq_dist(x, y, z, c[:, 0:1], c[:, 1:2], c[:, 2:3], np.empty((b, n), np.float32))
    cur = d2.argmax(axis=1)
    rows = np.arange(b)
    min_d = np.full((b, n), np.inf, dtype=np.float32)
    idx = np.empty((b, m), dtype=np.int64)
    tmp = np.empty((b, n), np.float32)
    for i in range(m):
        idx[:, i] = cur
        px, py, pz = x[rows, cur][:, None], y[rows, cur][:, None], z[rows, cur][:, None]
        np.minimum(min_d, _sq_dist(x, y, z, px, py, pz, d2, tmp), out=min_d)
        cur = min_d.argmax(axis=1)
    return idx


def _sq_dist(x: np.ndarray, y: np.ndarray, z: np.ndarray, px: np.ndarray, py: np.ndarray,
             pz: np.ndarray, out: np.ndarray, tmp: np.ndarray | None = None) -> np.ndarray:
    """(B, N) squared distances to one point per row, as dx*dx + dy*dy + dz*dz in float32."""
    tmp = np.empty_like(out) if tmp is None else tmp
    np.subtract(x, px, out=out)
    np.multiply(out, out, out=out)
    np.subtract(y, py, out=tmp)
    np.multiply(tmp, tmp, out=tmp)
    np.add(out, tmp, out=out)
    np.subtract(z, pz, out=tmp)
    np.multiply(tmp, tmp, out=tmp)
    np.add(out, tmp, out=out)
    return out


def subsample_batch(xyz: np.ndarray, n: int, method: Subsample = 'first') -> np.ndarray:
    """(B, N, 3) float32 -> (B, n, 3) float32, each cloud as `subsample` would do it."""
    b, count, _ = xyz.shape
    if count == n:
        return xyz
    if count < n:
        return xyz[:, np.arange(n) % count]
    if method == 'first':
        return np.ascontiguousarray(xyz[:, :n])
    if count > FPS_MAX_INPUT:  # resample() takes a random subset first; keep its result
        return np.stack([subsample(cloud, n, 'fps') for cloud in xyz])
    out = np.empty((b, n, 3), dtype=np.float32)
    for s in range(0, b, _FPS_CHUNK):
        chunk = xyz[s:s + _FPS_CHUNK]
        idx = fps_indices_batch(chunk, n)
        out[s:s + len(chunk)] = np.take_along_axis(chunk, idx[:, :, None], axis=1)
    return out


__all__ = ['SUBSAMPLE_METHODS', 'Subsample', 'fps_indices', 'fps_indices_batch', 'subsample',
           'subsample_batch']
