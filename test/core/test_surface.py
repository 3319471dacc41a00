"""Local surface-ness (core/surface.py) and the volume rule of the Recognizer."""

from __future__ import annotations

import numpy as np
import pytest

from point_gn_ros.core.surface import (DEFAULT_VOLUME_THRESHOLD, SURFACE_K, volume_rule,
                                       volumetric_shares)

from conftest import SHARED

SAMPLES = SHARED / 'samples' / 'pcd'


def _blobs(rng: np.random.Generator, count: int, n: int = 50) -> list[np.ndarray]:
    return [(rng.normal(size=(n, 3)) * rng.uniform(0.05, 1.0)).astype(np.float32)
            for _ in range(count)]


def _ring_scan(rng: np.random.Generator, radius: float, height: float) -> np.ndarray:
    """A lidar's view of an upright cylinder (a pole, a trunk) 6 m away.

    Points on 1.33-degree rings, 0.16 degrees apart along each ring, the near side only.
    """
    rings = np.radians(np.arange(-8, 3) * 1.33)
    az = np.radians(np.arange(-20, 20) * 0.16)
    pts = []
    for e in rings:
        for a in az:
            d = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
            # ray from the sensor at (0, 0, 1.8) against the cylinder at x = 6 m
            oc = np.array([-6.0, 0.0])
            b = d[:2] @ oc
            c = oc @ oc - radius ** 2
            a2 = d[:2] @ d[:2]
            disc = b * b - a2 * c
            if disc < 0:
                continue
            t = (-b - np.sqrt(disc)) / a2
            p = t * d + [0.0, 0.0, 1.8]
            if 0.0 <= p[2] <= height:
                pts.append(p + rng.normal(0, 0.01, 3))
    return np.asarray(pts, dtype=np.float32)


def test_blobs_are_volumetric_and_sensor_views_are_surfaces() -> None:
    rng = np.random.default_rng(0)
    blobs = volumetric_shares(_blobs(rng, 100))
    assert blobs.min() > DEFAULT_VOLUME_THRESHOLD
    pole = _ring_scan(rng, 0.15, 3.0)
    assert 30 <= len(pole) <= 400
    shares = volumetric_shares([pole, *[_read(f) for f in ('bunny', 'milk_color')]])
    assert shares.max() < 0.5


def test_shares_are_per_cloud_whatever_the_batch_order_or_scale() -> None:
    rng = np.random.default_rng(1)
    clouds = [*_blobs(rng, 3), _ring_scan(rng, 0.3, 2.0), np.zeros((SURFACE_K, 3), np.float32)]
    alone = np.array([volumetric_shares([c])[0] for c in clouds])
    np.testing.assert_allclose(volumetric_shares(clouds), alone)
    np.testing.assert_allclose(volumetric_shares(clouds[::-1]), alone[::-1])
    np.testing.assert_allclose(volumetric_shares([c * 1e4 for c in clouds]), alone)
    assert alone[-1] == 0.0                          # too few points to tell
    assert volume_rule(1.0) is None and volume_rule(0.8) == 0.8


def _read(name: str) -> np.ndarray:
    from point_gn_ros.datasets.points import read_points
    path = SAMPLES / f'{name}.pcd'
    if not path.is_file():
        pytest.skip(f'{path} absent (../shared/samples)')
    p = read_points(path)
    return p[np.isfinite(p).all(1)]


def test_recognizer_volume_rule_rejects_blobs_only() -> None:
    from point_gn_ros.recognizer import Recognizer
    rec = Recognizer.from_bank(None)
    rule = Recognizer(rec.bank, encoder=rec.encoder,
                      volume_threshold=volume_rule(DEFAULT_VOLUME_THRESHOLD))
    rng = np.random.default_rng(2)
    clouds = [*_blobs(rng, 4), _read('milk_color')]
    res = rule.classify_clouds(clouds)
    assert (res.labels[:4] == -1).all() and res.labels[4] >= 0
    assert res.volumetric is not None and res.volumetric.shape == (5,)
    later = rule.classify_later(clouds)()
    np.testing.assert_array_equal(later.labels, res.labels)
    assert rec.classify_clouds(clouds).volumetric is None      # no rule: not measured
