"""Roofline figures for the encoder's phases: peak rates of this core, work per phase.

`measure_peaks()` times micro-benchmarks (bench/pgn_peak.c, `kernels.load_bench()`)
with the calling thread's CPU clock, so another process on the core does not lower the
figure (it only takes wall time). `phase_work()` counts, for one cloud of a
configuration, the minimal work of each phase: fp32 lane operations, exps and bytes read.
floor = max(ops / peak_ops + exps / peak_exp, bytes / bandwidth); the phase's measured CPU
time over its floor says how far the code is from this core's limit.

The counts are of the computation, not of our implementation (e.g. a distance is 8
operations, an aggregated element 5), with exps counted for an axis's Gaussians as one
running product (2 exps per axis and neighbour: stage 1's neighbour lanes,
pgn_avx512_neighbour_lanes.c), the cheapest scheme in the code; the separable stages take one exp
per block of 16 centres plus one.
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass
import math
import threading
import time

import numpy as np

from point_gn_ros.core.config import EncoderConfig


@dataclass(frozen=True)
class Peaks:
    """Per-core peaks: fp32 lane operations/s, exps/s, bytes/s from L2 and from memory."""

    ops: float
    exps: float
    l2_bw: float
    mem_bw: float


@dataclass(frozen=True)
class Work:
    """Minimal work of a phase: fp32 lane operations, exps, bytes read and where from."""

    ops: float = 0.0
    exps: float = 0.0
    bytes: float = 0.0
    memory: bool = False  # bytes come from main memory (else from cache: L2)

    def floor(self, peaks: Peaks) -> float:
        """Seconds this work needs at best on one core."""
        compute = self.ops / peaks.ops + self.exps / peaks.exps
        return max(compute, self.bytes / (peaks.mem_bw if self.memory else peaks.l2_bw))


def _best_rate(fn, min_seconds: float, tries: int) -> float:
    """Best work / thread-CPU-second over tries; fn(scale) returns the work done."""
    scale, best = 1, 0.0
    while True:  # grow until one call takes min_seconds of CPU
        t0 = time.thread_time()
        work = fn(scale)
        dt = time.thread_time() - t0
        if dt >= min_seconds:
            break
        scale *= 2 if dt <= 0 else max(2, math.ceil(min_seconds / dt))
    best = work / dt
    for _ in range(tries - 1):
        t0 = time.thread_time()
        work = fn(scale)
        best = max(best, work / max(time.thread_time() - t0, 1e-9))
    return best


def measure_peaks(lib: ctypes.CDLL, min_seconds: float = 0.05, tries: int = 5) -> Peaks:
    """Micro-benchmark peaks of the current core (about 1 s of CPU in all)."""
    def aligned(nbytes: int) -> np.ndarray:
        raw = np.ones(nbytes // 4 + 16, np.float32)
        off = (-raw.ctypes.data % 64) // 4
        return raw[off:off + nbytes // 4]

    l2 = aligned(256 << 10)    # inside L2 (1 MB on Zen 4) and beyond L1
    mem = aligned(256 << 20)   # far beyond any cache
    ops = _best_rate(lambda s: lib.pgn_peak_ops(100_000 * s), min_seconds, tries)
    exps = _best_rate(lambda s: lib.pgn_peak_exp(100 * s), min_seconds, tries)
    l2_bw = _best_rate(lambda s: lib.pgn_peak_read(l2.ctypes.data, l2.size, 50 * s),
                       min_seconds, tries)
    # memory bandwidth is shared by every core: other processes lower it (the least
    # robust of these peaks on a busy machine)
    mem_bw = _best_rate(lambda s: lib.pgn_peak_read(mem.ctypes.data, mem.size, s),
                        min_seconds, tries)
    return Peaks(ops=ops, exps=exps, l2_bw=l2_bw, mem_bw=mem_bw)


def measure_parallel_ops(lib: ctypes.CDLL, threads: int, one_core_ops: float,
                         seconds: float = 0.2, tries: int = 3) -> float:
    """fp32 lane operations per WALL second of `threads` threads running pgn_peak_ops at once.

    What the CPUs this process may use deliver together: unlike the per-core peaks (thread CPU
    time), wall time counts what the hypervisor steals and what SMT siblings share, so
    this over `one_core_ops` is how many cores' worth a batched encoder can have here. Best
    of tries (ctypes releases the GIL for the calls).
    """
    per_iter = lib.pgn_peak_ops(1000) / 1000.0                 # lane operations an iteration
    iters = max(1, int(seconds * one_core_ops / per_iter))
    best = 0.0
    for _ in range(tries):
        done = [0.0] * threads
        start = threading.Barrier(threads + 1)

        def run(i: int, done: list[float] = done, start: threading.Barrier = start) -> None:
            start.wait()
            done[i] = lib.pgn_peak_ops(iters)

        workers = [threading.Thread(target=run, args=(i,)) for i in range(threads)]
        for w in workers:
            w.start()
        start.wait()
        t0 = time.perf_counter()
        for w in workers:
            w.join()
        best = max(best, sum(done) / (time.perf_counter() - t0))
    return best


def _stages(cfg: EncoderConfig):
    """(n points, S centres, K neighbours, D input width) per stage."""
    n, d = cfg.num_points, cfg.init_dim
    for _ in range(cfg.stages):
        s, k = n // 2, min(cfg.k, n)
        yield n, s, k, d
        n, d = s, 2 * d


def phase_work(cfg: EncoderConfig) -> dict[str, Work]:
    """Minimal work per encoder phase for one cloud (keys: the profile's phase names)."""
    fps = knn = std = pool = 0.0
    std_bytes = 0.0
    agg: dict[str, Work] = {}
    for st, (n, s, k, d) in enumerate(_stages(cfg), start=1):
        # FPS and kNN: a distance (3 sub, 3 mul, 2 add) per (centre, point), plus the
        # running min and arg-max (FPS) or one selection compare (kNN).
        pool += s * 2 * d * 2.0  # max and sum over centres of the (S, 2D) output
        fps += s * n * 10.0
        knn += s * n * 9.0
        # offset std: sub, add, fma per gathered element; reads the gathered rows
        std += s * k * d * 3.0
        std_bytes += s * k * d * 4.0
        # aggregation per element of the (S, K, 2D) tensor: sub, fma, mul, max, add for the
        # offset half (add, mul, max, add for the centre half) and one multiply of the
        # separable Gaussian; exps: 2 per neighbour and axis (one running product)
        agg[f'aggregation stage {st}'] = Work(
            ops=s * k * d * (6.0 + 5.0), exps=s * k * 3.0 * 2.0, bytes=s * k * d * 4.0)
    # initial embedding: one Gaussian (sub, mul, exp) per point and channel
    init = Work(ops=cfg.num_points * cfg.init_dim * 2.0, exps=cfg.num_points * cfg.init_dim)
    return {'initial embedding': init, 'FPS': Work(ops=fps), 'kNN': Work(ops=knn),
            'feature std': Work(ops=std, bytes=std_bytes), **agg, 'pooling': Work(ops=pool)}


def bank_scan_work(entries: int, dims: int, bytes_per_value: float) -> Work:
    """A lone query against a bank: one multiply-add per stored value, the bank read once."""
    return Work(ops=float(entries * dims), bytes=entries * dims * bytes_per_value, memory=True)
