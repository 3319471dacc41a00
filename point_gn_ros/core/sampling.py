"""Resampling any cloud to a fixed point count, and normalising it to the unit sphere."""

from __future__ import annotations

from typing import Literal

import numpy as np

from point_gn_ros.core.config import UPSAMPLE_METHODS

ResampleMethod = Literal['fps', 'random']
# How a cloud with fewer points than the encoder takes is filled up (EncoderConfig.upsample).
UpsampleMethod = Literal['repeat', 'midpoint']

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


def canonical_order(xyz: np.ndarray) -> np.ndarray:
    """Indices sorting points by (x, y, z): (N, 3) -> (N,) int64, the same for any input order.

    Ties (and -0 against +0) keep their input order, as np.lexsort's, which is the reference;
    with the compiled kernels a radix sort (pgn_prepare.c) gives the same indices, ~5x faster.
    """
    lib = _compiled_prepare() if xyz.dtype == np.float32 and xyz.flags.c_contiguous else None
    if lib is not None:
        idx = np.empty(xyz.shape[0], dtype=np.int64)
        if lib.pgn_canonical_order(xyz.ctypes.data, xyz.shape[0], idx.ctypes.data) == 0:
            return idx
    return np.lexsort((xyz[:, 2], xyz[:, 1], xyz[:, 0]))


def midpoint_neighbours(xyz: np.ndarray, k: int) -> np.ndarray:
    """Each point's k nearest other points: (N, 3) float32, 1 <= k < N -> (N, k) int64.

    Row i: the k + 1 nearest points by (squared distance in float64, index), nearest first,
    without the first (point i itself, or an exact copy of it). Compiled with the kernels
    (pgn_prepare.c: the float kNN, then the float64 order); this numpy form, O(N^2) in
    blocks of rows, is its reference and fallback.
    """
    n = xyz.shape[0]
    lib = _compiled_prepare() if xyz.dtype == np.float32 and xyz.flags.c_contiguous else None
    if lib is not None and float(np.abs(xyz).max()) < 1e18:  # float squares stay finite
        nb = np.empty((n, k), dtype=np.int32)
        if lib.pgn_midpoint_neighbours(xyz.ctypes.data, n, k, nb.ctypes.data) == 0:
            return nb.astype(np.int64)
    x = xyz.astype(np.float64)
    out = np.empty((n, k), dtype=np.int64)
    for s in range(0, n, 256):
        d = x[s:s + 256, None, :] - x[None, :, :]
        d2 = (d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]) + d[..., 2] * d[..., 2]
        order = np.lexsort((np.broadcast_to(np.arange(n), d2.shape), d2), axis=-1)
        out[s:s + 256] = order[:, 1:k + 1]
    return out


def hashed_subset(xyz: np.ndarray, m: int, seed: int = 0) -> np.ndarray:
    """A seeded pseudo-random subset of m points chosen by their coordinates, not positions.

    xyz: (N, 3) float32, m <= N -> (m,) int64 indices, ordered by hash. Each point's rank is
    a hash of its coordinate bits and the seed (splitmix64), so a shuffled cloud gives the
    same points in the same order; O(N), no sort of the whole cloud.
    """
    bits = np.ascontiguousarray(xyz, dtype=np.float32).view(np.uint32).astype(np.uint64)
    with np.errstate(over='ignore'):   # uint64 arithmetic wraps on purpose
        h = (bits[:, 0] * np.uint64(0x9E3779B97F4A7C15)
             ^ bits[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F)
             ^ bits[:, 2] * np.uint64(0x165667B19E3779F9) ^ np.uint64(seed & (2**64 - 1)))
        h ^= h >> np.uint64(30)
        h *= np.uint64(0xBF58476D1CE4E5B9)
        h ^= h >> np.uint64(27)
        h *= np.uint64(0x94D049BB133111EB)
        h ^= h >> np.uint64(31)
    idx = np.argpartition(h, m - 1)[:m] if m < len(h) else np.arange(len(h))
    return idx[np.argsort(h[idx], kind='stable')]


def midpoint_fill(xyz: np.ndarray, n: int) -> np.ndarray:
    """Fewer than n points -> n: every point, then midpoints with nearby points.

    xyz: (N, 3) float32, 1 <= N <= n, finite -> (n, 3) float32. With the points in (x, y, z)
    order, round r = 1, 2, ... adds the midpoint of every point and its r-th nearest other
    point (cycling for clouds of under r + 1 points); the last, partial round takes the
    points of a coordinate-hash subset, so its new points are spread over the cloud. New
    points lie on the sampled surface between neighbours (repeating points would leave the
    encoder's k neighbours of a centre only k / repeats distinct points: a sparse scan then
    looks unlike a dense one). Deterministic and independent of the input order.
    """
    xyz = xyz[canonical_order(xyz)]
    count = len(xyz)
    if count >= n or count < 2:
        return xyz[np.arange(n) % count]
    rounds = -(-(n - count) // count)
    k = min(rounds, count - 1)
    nb = midpoint_neighbours(xyz, k)
    parts, missing = [xyz], n - count
    for r in range(rounds):
        rows = np.arange(count) if missing >= count else np.sort(hashed_subset(xyz, missing))
        # halves first: a + b would overflow float32 for finite points near +-3e38
        parts.append(xyz[rows] * np.float32(0.5) + xyz[nb[rows, r % k]] * np.float32(0.5))
        missing -= len(rows)
    return np.concatenate(parts).astype(np.float32, copy=False)


def resample(xyz: np.ndarray, n: int, method: ResampleMethod = 'fps', seed: int = 0,
             upsample: UpsampleMethod = 'repeat') -> np.ndarray:
    """Any number of points -> exactly n points, independent of the input point order.

    xyz: (N, 3) float32 with N >= 1 and finite values -> (n, 3) float32.
    More points: FPS (default; geometric start, so order-free up to exact ties) or a seeded
    subset chosen by coordinate hash. Fewer points: every point kept, then (upsample
    'repeat') points repeated in (x, y, z) order, never zero padding, or ('midpoint',
    `midpoint_fill`) midpoints of neighbouring points. Exactly n: the points in (x, y, z)
    order. So a shuffled cloud gives the same array, bit for bit (FPS: up to exact
    distance ties).
    """
    xyz = np.ascontiguousarray(xyz, dtype=np.float32)
    count = xyz.shape[0]
    if count < n and upsample == 'midpoint':
        return midpoint_fill(xyz, n)
    if upsample not in UPSAMPLE_METHODS:
        raise ValueError(f'upsample must be one of {UPSAMPLE_METHODS}, got {upsample!r}')
    if count <= n:   # exactly n too: the encoder's sums and tie-breaks then see one order
        return xyz[canonical_order(xyz)[np.arange(n) % count]]
    if method == 'random':
        return xyz[hashed_subset(xyz, n, seed)]
    if method != 'fps':
        raise ValueError(f"resample method must be 'fps' or 'random', got {method!r}")
    if count > FPS_MAX_INPUT:
        xyz = xyz[hashed_subset(xyz, FPS_MAX_INPUT, seed)]
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
    cov = _cov_rows(xy.T) if len(xy) > 1 else np.eye(2)
    _, vecs = np.linalg.eigh(cov)
    major = vecs[:, 1]                                 # eigenvalues ascend
    c, s = major[0], major[1]
    xy = xy @ np.array([[c, -s], [s, c]])              # major axis -> x
    # |x|^3 with x's sign, not x ** 3: pow of a negative base takes libm's slow path (0.28 ms
    # a cloud). Both give the same signs on all 110,799 default-bank build and test clouds,
    # the frames the shipped banks were built in.
    signs = np.sign(np.copysign(np.abs(xy) ** 3, xy).mean(axis=0))
    signs[signs == 0] = 1.0
    out = xyz.copy()
    out[:, :2] = xy * signs
    return out.astype(np.float32)


def _cov_rows(m: np.ndarray) -> np.ndarray:
    """np.cov(m) for (V, N) float64 rows, N > 1: its own steps without its argument handling."""
    x = np.array(m, ndmin=2, dtype=np.float64)
    x -= x.mean(axis=1)[:, None]
    c = np.dot(x, x.T.conj())
    c *= np.true_divide(1, x.shape[1] - 1)
    return c


def _compiled_prepare():
    """The kernel library when it loads (pgn_prepare.c), else None (numpy forms above)."""
    from point_gn_ros.core import kernels
    return kernels.load()


def prepare(xyz: np.ndarray, n: int = 1024, method: ResampleMethod = 'fps',
            seed: int = 0, yaw_align: bool = False, upsample: UpsampleMethod = 'repeat'
            ) -> np.ndarray:
    """Resample, normalise (and optionally yaw-align): every cloud before the encoder.

    With the compiled kernels, normalize and canonical_yaw run as one C call each
    (pgn_prepare.c: normalize's bits, canonical_yaw's within a float32 rounding), ~0.14 ms
    of numpy calls less a cloud on the node's worker thread.
    """
    out = resample(xyz, n, method, seed, upsample)
    lib = _compiled_prepare()
    if lib is None:
        out = normalize(out)
        return canonical_yaw(out) if yaw_align else out
    out = np.ascontiguousarray(out, dtype=np.float32)
    m = out.shape[0]
    norm = np.empty_like(out)
    lib.pgn_normalize(out.ctypes.data, m, norm.ctypes.data)
    if not yaw_align:
        return norm
    yawed = np.empty_like(norm)
    scratch = np.empty((2, m), dtype=np.float64)
    lib.pgn_canonical_yaw(norm.ctypes.data, m, yawed.ctypes.data, scratch[0].ctypes.data,
                          scratch[1].ctypes.data)
    return yawed
