#!/usr/bin/env python3
"""The 4-bit coarse pass (pgn_scan_i4.c) of two revisions, timed in one process, interleaved.

usage: benchmarks/scan4_ab.py [--before REV] [--rows 78744] [--codes 288] [--batch 8]
       [--repeats 15]

Compiles core/kernels/bank/pgn_scan_i4.c of git revision REV (default HEAD) and of the working
tree as the package does (-march=native, fast-math), then alternates them on the same
random packed codes and queries: thread CPU a query for one query and for a batch (the
best of --repeats), and checks that both give the same integers. The scan section of the
shipped bank is 78,744 rows of 288 codes.
"""

from __future__ import annotations

import argparse
import ctypes
from pathlib import Path
import subprocess
import tempfile
import time

import numpy as np

from point_gn_ros.core import kernels

_SRC = 'point_gn_ros/core/kernels/bank/pgn_scan_i4.c'


def _build(source: bytes, out: Path) -> ctypes.CDLL:
    src = out.with_suffix('.c')
    src.write_bytes(source)
    cc = kernels._compiler()
    if cc is None:
        raise SystemExit('no C compiler')
    subprocess.run([cc, '-O3', '-fPIC', '-shared', '-std=gnu11', '-ffast-math',
                    *kernels._arch_flags(), str(src), '-o', str(out)], check=True)
    lib = ctypes.CDLL(str(out))
    p, i64 = ctypes.c_void_p, ctypes.c_int64
    lib.pgn_scan_i4_multi.argtypes = [p, i64, i64, p, i64, p]
    return lib


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--before', default='HEAD')
    ap.add_argument('--rows', type=int, default=78_744)
    ap.add_argument('--codes', type=int, default=288)
    ap.add_argument('--batch', type=int, default=8)
    ap.add_argument('--repeats', type=int, default=15)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    n, r, nq = args.rows, args.codes, args.batch
    packed = rng.integers(0, 256, (n, r // 2)).astype(np.uint8)
    q = rng.integers(-127, 128, (nq, r)).astype(np.int8)
    with tempfile.TemporaryDirectory() as tmp:
        old = subprocess.run(['git', 'show', f'{args.before}:{_SRC}'], check=True,
                             capture_output=True).stdout
        libs = {args.before: _build(old, Path(tmp) / 'before.so'),
                'tree': _build(Path(_SRC).read_bytes(), Path(tmp) / 'tree.so')}
        out = {k: np.empty((nq, n), np.int32) for k in libs}
        best = {(k, b): float('inf') for k in libs for b in (1, nq)}
        for _ in range(args.repeats):
            for k, lib in libs.items():
                for b in (1, nq):
                    t = time.thread_time()
                    lib.pgn_scan_i4_multi(packed.ctypes.data, n, r, q.ctypes.data, b,
                                          out[k].ctypes.data)
                    best[(k, b)] = min(best[(k, b)], time.thread_time() - t)
        for k in libs:
            print(f'{k}: one query {best[(k, 1)] * 1e3:.3f} ms, batch of {nq} '
                  f'{best[(k, nq)] / nq * 1e3:.3f} ms a query (thread CPU, best of '
                  f'{args.repeats})')
        a, b = out.values()
        print('same scores:', bool(np.array_equal(a, b)))


if __name__ == '__main__':
    main()
