"""Cloud structure (core/surface.py): the volume and scene rules of the Recognizer."""

from __future__ import annotations

import numpy as np
import pytest

from point_gn_ros.core.surface import (DEFAULT_SCENE_THRESHOLD, DEFAULT_VOLUME_THRESHOLD,
                                       SURFACE_K, scene_rule, separated_shares,
                                       structure_unknown, volume_rule, volumetric_shares)

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
    assert list(res.rejected_by) == ['volume'] * 4 + ['']
    assert res.volumetric is not None and res.volumetric.shape == (5,)
    later = rule.classify_later(clouds)()
    np.testing.assert_array_equal(later.labels, res.labels)
    assert rec.classify_clouds(clouds).volumetric is None      # no rule: not measured


def _box(rng: np.random.Generator, centre: list[float], dims: list[float],
         n: int) -> np.ndarray:
    """Points (n) on the sides and top of an upright box standing at `centre` (no bottom)."""
    length, width, height = dims
    u, v, face = rng.random(n), rng.random(n), rng.integers(0, 5, n)
    x = np.where(face == 0, -0.5, np.where(face == 1, 0.5, u - 0.5)) * length
    y = np.where(face == 2, -0.5, np.where(face == 3, 0.5,
                                           np.where(face < 2, u, v) - 0.5)) * width
    z = np.where(face == 4, 1.0, v) * height
    return (np.c_[x, y, z] + centre).astype(np.float32)


def _table_scene(rng: np.random.Generator, objects: int) -> np.ndarray:
    """A 1.2 x 0.8 m table top with `objects` cartons on it, 0.25 m or more apart."""
    top = np.c_[(rng.random((3000, 2)) - 0.5) * [1.2, 0.8], np.full(3000, 0.75)]
    spots = [[-0.45, -0.25], [0.0, 0.2], [0.45, -0.2], [-0.3, 0.25], [0.35, 0.25]]
    parts = [_box(rng, [*spots[i], 0.75], [0.07, 0.1, 0.2], 400) for i in range(objects)]
    return np.concatenate([top, *parts]).astype(np.float32)


def _street(rng: np.random.Generator) -> np.ndarray:
    """A lidar frame's worth of street, ground removed: two buildings, cars, poles."""
    parts = [_box(rng, [0, 15, 0], [40, 8, 10], 3000), _box(rng, [-5, -18, 0], [30, 10, 7], 3000)]
    parts += [_box(rng, [x, y, 0], [4.5, 1.8, 1.5], 300) for x, y in ((-20, 0), (-8, 2), (12, -3))]
    parts += [_box(rng, [x, y, 0], [0.2, 0.2, 5.0], 60) for x, y in ((-15, 5), (5, 6), (20, -8))]
    return np.concatenate(parts).astype(np.float32)


def test_scenes_are_apart_and_single_objects_are_not() -> None:
    rng = np.random.default_rng(3)
    scenes = [_table_scene(rng, 3), _table_scene(rng, 5), _street(rng)]
    table = _read('table_scene_mug_stereo_textured')          # camera frame: y down
    scenes.append(table[:, [0, 2, 1]] * np.array([1, 1, -1], dtype=np.float32))
    assert separated_shares(scenes).min() > DEFAULT_SCENE_THRESHOLD
    # one carton on a table it was not cut from: a bare support
    assert separated_shares([_table_scene(rng, 1)])[0] == 1.0
    objects = [_ring_scan(rng, 0.15, 3.0), _ring_scan(rng, 0.3, 2.0),
               _box(rng, [0, 0, 0], [0.07, 0.1, 0.2], 800),
               np.concatenate([_box(rng, [0, 0, 0], [0.8, 0.8, 0.75], 1500),     # a table top
                               np.c_[(rng.random((500, 2)) - 0.5) * 0.8,         # on legs
                                     rng.random(500) * 0.7].astype(np.float32)]),
               *[_read(f) for f in ('bunny', 'milk_color')]]
    assert separated_shares(objects).max() < 0.1
    # a stray point far off neither counts nor grows the grid
    stray = np.concatenate([objects[2], [[1e6, -1e6, 0.1]]]).astype(np.float32)
    assert separated_shares([stray])[0] < 0.1


def test_separated_shares_are_per_cloud_whatever_the_batch_order_or_scale() -> None:
    rng = np.random.default_rng(4)
    clouds = [_table_scene(rng, 3), _ring_scan(rng, 0.3, 2.0), _street(rng),
              np.zeros((SURFACE_K, 3), np.float32), np.ones((100, 3), np.float32)]
    alone = np.array([separated_shares([c])[0] for c in clouds])
    np.testing.assert_allclose(separated_shares(clouds[::-1]), alone[::-1])
    np.testing.assert_allclose(separated_shares([c * 1e3 for c in clouds]), alone, atol=1e-12)
    assert alone[0] > DEFAULT_SCENE_THRESHOLD and alone[2] > DEFAULT_SCENE_THRESHOLD
    assert alone[3] == 0.0 and alone[4] == 0.0        # too few points; one place
    assert scene_rule(1.0) is None and scene_rule(0.3) == 0.3
    rules = structure_unknown([*_blobs(rng, 1), *clouds], DEFAULT_VOLUME_THRESHOLD,
                              DEFAULT_SCENE_THRESHOLD)
    np.testing.assert_array_equal(rules, [True, True, False, True, False, False])
    assert not structure_unknown(clouds, None, None).any()


def test_recognizer_scene_rule_rejects_scenes_only() -> None:
    from point_gn_ros.recognizer import Recognizer
    rec = Recognizer.as_node()
    assert rec.classifier.scene_threshold == DEFAULT_SCENE_THRESHOLD
    rng = np.random.default_rng(5)
    carton = _box(rng, [0.0, 0.0, 0.0], [0.07, 0.1, 0.2], 800)
    clouds = [_table_scene(rng, 3), carton, _street(rng)]
    res = rec.classify_clouds(clouds)
    assert res.separated is not None and res.separated.shape == (3,)
    assert res.labels[0] == -1 and res.labels[2] == -1
    assert 'scene' in res.rejected_by[0].split('+') and 'scene' not in res.rejected_by[1]
    assert res.separated[1] <= DEFAULT_SCENE_THRESHOLD
    later = rec.classify_later(clouds)()
    np.testing.assert_array_equal(later.labels, res.labels)
    off = Recognizer(rec.bank, encoder=rec.encoder)
    assert off.classify_clouds(clouds).separated is None        # no rule: not measured
