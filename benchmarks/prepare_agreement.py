"""prepare()'s compiled normalisation and yaw alignment (pgn_prepare.c) against its numpy forms.

Every ModelNet40 cloud (train and test), whole and as a simulated single-view scan in a
sensor frame (the views of core/views.py through the demo's placement), goes through
`resample` and then both forms of `normalize` + `canonical_yaw` (the shipped bank's
settings). Prints how many prepared clouds are bit-identical, the largest difference, and
how many differ by more than 1e-6 (a flipped sign or axis would show there).

Run: python benchmarks/prepare_agreement.py [--data ../shared/datasets/modelnet40_1024]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import h5py
import numpy as np

from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.clients.node_client import place_in_sensor_frame
from point_gn_ros.core import kernels, sampling


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--data', default=str(Path(__file__).parents[1] / '..' / 'shared' / 'datasets'
                                         / 'modelnet40_1024'))
    args = p.parse_args()
    lib = kernels.load()
    if lib is None:
        raise SystemExit(f'kernels unavailable: {kernels.last_error()}')
    cfg = FeatureBank.load(None).config
    rng = np.random.default_rng(0)
    counts = {'whole': [0, 0, 0, 0.0], 'scan': [0, 0, 0, 0.0]}  # clouds, equal, > 1e-6, max
    for f in sorted(Path(args.data).glob('ply_data_*.h5')):
        with h5py.File(f, 'r') as h:
            data = h['data'][:].astype(np.float32)
        for cloud in data:
            for kind, single in (('whole', False), ('scan', True)):
                raw = place_in_sensor_frame(cloud, rng, single_view=single)
                ref = sampling.normalize(sampling.resample(raw, cfg.num_points,
                                                           upsample=cfg.upsample))
                if cfg.yaw_align:
                    ref = sampling.canonical_yaw(ref)
                got = sampling.prepare(raw, cfg.num_points, yaw_align=cfg.yaw_align,
                                       upsample=cfg.upsample)
                d = float(np.abs(got - ref).max())
                c = counts[kind]
                c[0] += 1
                c[1] += d == 0.0
                c[2] += d > 1e-6
                c[3] = max(c[3], d)
    for kind, (n, eq, big, mx) in counts.items():
        print(f'{kind}: {n} clouds, {eq} bit-identical, {big} differ by more than 1e-6, '
              f'max difference {mx:.3g}')


if __name__ == '__main__':
    main()
