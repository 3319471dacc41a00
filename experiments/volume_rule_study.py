#!/usr/bin/env python3
"""The volume rule (core/surface.py) on what must be unknown and what must be kept.

Per group of clouds, the share of volumetric neighbourhoods (volumetric_shares) and how many
the default rule (> DEFAULT_VOLUME_THRESHOLD -> unknown) rejects:

  must be unknown  random Gaussian blobs of 50 points (sd 0.05-1 m), 200 of them
  must be kept     the restaurant Kinect-sim tabletop views (every 3rd of 1,200); ModelNet40
                   TEST objects (--objects, seeded) at a plausible real size as single-view
                   scans (core/views.py) and as sparse lidar clusters (first return per beam of
                   a 32-ring, 1.33-degree / 0.16-degree scanner 4-25 m away, 30-2,000 points);
                   bush-like volumes of foliage seen the same way; the real PCDs (bunny,
                   milk carton, the table scene)
  reported         complete ModelNet40 objects (1,024 points on the whole CAD surface, inner
                   faces included: no sensor sees this) at a plausible size

usage: experiments/volume_rule_study.py [--objects 300] [--seed 0]
"""

from __future__ import annotations

import argparse
from pathlib import Path
import time

import numpy as np
from scipy.spatial import cKDTree

from point_gn_ros.bank.taught import plausible_scale
from point_gn_ros.core.surface import DEFAULT_VOLUME_THRESHOLD, volumetric_shares
from point_gn_ros.core.views import simulate_view
from point_gn_ros.datasets import open_dataset
from point_gn_ros.datasets.points import read_points

SHARED = Path(__file__).resolve().parents[2] / 'shared'


def ring_scan(x: np.ndarray, rng: np.random.Generator, dist: float, h: float = 1.8,
              az_step: float = 0.16, el_step: float = 1.33, beam: float = 0.1,
              noise: float = 0.01) -> np.ndarray:
    """A lidar's first returns off an object `dist` m away -> (M, 3).

    Per (ring, azimuth step), the nearest point within `beam` degrees of the beam, placed on
    the beam at its range (+ range noise).
    """
    x = x - np.r_[x[:, :2].mean(0), x[:, 2].min()]
    yaw = rng.uniform(0, 2 * np.pi)
    x = x + dist * np.r_[np.cos(yaw), np.sin(yaw), 0.0] - [0.0, 0.0, h]
    r = np.linalg.norm(x, axis=1)
    az = np.degrees(np.arctan2(x[:, 1], x[:, 0]))
    el = np.degrees(np.arcsin(x[:, 2] / r))
    ring, step = np.round(el / el_step), np.round(az / az_step)
    ok = (np.abs(el - ring * el_step) < beam) & (np.abs(az - step * az_step) < beam)
    first: dict = {}
    for i in np.flatnonzero(ok):
        key = (ring[i], step[i])
        if key not in first or r[i] < r[first[key]]:
            first[key] = i
    if not first:
        return np.zeros((0, 3))
    keys, idx = np.array(list(first)), np.array(list(first.values()))
    rr = r[idx] + rng.normal(0, noise, len(idx))
    e, a = np.radians(keys[:, 0] * el_step), np.radians(keys[:, 1] * az_step)
    return np.c_[rr * np.cos(e) * np.cos(a), rr * np.cos(e) * np.sin(a), rr * np.sin(e) + h]


def densified(x: np.ndarray, m: int, rng: np.random.Generator) -> np.ndarray:
    """M points near the surface of a 1,024-point object, each jittered within its spacing."""
    d, _ = cKDTree(x).query(x, k=4)
    return x[rng.integers(0, len(x), m)] + rng.normal(0, np.median(d[:, 3]) / 3, (m, 3))


def groups(n_objects: int, rng: np.random.Generator) -> dict[str, list[np.ndarray]]:
    g: dict[str, list[np.ndarray]] = {}
    g['blobs (unknown)'] = [rng.normal(size=(50, 3)) * rng.uniform(0.05, 1.0)
                            for _ in range(200)]
    tab = open_dataset(SHARED / 'datasets' / 'restaurant_kinectsim' / 'all', split='train')
    g['tabletop views'] = [tab[i][0] for i in range(0, len(tab), 3)]
    mn = open_dataset(SHARED / 'datasets' / 'modelnet40_1024', split='test')
    scans, lidar, complete = [], [], []
    for i in rng.choice(len(mn), n_objects, replace=False):
        x, y = mn[int(i)]
        s = plausible_scale(x, mn.class_names[int(y)]) * rng.uniform(0.8, 1.25)
        complete.append(x * s)
        scans.append(simulate_view(x, int(i)).points * s)
        ring = ring_scan(densified(x * s, 60000, rng), rng, rng.uniform(4, 25))
        if len(ring) >= 30:
            lidar.append(ring[:2000])
    g['ModelNet40 scans'] = scans
    g['ModelNet40 lidar clusters'] = lidar
    bushes = []
    for _ in range(60):
        r0 = rng.uniform(0.3, 1.0)
        b = rng.normal(size=(80000, 3))
        b = b / np.linalg.norm(b, axis=1, keepdims=True) * r0 * rng.uniform(0, 1, (80000, 1)) \
            ** (1 / 3)
        b[:, 2] = b[:, 2] * 0.8 + r0
        ring = ring_scan(b, rng, rng.uniform(4, 20))
        if len(ring) >= 30:
            bushes.append(ring[:2000])
    g['bush-like lidar clusters'] = bushes
    for name in ('bunny', 'milk_color', 'table_scene_mug_stereo_textured'):
        p = read_points(SHARED / 'samples' / 'pcd' / f'{name}.pcd')
        g[f'{name}.pcd'] = [p[np.isfinite(p).all(1)]]
    g['complete ModelNet40 (reported)'] = complete
    return g


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--objects', type=int, default=300)
    ap.add_argument('--seed', type=int, default=0)
    args = ap.parse_args()
    g = groups(args.objects, np.random.default_rng(args.seed))
    thr = DEFAULT_VOLUME_THRESHOLD
    print(f'| group | clouds | points (median) | volumetric share min / 5th / median / 95th / '
          f'max | > {thr:g} (unknown) |\n|---|---|---|---|---|')
    total, count = 0.0, 0
    for name, clouds in g.items():
        t0 = time.perf_counter()
        v = volumetric_shares(clouds)
        total += time.perf_counter() - t0
        count += len(clouds)
        pct = ' / '.join(f'{x:.2f}' for x in np.percentile(v, [0, 5, 50, 95, 100]))
        print(f'| {name} | {len(clouds)} | {np.median([len(c) for c in clouds]):.0f} | {pct} | '
              f'{100 * np.mean(v > thr):.1f} % |')
    print(f'\nmeasuring: {1e3 * total / count:.2f} ms a cloud (whole groups in one call)')


if __name__ == '__main__':
    main()
