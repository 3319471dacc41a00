"""Single-view scan simulator: geometry against analytic cases, determinism, subset property."""

from __future__ import annotations

import numpy as np
import pytest

from point_gn_ros.bank.selection import stratified_folds
from point_gn_ros.core.views import (DEFAULT_VIEW_CONFIG, VIEW_PROTOCOLS, ZBUFFER_VIEW_CONFIG,
                                     ViewConfig, camera_position, hpr_indices, point_spacing,
                                     simulate_view, simulate_views, visible_indices)
from point_gn_ros.datasets.views import ViewsDataset
from conftest import ArrayDataset

CLEAN = ViewConfig(noise=(0.0, 0.0), dropout=(0.0, 0.0), falloff=0.0)


def sphere(n: int, seed: int = 0) -> np.ndarray:
    p = np.random.default_rng(seed).normal(size=(n, 3))
    return (p / np.linalg.norm(p, axis=1, keepdims=True)).astype(np.float32)


def cube(n: int, half: float = 0.5, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    p = rng.uniform(-half, half, size=(n, 3))
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = rng.choice([-half, half], n)
    return p.astype(np.float32)


@pytest.mark.parametrize('n', [1024, 4000])
@pytest.mark.parametrize('distance', [2.0, 3.0])
def test_sphere_keeps_its_visible_cap(n: int, distance: float) -> None:
    # Unit sphere, camera on +x: p is visible iff n . (c - p) > 0 with n = p.
    xyz = sphere(n)
    cam = np.array([distance, 0.0, 0.0])
    idx = visible_indices(xyz, cam, np.zeros(3), point_spacing(xyz))
    facing = (xyz * (cam - xyz)).sum(axis=1) / np.linalg.norm(cam - xyz, axis=1)
    kept = np.zeros(n, dtype=bool)
    kept[idx] = True
    # Nothing from the far side beyond grazing (sparse clouds keep a few edge-on points just
    # past the silhouette, within the depth tolerance, as a real sensor's grazing returns).
    assert not kept[facing < -0.3].any()
    assert kept[facing < 0].sum() <= 0.15 * kept.sum()
    assert kept[facing > 0.5].mean() > 0.95            # the cap seen under < 60 degrees
    assert kept[facing > 0.3].mean() > 0.6             # and most of it further out
    assert kept.sum() < 0.4 * n                        # a cap, not a hemisphere or more


def test_sparse_sphere_never_sees_its_far_side() -> None:
    # 400 points: cells are ~0.27 radii wide, so grazing returns reach further past the
    # silhouette (measured down to facing -0.25), but nothing from the far side.
    xyz = sphere(400)
    for distance in (2.0, 3.0):
        cam = np.array([distance, 0.0, 0.0])
        idx = visible_indices(xyz, cam, np.zeros(3), point_spacing(xyz))
        facing = (xyz[idx] * (cam - xyz[idx])).sum(axis=1) / np.linalg.norm(cam - xyz[idx],
                                                                            axis=1)
        assert facing.min() > -0.3


def test_cube_face_on_keeps_one_face() -> None:
    half = 0.5
    xyz = cube(6000, half)
    sp = point_spacing(xyz)
    cam = np.array([0.0, 0.0, 2.5])                    # straight above the +z face
    cell, tol = 1.5, 1.5
    idx = visible_indices(xyz, cam, np.zeros(3), sp, cell, tol)
    top = np.isclose(xyz[:, 2], half)
    assert np.isin(np.flatnonzero(top), idx).all()     # every point of the facing face
    # Nothing else but the sides' edge-on rims, within the depth tolerance of the face.
    # (the tolerance grows with depth like a cell's footprint: 10 % over this range)
    depth_below = half - xyz[idx, 2]
    assert depth_below.max() <= 1.1 * tol * cell * sp
    assert top[idx].mean() > 0.7
    assert not np.isclose(xyz[idx, 2], -half).any()    # never the far face


@pytest.mark.parametrize('n', [1024, 4000])
@pytest.mark.parametrize('distance', [2.0, 3.0])
def test_hidden_point_removal_keeps_the_sphere_cap(n: int, distance: float) -> None:
    # The default visibility (issue 9's protocol). Analytic cap: n . (c - p) > 0.
    xyz = sphere(n)
    cam = np.array([distance, 0.0, 0.0])
    idx = hpr_indices(xyz, cam, DEFAULT_VIEW_CONFIG.hpr_radius)
    facing = (xyz * (cam - xyz)).sum(axis=1) / np.linalg.norm(cam - xyz, axis=1)
    kept = np.zeros(n, dtype=bool)
    kept[idx] = True
    assert kept[facing > 0.2].all()                    # the whole cap seen under < 78 degrees
    # Only grazing points past the silhouette (measured down to facing -0.16, 16 % extra at
    # 1,024 points), never the far side (a flip radius of 100 would keep twice the cap).
    assert not kept[facing < -0.25].any()
    assert kept.sum() <= 1.25 * (facing > 0).sum()


def test_hidden_point_removal_sees_one_face_of_a_cube() -> None:
    half = 0.5
    for n in (2000, 6000):
        xyz = cube(n, half)
        idx = hpr_indices(xyz, np.array([0.0, 0.0, 2.5]))     # straight above the +z face
        top = np.isclose(xyz[:, 2], half)
        assert np.isin(np.flatnonzero(top), idx).all()        # every point of the face
        assert top[idx].mean() > 0.8                          # the rest: rims seen edge-on
        assert (half - xyz[idx, 2]).max() < 0.1               # (measured <= 0.083)
        assert not np.isclose(xyz[idx, 2], -half).any()       # never the far face


def test_hidden_point_removal_on_degenerate_clouds() -> None:
    # Too few points for a hull, a flat patch seen from above, a line, one repeated point:
    # everything is seen, nothing fails.
    rng = np.random.default_rng(0)
    for n in (1, 2, 3):
        assert len(simulate_view(rng.normal(size=(n, 3)).astype(np.float32), 0).indices) == n
    plane = np.zeros((50, 3), np.float32)
    plane[:, :2] = rng.uniform(-1, 1, (50, 2))
    line = np.zeros((50, 3), np.float32)
    line[:, 0] = np.linspace(-1, 1, 50)
    for xyz in (plane, line, np.ones((20, 3), np.float32)):
        np.testing.assert_array_equal(simulate_view(xyz, 0, CLEAN).indices, np.arange(len(xyz)))


def test_zbuffer_protocol_is_the_harsher_one() -> None:
    # Round 1's scans (z-buffer, dropout, range falloff) stay available and keep fewer points.
    for xyz in (sphere(1024), cube(1024)):
        hpr = [len(simulate_view(xyz, s).indices) for s in range(10)]
        zbuf = [len(simulate_view(xyz, s, ZBUFFER_VIEW_CONFIG).indices) for s in range(10)]
        assert np.mean(zbuf) < 0.75 * np.mean(hpr), (hpr, zbuf)


def test_mixed_protocol_shares_the_views_in_blocks() -> None:
    # 'mixed' (bank build): view j uses cfg[j * len // k], the same scan the single protocol
    # gives for that view (same seed, azimuth and noise), so caches and CV stay comparable.
    xyz = cube(1500)
    mixed = simulate_views(xyz, 4, 3, VIEW_PROTOCOLS['mixed'])
    hpr = simulate_views(xyz, 4, 3, DEFAULT_VIEW_CONFIG)
    zbuf = simulate_views(xyz, 4, 3, ZBUFFER_VIEW_CONFIG)
    for j, expect in enumerate((hpr[0], hpr[1], zbuf[2], zbuf[3])):
        np.testing.assert_array_equal(mixed[j].points, expect.points)
    assert not np.array_equal(hpr[2].indices, zbuf[2].indices)


def test_views_are_subsets_with_bounded_noise_and_seeded() -> None:
    xyz = cube(2000)
    cfg = ViewConfig(noise=(0.01, 0.01))
    a = simulate_view(xyz, 7, cfg)
    b = simulate_view(xyz, 7, cfg)
    c = simulate_view(xyz, 8, cfg)
    np.testing.assert_array_equal(a.indices, b.indices)
    np.testing.assert_array_equal(a.points, b.points)
    assert not np.array_equal(a.points, c.points)
    # No point invented: each output is its source point plus noise of sigma 1 % of the radius.
    assert len(np.unique(a.indices)) == len(a.indices) and a.indices.max() < len(xyz)
    radius = np.linalg.norm(xyz - xyz.mean(axis=0), axis=1).max()
    disp = np.linalg.norm(a.points - xyz[a.indices], axis=1)
    assert disp.max() < 6 * 0.01 * radius * np.sqrt(3)
    assert 0.5 * 0.01 * radius < np.sqrt((disp ** 2).mean() / 3) < 2 * 0.01 * radius
    clean = simulate_view(xyz, 7, CLEAN)
    np.testing.assert_array_equal(clean.points, xyz[clean.indices])


def test_dropout_and_falloff_thin_a_view() -> None:
    xyz = sphere(4000)
    full = simulate_view(xyz, 3, CLEAN)
    thin = simulate_view(xyz, 3, ViewConfig(noise=(0.0, 0.0), dropout=(0.5, 0.5), falloff=2.0))
    assert np.isin(thin.indices, full.indices).all()
    assert len(thin.indices) < 0.5 * len(full.indices)
    # The near side keeps more of its points than the far side.
    rng_full = np.linalg.norm(xyz[full.indices] - full.camera, axis=1)
    near = full.indices[rng_full < np.median(rng_full)]
    far = full.indices[rng_full >= np.median(rng_full)]
    assert np.isin(near, thin.indices).mean() > np.isin(far, thin.indices).mean()


def test_camera_placement_and_views_spread() -> None:
    cam = camera_position(np.zeros(3), 2.0, np.pi / 2, np.deg2rad(30), 2.5)
    np.testing.assert_allclose(np.linalg.norm(cam), 5.0)
    np.testing.assert_allclose(np.rad2deg(np.arcsin(cam[2] / 5.0)), 30.0)
    views = simulate_views(cube(1500), 4, seed=1)
    az = np.sort([v.azimuth for v in views])
    assert np.all(np.diff(az) > 0) and (np.diff(az) < np.pi).all()   # one per sector
    np.testing.assert_array_equal(simulate_views(cube(1500), 4, seed=1)[2].points,
                                  views[2].points)
    # A camera behind which every point lies sees nothing (no error).
    assert len(visible_indices(cube(100) + 10, np.zeros(3), -np.ones(3), 0.1)) == 0
    for v in views:
        assert 10.0 <= np.rad2deg(v.elevation) <= 40.0 and 2.0 <= v.distance <= 3.0


def test_view_config_validates() -> None:
    with pytest.raises(ValueError):
        ViewConfig(distance=(0.5, 2.0))
    with pytest.raises(ValueError):
        ViewConfig(dropout=(0.0, 1.0))
    with pytest.raises(ValueError):
        ViewConfig(visibility='raycast')
    with pytest.raises(ValueError):
        ViewConfig(hpr_radius=1.0)
    assert ViewConfig.from_dict(ViewConfig().to_dict()) == ViewConfig()


def test_views_dataset_groups_and_folds_keep_objects_together() -> None:
    rng = np.random.default_rng(0)
    clouds = np.stack([cube(600, seed=i) for i in range(30)])
    labels = rng.integers(0, 3, 30)
    base = ArrayDataset(clouds, labels, ['a', 'b', 'c'])
    ds = ViewsDataset(base, 3, seed=2, random_yaw=True)
    assert len(ds) == 120
    np.testing.assert_array_equal(ds.groups, np.repeat(np.arange(30), 4))
    np.testing.assert_array_equal(ds.view_index[:4], [-1, 0, 1, 2])
    np.testing.assert_array_equal(ds.labels, np.repeat(labels, 4))
    # Complete object first (turned by its yaw: same radii), then smaller views.
    np.testing.assert_allclose(np.linalg.norm(ds[0][0][:, :2], axis=1),
                               np.linalg.norm(clouds[0][:, :2], axis=1), rtol=1e-5)
    assert all(len(ds[i][0]) < 600 for i in (1, 2, 3))
    np.testing.assert_array_equal(ds[5][0], ViewsDataset(base, 3, seed=2, random_yaw=True)[5][0])
    folds = stratified_folds(ds.labels, 5, groups=ds.groups)
    fold_of = np.empty(len(ds), dtype=np.int64)
    for f, idx in enumerate(folds):
        fold_of[idx] = f
    for g in range(30):
        assert len(set(fold_of[ds.groups == g])) == 1
    assert sorted(np.concatenate(folds).tolist()) == list(range(len(ds)))


def test_bag_realism_single_view_faces_the_sensor() -> None:
    from point_gn_ros.bag.realism import Placement, Realism

    xyz = cube(3000)
    out = Realism(sensor_frame=True, single_view=True).apply(xyz, np.random.default_rng(4))
    assert 32 <= len(out) < 0.55 * len(xyz)            # at most 3 of the 6 faces (and rims)
    # The scan is the side facing the sensor at the origin: mostly nearer the sensor than the
    # object's centre (the placement's offset: drawn first from the same seed); the whole
    # cube would be half nearer, half farther (measured 0.69: the 3 faces seen from a corner
    # reach past the centre's depth at their far edges).
    centre = Placement.draw(xyz, np.random.default_rng(4)).offset
    dist = np.linalg.norm(out, axis=1)
    assert (dist < np.linalg.norm(centre)).mean() > 0.6
    assert dist.mean() < np.linalg.norm(centre)
    same = Realism(sensor_frame=True, single_view=True).apply(xyz, np.random.default_rng(4))
    np.testing.assert_array_equal(out, same)
    assert Realism(single_view=True).active
