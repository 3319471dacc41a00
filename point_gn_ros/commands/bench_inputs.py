"""Synthetic inputs for the benchmarks (and tests): surface-sampled clouds, clustered banks.

Deterministic for a seed, so a figure or a test sees the same data on every run.
"""

from __future__ import annotations

__all__ = ['synthetic_bank', 'synthetic_clouds']


def synthetic_clouds(count: int, n: int, seed: int = 0):
    """Prepared clouds sampled from surfaces (spheres, boxes, cylinders): (count, n, 3)."""
    import numpy as np

    from point_gn_ros.core.sampling import normalize

    rng = np.random.default_rng(seed)
    out = np.empty((count, n, 3), np.float32)
    for i in range(count):
        kind = i % 3
        u = rng.uniform(-1, 1, (n, 3))
        if kind == 0:  # ellipsoid surface
            pts = u / np.linalg.norm(u, axis=1, keepdims=True) * rng.uniform(0.3, 1, 3)
        elif kind == 1:  # box surface
            axis = rng.integers(0, 3, n)
            pts = u * rng.uniform(0.3, 1, 3)
            pts[np.arange(n), axis] = np.sign(u[np.arange(n), axis]) * rng.uniform(0.3, 1)
        else:  # cylinder side
            a = rng.uniform(0, 2 * np.pi, n)
            pts = np.stack([np.cos(a), np.sin(a), u[:, 2] * rng.uniform(0.5, 2)], axis=1)
        pts = pts + rng.normal(0, 0.005, pts.shape)
        out[i] = normalize(pts.astype(np.float32))
    return out


def synthetic_bank(n: int, dims: int, seed: int = 0, classes: int = 40):
    """A clustered bank of unit rows: (n, dims) float32 features, (n,) int64 labels.

    Each class has a few modes; entries scatter around them, so nearest entries are
    structured like a real bank's rather than uniform on the sphere. Coordinate j has
    scale (1 + j)^-0.6, a decaying spectrum like the shipped bank's PCA features (the
    leading quarter of the coordinates holds ~90 % of the energy; 93 % in the bank).
    """
    import numpy as np

    rng = np.random.default_rng(seed)
    scale = (1.0 + np.arange(dims, dtype=np.float32)) ** -0.6
    modes = rng.standard_normal((classes * 8, dims)).astype(np.float32)
    which = rng.integers(0, len(modes), n)
    feats = (modes[which] + rng.standard_normal((n, dims)).astype(np.float32) * 0.8) * scale
    feats /= np.linalg.norm(feats, axis=1, keepdims=True)
    return feats, which % classes
