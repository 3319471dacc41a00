"""Local surface-ness of a cloud: a view of surfaces, or a volume of points.

Depth cameras and lidars return points on surfaces: around most points, the K nearest
neighbours lie near a plane (a lidar ring: near a line), so their covariance has one small
eigenvalue. A cloud of random points (a Gaussian blob, noise from a bad decode) fills a
volume: its neighbourhoods are round. `volumetric_shares` gives, per cloud, the share of
points whose neighbourhood is volumetric (smallest / largest covariance eigenvalue above
VOLUME_RATIO), measured on at most SURFACE_POINTS points taken evenly from the cloud, so the
neighbourhood's scale follows the cloud's own point spacing. Figures: docs/SIZE.md.
Pure numpy / scipy; no ROS.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

SURFACE_K = 16          # neighbours per point (the point itself included)
SURFACE_POINTS = 256    # points measured per cloud at most (evenly strided)
VOLUME_RATIO = 0.15     # smallest / largest eigenvalue above this: a volumetric neighbourhood
# The node's default rule: a cloud with more volumetric points than this is unknown
# (docs/SIZE.md: every random blob measured is above, every real or simulated sensor view
# below; 8 % of complete synthetic ModelNet40 objects at 1,024 points are above).
DEFAULT_VOLUME_THRESHOLD = 0.8
# The clouds of one batch share one k-d tree, each scaled into the unit cube (the ratio is
# scale-free) and set this far apart, out of each other's neighbourhoods.
_GAP = 3.0


def volumetric_shares(clouds: Sequence[np.ndarray]) -> np.ndarray:
    """clouds: B clouds (N_i, 3) finite -> (B,) float64 share in [0, 1] of volumetric points.

    A cloud of SURFACE_K points or fewer measures 0 (too few to tell).
    """
    subs, owners = [], []
    for i, c in enumerate(clouds):
        p = np.asarray(c, dtype=np.float64).reshape(-1, 3)
        if len(p) <= SURFACE_K:
            continue
        if len(p) > SURFACE_POINTS:
            p = p[(np.arange(SURFACE_POINTS) * (len(p) / SURFACE_POINTS)).astype(np.int64)]
        p = p - p.mean(axis=0)
        p = p / max(float(np.abs(p).max()), 1e-300)
        subs.append(p + [_GAP * len(subs), 0.0, 0.0])
        owners.append(i)
    out = np.zeros(len(clouds))
    if not subs:
        return out
    pts = np.concatenate(subs)
    _, idx = cKDTree(pts).query(pts, k=SURFACE_K)
    nb = pts[idx]
    nb = nb - nb.mean(axis=1, keepdims=True)
    ev = np.linalg.eigvalsh(np.matmul(nb.transpose(0, 2, 1), nb))     # ascending
    vol = ev[:, 0] > VOLUME_RATIO * ev[:, 2]
    counts = [len(s) for s in subs]
    out[owners] = [v.mean() for v in np.split(vol, np.cumsum(counts)[:-1])]
    return out


def volume_rule(threshold: float) -> float | None:
    """A node / CLI volume threshold -> the Recognizer's (None: off, at 1.0 or above)."""
    return None if threshold >= 1.0 else float(threshold)
