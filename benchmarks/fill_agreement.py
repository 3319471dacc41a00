"""midpoint_fill's compiled parts (pgn_prepare.c) against their references, on ModelNet40 scans.

Every ModelNet40 cloud (train and test) as a simulated single-view scan in a sensor frame
(the views of core/views.py through the demo's placement; under 1,024 points, so the shipped
bank's 'midpoint' upsampling fills it up):
- canonical_order: the radix sort against np.lexsort;
- midpoint_neighbours: compiled against the numpy form (float64 input takes it);
- midpoint_fill: the output against the k-d tree form used before 2026-12-04 (scipy's
  cKDTree, whose order of exactly tied distances is its own), which built the shipped bank.
Prints how many clouds agree bit for bit in each.

Run: python benchmarks/fill_agreement.py [--data ../shared/datasets/modelnet40_1024]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import h5py
import numpy as np
from scipy.spatial import cKDTree

from point_gn_ros.clients.node_client import place_in_sensor_frame
from point_gn_ros.core import kernels, sampling


def kdtree_fill(xyz: np.ndarray, n: int) -> np.ndarray:
    """midpoint_fill as it was: the neighbours from scipy's cKDTree."""
    xyz = xyz[np.lexsort((xyz[:, 2], xyz[:, 1], xyz[:, 0]))]
    count = len(xyz)
    if count >= n or count < 2:
        return xyz[np.arange(n) % count]
    rounds = -(-(n - count) // count)
    k = min(rounds, count - 1)
    nb = cKDTree(xyz).query(xyz, k=k + 1)[1].reshape(count, k + 1)[:, 1:]
    parts, missing = [xyz], n - count
    for r in range(rounds):
        rows = (np.arange(count) if missing >= count
                else np.sort(sampling.hashed_subset(xyz, missing)))
        parts.append(xyz[rows] * np.float32(0.5) + xyz[nb[rows, r % k]] * np.float32(0.5))
        missing -= len(rows)
    return np.concatenate(parts).astype(np.float32, copy=False)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--data', default=str(Path(__file__).parents[1] / '..' / 'shared' / 'datasets'
                                         / 'modelnet40_1024'))
    args = p.parse_args()
    if kernels.load() is None:
        raise SystemExit(f'kernels unavailable: {kernels.last_error()}')
    rng = np.random.default_rng(0)
    n = order_eq = nb_eq = fill_eq = 0
    for f in sorted(Path(args.data).glob('ply_data_*.h5')):
        with h5py.File(f, 'r') as h:
            data = h['data'][:].astype(np.float32)
        for cloud in data:
            scan = np.ascontiguousarray(place_in_sensor_frame(cloud, rng, single_view=True),
                                        dtype=np.float32)
            n += 1
            order_eq += np.array_equal(sampling.canonical_order(scan),
                                       np.lexsort((scan[:, 2], scan[:, 1], scan[:, 0])))
            x = scan[sampling.canonical_order(scan)]
            k = min(-(-(1024 - len(x)) // len(x)), len(x) - 1)
            nb_eq += np.array_equal(sampling.midpoint_neighbours(x, k),
                                    sampling.midpoint_neighbours(x.astype(np.float64), k))
            fill_eq += np.array_equal(sampling.midpoint_fill(scan, 1024), kdtree_fill(scan, 1024))
    print(f'{n} scans: canonical order equal to np.lexsort in {order_eq}, neighbours equal to '
          f'the numpy form in {nb_eq}, fills equal to the k-d tree form in {fill_eq}')


if __name__ == '__main__':
    main()
