"""What this process's CPUs deliver together over time: cores' worth of the one-core peak.

Every --every seconds, pgn_peak_ops on all allowed CPUs at once for ~0.2 s (wall clock,
core/kernels/roofline.py measure_parallel_ops) over the one-core peak (thread CPU time). On
a virtual machine whose host is shared, steal time shows here and nowhere else: the batched
encoder's rate (issue 13's 1,000 clouds/s) can be at most this many cores' worth.

Run: python benchmarks/cpu_capacity.py [--seconds 60] [--every 5]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from point_gn_ros.core import kernels
from point_gn_ros.core.encoder import default_threads
from point_gn_ros.core.kernels.roofline import measure_parallel_ops, measure_peaks


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--seconds', type=float, default=60.0)
    p.add_argument('--every', type=float, default=5.0)
    args = p.parse_args()
    lib = kernels.load_bench()
    cpus = default_threads()
    one = measure_peaks(lib, tries=3).ops
    got = []
    end = time.monotonic() + args.seconds
    while time.monotonic() < end:
        got.append(measure_parallel_ops(lib, cpus, one, tries=1) / one)
        print(f'{time.strftime("%H:%M:%S")}  {got[-1]:.2f} cores\' worth of {cpus}', flush=True)
        time.sleep(args.every)
    q = np.percentile(got, [0, 50, 100])
    print(f'one core {one / 1e9:.1f} G lane-ops/s; {cpus} CPUs at once: min / median / max '
          f"{q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f} cores' worth over {len(got)} samples")


if __name__ == '__main__':
    main()
