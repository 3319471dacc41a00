"""Point order never changes a feature: shuffled clouds of every size encode identically.

Sparse clouds (fewer points than the encoder takes) are upsampled by repeating points in a
canonical (x, y, z) order; denser ones go through FPS, whose start point is geometric; huge
ones are first thinned by a coordinate hash. So the prepared array, and with it the feature,
is the same whatever order a sensor driver or a segmenter emits the points in.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.core.sampling import FPS_MAX_INPUT, canonical_order, hashed_subset, prepare
from point_gn_ros.recognizer import encode_clouds, make_encoder


def _object(n: int, seed: int) -> np.ndarray:
    """An object-like cloud: points on a squashed sphere shell plus a few outliers, metres."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v *= np.array([0.4, 0.25, 0.9])
    v[: n // 20] *= 1.3
    return (v + np.array([3.0, -1.0, 0.5])).astype(np.float32)


@pytest.fixture(scope='module')
def encoder():  # noqa: ANN201 - the fast encoder (or the oracle when kernels cannot build)
    return make_encoder(EncoderConfig(num_points=256, k=32), 'cpu', threads=1)


@pytest.mark.parametrize('n', [17, 100, 255, 256, 397])
@pytest.mark.parametrize('method', ['fps', 'random'])
def test_sparse_cloud_shuffles_give_identical_features(encoder, n: int, method: str) -> None:
    cloud = _object(n, n)
    rng = np.random.default_rng(7)
    clouds = [cloud] + [cloud[rng.permutation(n)] for _ in range(4)]
    feats = encode_clouds(clouds, encoder, method)
    for f in feats[1:]:
        assert torch.equal(f, feats[0])   # bit for bit, not approximately


@pytest.mark.parametrize('n', [600, 5000])
def test_denser_cloud_shuffles_give_identical_features(encoder, n: int) -> None:
    cloud = _object(n, n)
    rng = np.random.default_rng(8)
    clouds = [cloud] + [cloud[rng.permutation(n)] for _ in range(3)]
    feats = encode_clouds(clouds, encoder, 'fps')
    for f in feats[1:]:
        assert torch.equal(f, feats[0])


def test_upsampling_keeps_every_point_and_repeats_evenly() -> None:
    cloud = _object(397, 1)
    out = prepare(cloud, 1024)
    assert out.shape == (1024, 3)
    shuffled = prepare(cloud[::-1].copy(), 1024)
    np.testing.assert_array_equal(out, shuffled)
    order = canonical_order(cloud)
    np.testing.assert_array_equal(order, np.lexsort((cloud[:, 2], cloud[:, 1], cloud[:, 0])))


def test_hashed_subset_is_order_free_and_seeded() -> None:
    cloud = _object(FPS_MAX_INPUT + 5000, 2)
    perm = np.random.default_rng(3).permutation(len(cloud))
    a = cloud[hashed_subset(cloud, 1000, seed=4)]
    b = cloud[perm][hashed_subset(cloud[perm], 1000, seed=4)]
    np.testing.assert_array_equal(a, b)
    assert len({tuple(p) for p in a}) == 1000          # distinct points, no repeats
    c = cloud[hashed_subset(cloud, 1000, seed=5)]
    assert not np.array_equal(a, c)
    assert len(hashed_subset(cloud[:10], 10)) == 10    # m == N: every point


def test_huge_cloud_shuffle_prepares_identically() -> None:
    cloud = _object(FPS_MAX_INPUT * 2, 3)
    perm = np.random.default_rng(5).permutation(len(cloud))
    np.testing.assert_array_equal(prepare(cloud, 256), prepare(cloud[perm], 256))
