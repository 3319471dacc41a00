"""Metric size of an object cloud, measured before the encoder scales it to the unit sphere.

The encoder sees every object at the same size; a robot's clouds are in metres, so how big an
object is comes for free and tells a 15 cm carton from a wardrobe. `size_descriptor` measures,
in the cloud's own z-up frame:

  0 height        z extent (98th - 2nd percentile)
  1 length        extent along the major horizontal axis (98th - 2nd percentile)
  2 width         extent along the minor horizontal axis
  3-5 spreads     standard deviations along the three principal axes, largest first

each as log(max(value, SIZE_FLOOR)) (natural log of metres). Percentiles and spreads, not
min / max: a stray point or a denser patch barely moves them. A cloud of one point, or one
with no finite extent, measures SIZE_FLOOR everywhere. Pure numpy; no ROS.
"""

from __future__ import annotations

import numpy as np

SIZE_DIM = 6
SIZE_NAMES = ('height', 'length', 'width', 'spread1', 'spread2', 'spread3')
# Extents below this (metres) are measured as this: below a sensor's resolution anyway, and
# log() stays finite.
SIZE_FLOOR = 0.005
_LO, _HI = 2.0, 98.0


def size_descriptor(xyz: np.ndarray) -> np.ndarray:
    """xyz: (N, 3) float finite points in metres, z up, N >= 1 -> (SIZE_DIM,) float64 log sizes."""
    p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if len(p) < 2:
        return np.full(SIZE_DIM, np.log(SIZE_FLOOR))
    z_lo, z_hi = np.percentile(p[:, 2], (_LO, _HI))
    xy = p[:, :2] - np.median(p[:, :2], axis=0)
    # the horizontal axes from the points inside the per-axis percentile box: a stray point
    # must not turn them
    lo_xy, hi_xy = np.percentile(xy, (_LO, _HI), axis=0)
    inner = xy[((xy >= lo_xy) & (xy <= hi_xy)).all(axis=1)]
    inner = inner if len(inner) >= 2 else xy
    inner = inner - inner.mean(axis=0)
    _, vecs = np.linalg.eigh(inner.T @ inner)
    along = xy @ vecs[:, ::-1]                        # major axis first
    lo, hi = np.percentile(along, (_LO, _HI), axis=0)
    c = p - p.mean(axis=0)
    spreads = np.sqrt(np.clip(np.linalg.eigvalsh(c.T @ c / len(p))[::-1], 0.0, None))
    ext = np.sort(hi - lo)[::-1]
    out = np.array([z_hi - z_lo, ext[0], ext[1], *spreads])
    out = np.where(np.isfinite(out), out, SIZE_FLOOR)
    return np.log(np.maximum(out, SIZE_FLOOR))


def size_descriptors(clouds: list[np.ndarray]) -> np.ndarray:
    """clouds: list of (N_i, 3) in metres, z up -> (B, SIZE_DIM) float64 log sizes."""
    if not clouds:
        return np.zeros((0, SIZE_DIM))
    return np.stack([size_descriptor(c) for c in clouds])
