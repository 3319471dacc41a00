"""Cloud structure: a view of one object's surfaces, or a volume of points, or a scene.

Depth cameras and lidars return points on surfaces: around most points, the K nearest
neighbours lie near a plane (a lidar ring: near a line), so their covariance has one small
eigenvalue. A cloud of random points (a Gaussian blob, noise from a bad decode) fills a
volume: its neighbourhoods are round. `volumetric_shares` gives, per cloud, the share of
points whose neighbourhood is volumetric (smallest / largest covariance eigenvalue above
VOLUME_RATIO), measured on at most SURFACE_POINTS points taken evenly from the cloud, so the
neighbourhood's scale follows the cloud's own point spacing.

A segmented object stands in one place: seen from above, whatever stands on its lowest part
overlaps. A scene (several objects, a street, a table with things on it) is parts apart.
`separated_shares` gives, per cloud, the share of the area seen from above outside its
largest part. A floor or a table top joins everything standing on it, so the support is left
out first: a plane fitted (robustly) to the lowest SUPPORT_BAND of the cloud's height, or,
where more points lie on it (within SCENE_SLAB of the height), one fitted to the lowest
SUPPORT_BAND measured from that plane (a ground tilted a few degrees reaches past the first
band), and the points less than max(SCENE_SLAB of the height, 3 residual sd)
above it. The rest is binned from above into square cells, the larger of 1 / SCENE_CELLS of
its footprint's diagonal and SCENE_SPACING times its mean point spacing (a sparse lidar
cluster is not cut into its rings); parts are the 8-connected groups of occupied cells, and
area is counted in cells (a near object's many points do not outweigh far ones). One object
on a table or floor that was not cut from it is a scene too: a support holding more than
SUPPORT_SHARE of the points whose box's diagonal is more than SUPPORT_WIDER times that of what
stands on it measures 1 (a diagonal, not an area: a laptop's screen seen from above is a thin
strip over its base). Scale-free; z up. Figures: docs/SIZE.md.
Pure numpy / scipy; no ROS.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

SURFACE_K = 16          # neighbours per point (the point itself included)
SURFACE_POINTS = 256    # points measured per cloud at most (evenly strided)
VOLUME_RATIO = 0.15     # smallest / largest eigenvalue above this: a volumetric neighbourhood
# The node's default rule: a cloud with more volumetric points than this is unknown
# (docs/SIZE.md: every random blob measured is above, every real or simulated sensor view
# below; 8 % of complete synthetic ModelNet40 objects at 1,024 points are above).
DEFAULT_VOLUME_THRESHOLD = 0.8
SUPPORT_BAND = 0.2      # the support plane is fitted to the lowest share of the height,
                        # and again to that share measured from the first plane
SUPPORT_ROUNDS = 2      # least-squares fits of each plane, the second on the first's inliers
SUPPORT_SLOPE = 1.0     # a support is within 45 degrees of level (a camera pitched down
                        # at a table, its cloud turned by up_axis only, sees it tilted)
SCENE_SLAB = 0.05       # points less than this share of the height or 3 residual sd above
                        # the plane are the support's (left out)
SUPPORT_SHARE = 0.4     # a support holding more than this share of the points (within
SUPPORT_WIDER = 3.0     # SCENE_SLAB of it) whose box's diagonal is this many times the
                        # diagonal of what stands on it: a bare support, a scene
SCENE_CELLS = 32        # cells along the footprint's diagonal at most
SCENE_SPACING = 4.0     # a cell is at least this many point spacings wide
SCENE_POINTS = 2048     # points the support is fitted on at most (evenly strided)
# The node's default rule: a cloud with more of its area apart from its largest part than
# this is unknown (docs/SIZE.md, experiments/structure_rule_study.py: 72-100 % of the scenes
# measured, by kind, are above it; 5 of 1,200 tabletop views, 1 % of simulated lidar clusters,
# 0.3 % of ModelNet40 scans and no complete object).
DEFAULT_SCENE_THRESHOLD = 0.3
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


def separated_shares(clouds: Sequence[np.ndarray]) -> np.ndarray:
    """clouds: B clouds (N_i, 3) finite, z up -> (B,) float64 share in [0, 1] of area apart.

    The share of the area seen from above (module docstring) outside the cloud's largest
    part; 1.0 for a bare support (module docstring); a cloud with SURFACE_K points or fewer
    above its support measures 0.
    """
    return np.array([_separated_share(np.asarray(c, dtype=np.float64).reshape(-1, 3))
                     for c in clouds], dtype=np.float64)


def _separated_share(cloud: np.ndarray) -> float:
    p = cloud
    if len(p) > SCENE_POINTS:          # the support is fitted on an even subsample
        p = p[(np.arange(SCENE_POINTS) * (len(p) / SCENE_POINTS)).astype(np.int64)]
    if len(p) <= SURFACE_K:
        return 0.0
    z_lo, z_hi = _percentiles(np.sort(p[:, 2]), (2.0, 98.0))
    height = z_hi - z_lo
    plane, sd = _support_plane(p[p[:, 2] <= z_lo + SUPPORT_BAND * height])
    over = _height_over(p, plane)
    # the band again, measured from that plane (a tilted ground reaches past the first band);
    # the support is whichever plane more points lie on
    a_lo, a_hi = _percentiles(np.sort(over), (2.0, 98.0))
    again, sd_again = _support_plane(p[over <= a_lo + SUPPORT_BAND * (a_hi - a_lo)])
    over_again = _height_over(p, again)
    on = SCENE_SLAB * height
    if (np.abs(over_again) <= on).sum() > (np.abs(over) <= on).sum():
        plane, sd, over = again, sd_again, over_again
    clear = max(on, 3.0 * sd)
    top = p[over > clear, :2]
    if len(top) <= SURFACE_K:
        return 0.0
    lo, hi = _percentiles(np.sort(top, axis=0), (1.0, 99.0))
    span = np.maximum(hi - lo, 1e-12 * max(float(np.abs(top).max()), 1e-300))
    support = p[np.abs(over) <= on, :2]
    if len(support) > SUPPORT_SHARE * len(p):
        s_lo, s_hi = _percentiles(np.sort(support, axis=0), (1.0, 99.0))
        if np.hypot(*(s_hi - s_lo)) > SUPPORT_WIDER * np.hypot(*span):
            return 1.0                 # an object on a table or floor not cut from it
    if len(cloud) > len(p):            # every point is binned: the cells follow its density
        top = cloud[_height_over(cloud, plane) > clear, :2]
    spacing = float(np.sqrt(span.prod() / len(top)))
    cell = max(float(np.hypot(*span)) / SCENE_CELLS, SCENE_SPACING * spacing)
    # the outer 1 % per side lands in the border cells: the grid stays SCENE_CELLS wide
    ij = np.clip(np.floor((top - lo) / cell), -1, np.ceil(span / cell)).astype(np.int64) + 1
    occupied = np.zeros(ij.max(0) + 1, dtype=bool)
    occupied[ij[:, 0], ij[:, 1]] = True
    parts, n = ndimage.label(occupied, structure=np.ones((3, 3), dtype=bool))
    if n <= 1:
        return 0.0
    area = np.bincount(parts.ravel())[1:]            # occupied cells per part
    return float(1.0 - area.max() / area.sum())


def _height_over(p: np.ndarray, plane: np.ndarray) -> np.ndarray:
    """(M, 3) points, plane (a, b, c) -> (M,) z - (a x + b y + c)."""
    return p[:, 2] - p[:, :2] @ plane[:2] - plane[2]


def _percentiles(ordered: np.ndarray, qs: tuple[float, float]) -> np.ndarray:
    """Sorted (M,) or (M, K) values along axis 0 -> their percentiles qs, (2,) or (2, K).

    numpy's default (linear) percentile, without its per-call overhead.
    """
    pos = np.asarray(qs) / 100.0 * (len(ordered) - 1)
    below = np.floor(pos).astype(np.int64)
    above = np.minimum(below + 1, len(ordered) - 1)
    frac = (pos - below).reshape((-1,) + (1,) * (ordered.ndim - 1))
    return ordered[below] + (ordered[above] - ordered[below]) * frac


def _support_plane(low: np.ndarray) -> tuple[np.ndarray, float]:
    """(M, 3) the lowest points -> plane (a, b, c) of z = a x + b y + c, residual sd.

    SUPPORT_ROUNDS least-squares fits, each after the first on the points within 2 residual
    sd of the one before (objects standing on the support stay out of it). A support is near
    level: a fit steeper than SUPPORT_SLOPE, or one of fewer than 3 points, is the level
    plane at their median.
    """
    keep = np.ones(len(low), dtype=bool)
    plane = None
    for _ in range(SUPPORT_ROUNDS):
        if keep.sum() < 3:
            break
        plane = _plane_fit(low[keep])
        resid = _height_over(low, plane)
        keep = np.abs(resid) <= 2.0 * float(np.sqrt(np.mean(resid[keep] ** 2)))
    if plane is None or np.hypot(plane[0], plane[1]) > SUPPORT_SLOPE:
        plane = np.array([0.0, 0.0, float(np.median(low[:, 2])) if len(low) else 0.0])
        keep = np.ones(len(low), dtype=bool)
    resid = _height_over(low, plane)
    return plane, float(np.sqrt(np.mean(resid[keep] ** 2))) if keep.any() else 0.0


def _plane_fit(q: np.ndarray) -> np.ndarray:
    """(M, 3), M >= 3 -> the least-squares plane (a, b, c) of z = a x + b y + c.

    The minimum-norm slope where x-y is degenerate (points on a line: no tilt across it).
    """
    mean = q.sum(axis=0) / len(q)
    c = q - mean
    (sxx, sxy), (_, syy) = c[:, :2].T @ c[:, :2]
    rx, ry = c[:, :2].T @ c[:, 2]
    det, trace = sxx * syy - sxy * sxy, sxx + syy
    if det > 1e-12 * trace * trace:
        a, b = (syy * rx - sxy * ry) / det, (sxx * ry - sxy * rx) / det
    elif trace > 0.0:                       # rank one: along its one direction only
        u = np.array([sxx, sxy]) if sxx >= syy else np.array([sxy, syy])
        u = u / np.linalg.norm(u)
        a, b = u * (u[0] * rx + u[1] * ry) / trace
    else:
        a = b = 0.0
    return np.array([a, b, mean[2] - a * mean[0] - b * mean[1]])


def structure_unknown(clouds: Sequence[np.ndarray], volume_threshold: float | None,
                      scene_threshold: float | None) -> np.ndarray:
    """(B,) bool: the clouds the volume and scene rules (None: off) call unknown."""
    out = np.zeros(len(clouds), dtype=bool)
    if volume_threshold is not None:
        out |= volumetric_shares(clouds) > volume_threshold
    if scene_threshold is not None:
        out |= separated_shares(clouds) > scene_threshold
    return out


def scene_rule(threshold: float) -> float | None:
    """A node / CLI scene threshold -> the Recognizer's (None: off, at 1.0 or above)."""
    return None if threshold >= 1.0 else float(threshold)
