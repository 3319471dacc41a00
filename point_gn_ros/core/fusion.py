"""Several views of one object, given in one fixed frame, fused into more enrollment examples.

A robot that looks at an object from a few sides sees more of it than any single view. When
its clouds come in a fixed frame (`odom`, `map`: the object stays put while the camera moves),
the views overlap where the object is, and their union is close to the complete object.
`fused_examples` draws from that union what the default bank holds of each of its own train
objects: the complete cloud and k simulated single-view scans (core/views.py, evenly spread
azimuths). An instance taught from 5 real scans then has 5 + 1 + 8 examples, and the LDA's
estimate of its class mean is less noisy (benchmarks/RESULTS.md, enrollment).

Views in a moving frame (a camera's optical frame, the robot's base) do not overlap: their
union would be a new object made of misplaced parts. `views_overlap` refuses such sets by
their centroids, so the caller enrolls the views as they are instead.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from point_gn_ros.core.views import ViewConfig, simulate_views

# Synthetic scans drawn from the fused cloud (the default bank's own objects have 8 each).
FUSED_SCANS = 8
# The union is thinned to this many points (seeded) before scans are drawn from it: hidden
# point removal is a convex hull over every point, and 5 real sensor clouds can hold 100k.
FUSE_MAX_POINTS = 8192
# Two views of one object in one frame have centroids inside the object: at most this many
# times the larger view's radius apart (views of a moving frame are metres apart).
OVERLAP_FACTOR = 1.5


def views_overlap(views: Sequence[np.ndarray], factor: float = OVERLAP_FACTOR) -> bool:
    """True if every pair of views lies within one object: (N_i, 3) float32 clouds.

    The test: centroid distance <= factor x the larger of the two views' radii (each about
    its own centroid). Fewer than two views: False (nothing to fuse).
    """
    if len(views) < 2:
        return False
    pts = [np.asarray(v, dtype=np.float64) for v in views]
    cents = np.stack([p.mean(axis=0) for p in pts])                          # (V, 3)
    radii = np.array([np.linalg.norm(p - c, axis=1).max() for p, c in zip(pts, cents,
                                                                           strict=True)])
    # All pairs at once: a capture may hold capture_max (200) views, ~20k pairs.
    apart = np.linalg.norm(cents[:, None] - cents[None], axis=2)              # (V, V)
    return bool((apart <= factor * np.maximum(np.maximum.outer(radii, radii), 1e-9)).all())


def fuse_views(views: Sequence[np.ndarray], max_points: int = FUSE_MAX_POINTS,
               seed: int = 0) -> np.ndarray:
    """Union of views of one object in one frame: list of (N_i, 3) -> (M, 3) float32.

    M = sum N_i, or max_points drawn at random (seeded) when the union is larger.
    """
    if not views:
        raise ValueError('fuse_views needs at least one view')
    pts = np.concatenate([np.asarray(v, dtype=np.float32).reshape(-1, 3) for v in views])
    if not np.isfinite(pts).all():
        raise ValueError('views hold non-finite points')
    if len(pts) > max_points:
        pts = pts[np.sort(np.random.default_rng(seed).choice(len(pts), max_points,
                                                             replace=False))]
    return pts


def fused_examples(views: Sequence[np.ndarray], scans: int = FUSED_SCANS, seed: int = 0,
                   cfg: ViewConfig | None = None) -> list[np.ndarray]:
    """The fused cloud and `scans` simulated single-view scans of it: 1 + scans (M_j, 3) clouds.

    views: >= 2 (N_i, 3) float32 views of ONE object in one fixed frame (check with
    `views_overlap`); the views themselves are not returned (the caller keeps them as
    examples too). cfg: the scans' simulator setting (None: core/views.py's default, the
    default bank's). Seeded: the same views and seed give the same clouds.
    """
    if len(views) < 2:
        raise ValueError(f'fusing needs at least 2 views, got {len(views)}')
    fused = fuse_views(views, seed=seed)
    scans_ = simulate_views(fused, scans, seed=seed, cfg=cfg or ViewConfig())
    return [fused] + [v.points for v in scans_]


def with_fused(views: Sequence[np.ndarray], seed: int = 0) -> tuple[list[np.ndarray], str]:
    """The views plus `fused_examples(views)` where they overlap -> (clouds, what happened).

    views: (N_i, 3) float32 views of one object; the text says how many examples fusing added
    or why it did not (fewer than 2 views, or views that do not overlap): the clouds are then
    the views alone.
    """
    views = list(views)
    if len(views) < 2:
        return views, f'not fused: {len(views)} view (fusing needs 2 or more)'
    if not views_overlap(views):
        return views, ('not fused: the views do not overlap (not one object in one fixed '
                       'frame?)')
    extra = fused_examples(views, seed=seed)
    return views + extra, f'{len(views)} views fused into {len(extra)} more examples'
