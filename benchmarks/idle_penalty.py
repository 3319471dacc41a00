"""A lone cloud's wall time back to back, after a 33 ms sleep and after a 33 ms busy loop.

If the busy loop removes the penalty seen after a sleep, the cost is the core's or vCPU's
idle state (clock, C-state, the hypervisor); if it leaves it, the cost is the caches' and
predictors' state, which other work replaces meanwhile (benchmarks/log/2026-12-05.md).

Run: python benchmarks/idle_penalty.py   (prints median ms per mode, twice each, for 1 and 2
threads)
"""

from __future__ import annotations

import statistics
import time

import numpy as np
import torch

from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.core.encoder import PointGNEncoder
from point_gn_ros.core.sampling import prepare

GAP_S = 0.033


def main() -> None:
    rng = np.random.default_rng(0)
    clouds = torch.from_numpy(np.stack([
        prepare(rng.standard_normal((2000, 3)).astype(np.float32), n=1024) for _ in range(16)]))
    for lone in (1, 2):
        enc = PointGNEncoder(EncoderConfig(), lone_threads=lone)
        for i in range(len(clouds)):          # warm-up: kernels built, buffers touched
            enc.encode(clouds[i:i + 1])
        medians: dict[str, list[float]] = {}
        for mode in ('back to back', 'sleep', 'busy', 'sleep', 'busy', 'back to back'):
            times = []
            for r in range(24):
                if mode == 'sleep':
                    time.sleep(GAP_S)
                elif mode == 'busy':
                    end = time.perf_counter() + GAP_S
                    while time.perf_counter() < end:
                        pass
                cloud = clouds[r % len(clouds)][None]
                t = time.perf_counter()
                enc.encode(cloud)
                times.append(time.perf_counter() - t)
            medians.setdefault(mode, []).append(statistics.median(times) * 1e3)
        print(f'lone_threads={lone}: ' + '; '.join(
            f'{mode} {" / ".join(f"{m:.2f}" for m in ms)} ms' for mode, ms in medians.items()))


if __name__ == '__main__':
    main()
