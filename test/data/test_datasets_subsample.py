"""Fixing point counts: 'first', FPS (batched == sampling.fps_indices), repetition."""

from __future__ import annotations

import numpy as np
import pytest

from point_gn_ros.datasets.subsample import fps_indices_batch, subsample, subsample_batch
from point_gn_ros.core.sampling import fps_indices


def test_batched_fps_equals_reference_fps() -> None:
    rng = np.random.default_rng(3)
    xyz = rng.standard_normal((5, 300, 3)).astype(np.float32)
    xyz[1, 100:] = xyz[1, :200]  # duplicate points: ties must resolve like the reference
    xyz[2] = np.round(xyz[2])    # many equal distances
    got = fps_indices_batch(xyz, 64)
    want = np.stack([fps_indices(c, 64) for c in xyz])
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize('method', ['first', 'fps'])
def test_subsample_batch_matches_per_cloud(method: str) -> None:
    rng = np.random.default_rng(4)
    xyz = rng.standard_normal((70, 40, 3)).astype(np.float32)  # more than one FPS chunk
    got = subsample_batch(xyz, 16, method)
    want = np.stack([subsample(c, 16, method) for c in xyz])
    np.testing.assert_array_equal(got, want)
    assert got.shape == (70, 16, 3) and got.dtype == np.float32


def test_first_keeps_order_and_fewer_points_repeat() -> None:
    xyz = np.arange(15, dtype=np.float32).reshape(5, 3)
    np.testing.assert_array_equal(subsample(xyz, 2, 'first'), xyz[:2])
    for method in ('first', 'fps'):
        np.testing.assert_array_equal(subsample(xyz, 7, method), xyz[[0, 1, 2, 3, 4, 0, 1]])
    np.testing.assert_array_equal(subsample_batch(xyz[None], 7)[0], xyz[[0, 1, 2, 3, 4, 0, 1]])
