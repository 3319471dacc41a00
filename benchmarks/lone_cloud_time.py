"""Median wall time of a lone cloud on 1 and 2 encoder threads, for A/B runs of two trees.

Run: PYTHONPATH=TREE python benchmarks/lone_cloud_time.py LABEL
(32 seeded random clouds resampled to 1,024 points, each encoded alone 7 times over;
prints 'LABEL lone1 MS lone2 MS'). Interleave runs of the two trees: wall time on a shared
box drifts by more than the effects measured.
"""

from __future__ import annotations

import statistics
import sys
import time

import numpy as np
import torch

from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.core.encoder import PointGNEncoder
from point_gn_ros.core.sampling import prepare


def main(label: str) -> None:
    rng = np.random.default_rng(0)
    clouds = torch.from_numpy(np.stack([
        prepare(rng.standard_normal((2000, 3)).astype(np.float32), n=1024) for _ in range(32)]))
    out = []
    for lone in (1, 2):
        enc = PointGNEncoder(EncoderConfig(), lone_threads=lone)
        for i in range(len(clouds)):          # warm-up: kernels built, buffers touched
            enc.encode(clouds[i:i + 1])
        times = []
        for _ in range(7):
            t0 = time.perf_counter()
            for i in range(len(clouds)):
                enc.encode(clouds[i:i + 1])
            times.append((time.perf_counter() - t0) / len(clouds) * 1e3)
        out.append(f'lone{lone} {statistics.median(times):.3f}')
    print(label, ' '.join(out))


if __name__ == '__main__':
    main(sys.argv[1] if len(sys.argv) > 1 else 'tree')
