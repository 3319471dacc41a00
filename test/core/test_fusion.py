"""core/fusion.py: views of one object in one frame, fused into more enrollment examples."""

from __future__ import annotations

import numpy as np
import pytest

from point_gn_ros.core.fusion import (FUSED_SCANS, fuse_views, fused_examples, views_overlap,
                                      with_fused)
from point_gn_ros.core.views import simulate_views


def _sphere(n: int = 1024, seed: int = 0) -> np.ndarray:
    p = np.random.default_rng(seed).normal(size=(n, 3))
    return (p / np.linalg.norm(p, axis=1, keepdims=True)).astype(np.float32)


def _coverage(obj: np.ndarray, cloud: np.ndarray, tol: float = 0.05) -> float:
    """Share of the object's points within tol of some point of cloud."""
    d = np.linalg.norm(obj[:, None] - cloud[None], axis=2).min(axis=1)
    return float((d < tol).mean())


def test_fused_views_see_most_of_the_object_and_one_view_does_not() -> None:
    obj = _sphere() + np.float32([4.0, -2.0, 0.5])          # an object away from the origin
    views = [v.points for v in simulate_views(obj, 5, seed=3)]
    assert views_overlap(views)
    one = max(_coverage(obj, v) for v in views)
    fused = fuse_views(views)
    assert len(fused) == sum(len(v) for v in views)       # below the cap: the whole union
    # Cameras 10-40 degrees above the horizon never see the bottom: ~85 % of a sphere.
    assert one < 0.5 and _coverage(obj, fused) > 0.8, (one, _coverage(obj, fused))


def test_fused_examples_are_the_union_and_scans_of_it_seeded() -> None:
    obj = _sphere()
    views = [v.points for v in simulate_views(obj, 4, seed=1)]
    out = fused_examples(views, seed=7)
    assert len(out) == 1 + FUSED_SCANS
    np.testing.assert_array_equal(out[0], np.concatenate(views))
    for scan in out[1:]:                                  # a partial view of the union
        assert 32 <= len(scan) < len(out[0]) and scan.dtype == np.float32
        assert _coverage(scan, out[0], tol=0.06) == 1.0
    again = fused_examples(views, seed=7)
    assert all(np.array_equal(a, b) for a, b in zip(out, again, strict=True))
    other = fused_examples(views, seed=8)
    assert not all(np.array_equal(a, b) for a, b in zip(out[1:], other[1:], strict=True))


def test_views_of_a_moving_frame_are_not_fused() -> None:
    obj = _sphere()
    views = [v.points for v in simulate_views(obj, 5, seed=2)]
    moved = [v + np.float32([3.0 * i, 0.0, 0.0]) for i, v in enumerate(views)]
    assert not views_overlap(moved)
    clouds, note = with_fused(moved)
    assert len(clouds) == 5 and 'do not overlap' in note
    clouds, note = with_fused(views)
    assert len(clouds) == 5 + 1 + FUSED_SCANS and '5 views fused into 9' in note
    clouds, note = with_fused(views[:1])
    assert len(clouds) == 1 and 'needs 2 or more' in note
    with pytest.raises(ValueError, match='at least 2'):
        fused_examples(views[:1])


def test_a_large_union_is_thinned_seeded() -> None:
    big = [_sphere(6000, s) for s in range(3)]
    a, b = fuse_views(big, max_points=5000, seed=1), fuse_views(big, max_points=5000, seed=1)
    assert a.shape == (5000, 3) and np.array_equal(a, b)
    with pytest.raises(ValueError, match='non-finite'):
        fuse_views([np.float32([[0, 0, np.nan]]), big[0]])
