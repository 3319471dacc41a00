#!/usr/bin/env python3
"""The coarse pass's kernels alone: int8 (pgn_scan_i8) against packed 4-bit (pgn_scan_i4).

usage: benchmarks/coarse_scan_time.py [--shapes 78744x288 100000x128] [--gap-ms 0 33]
       [--repeats 40]

Random codes in [-7, 7] (the same integers for both kernels), one lone query, the median
wall time of `--repeats` passes, each after `--gap-ms` of idle time (33: a sensor's rate,
when caches and clocks have gone cold). Checks that both kernels give the same scores.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from point_gn_ros.bank.index import pack_codes
from point_gn_ros.core import kernels


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--shapes', nargs='+', default=['78744x288', '100000x128', '100000x512'])
    ap.add_argument('--gap-ms', type=float, nargs='+', default=[0.0, 33.0])
    ap.add_argument('--repeats', type=int, default=40)
    args = ap.parse_args()
    lib = kernels.load()
    if lib is None:
        raise SystemExit(f'compiled kernels unavailable: {kernels.last_error()}')
    rng = np.random.default_rng(0)
    print('| rows x dims | gap ms | int8 median ms | int4 median ms |\n|---|---:|---:|---:|')
    for shape in args.shapes:
        n, r = (int(v) for v in shape.split('x'))
        codes = rng.integers(-7, 8, (n, r)).astype(np.int8)
        packed, q = pack_codes(codes), rng.integers(-127, 128, r).astype(np.int8)
        out8, out4 = np.empty(n, np.int32), np.empty(n, np.int32)
        runs = {'int8': (lib.pgn_scan_i8, codes, out8), 'int4': (lib.pgn_scan_i4, packed, out4)}
        for gap in args.gap_ms:
            med = {}
            for name, (kernel, rows, out) in runs.items():
                times = []
                for _ in range(args.repeats):
                    if gap:
                        time.sleep(gap / 1e3)
                    t0 = time.perf_counter()
                    kernel(rows.ctypes.data, n, r, q.ctypes.data, out.ctypes.data)
                    times.append(time.perf_counter() - t0)
                med[name] = 1e3 * float(np.median(times))
            assert np.array_equal(out8, out4), 'the kernels disagree'
            print(f'| {n:,} x {r} | {gap:g} | {med["int8"]:.3f} | {med["int4"]:.3f} |')


if __name__ == '__main__':
    main()
