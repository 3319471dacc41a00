"""`point_gn bench --profile`: the roofline table, each phase's time against its floor.

Kernel phases come from the instrumented build (pgn_prof); the classifier rows time the
lone-query bank scans. Floors are work / peaks measured in the same run
(core/kernels/roofline.py).
"""

from __future__ import annotations

import time
from typing import Any

from point_gn_ros.commands.bench_inputs import synthetic_bank, synthetic_clouds

Row = dict[str, Any]     # one row of `point_gn bench`'s table

__all__ = ['PROFILE_SLOTS', 'profile_rows', 'search_roofline_rows']


# Instrumented kernel slots (pgn_prof, encoder/pgn_encode.c) -> phase names of the roofline
# table.
PROFILE_SLOTS = {8: 'initial embedding', 0: 'FPS', 1: 'kNN', 7: 'feature std',
                 3: 'aggregation stage 1', 4: 'aggregation stage 2', 5: 'aggregation stage 3',
                 6: 'aggregation stage 4', 9: 'pooling', 10: 'offsets and their std',
                 11: 'work space (allocate, zero)'}
_PROF_LEN = 16  # length of pgn_prof


def _roofline_row(what: str, seconds: float, floor: float | None, note: str = '') -> Row:
    ratio = f'{seconds / floor:.1f}x its floor' if floor else 'no floor counted'
    return dict(section='roofline', what=what, value=seconds * 1e3, unit='ms CPU',
                floor_ms=None if floor is None else floor * 1e3,
                note=(f'floor {floor * 1e3:.3f} ms, ' if floor else '') + ratio
                + (f'; {note}' if note else ''))


def profile_rows(quick: bool, repeats: int) -> list[Row]:
    """Roofline table: each phase's CPU time per cloud against its floor on this core.

    Time: one thread, instrumented build, min of repeats. Floor: work / peaks measured
    in this run (core/kernels/roofline.py).
    """
    import ctypes

    import numpy as np

    from point_gn_ros.core import kernels
    from point_gn_ros.core.encoder import PointGNEncoder, default_threads
    from point_gn_ros.core.kernels.roofline import (measure_parallel_ops, measure_peaks,
                                                    phase_work)

    lib = kernels.load()
    try:
        prof = (ctypes.c_double * _PROF_LEN).in_dll(lib, 'pgn_prof') if lib is not None else None
    except ValueError:
        prof = None
    if prof is None:
        return [dict(section='roofline', what='kernel phases', value=float('nan'), unit='ms',
                     note='needs the instrumented kernel: run with --profile from a fresh '
                          'process')]
    bench = kernels.load_bench()     # bench/pgn_peak.c: not in the product library
    peaks = measure_peaks(bench, tries=2 if quick else 5)
    rows = [dict(section='peaks', what='fp32 lane ops (FMA + add chains)', value=peaks.ops / 1e9,
                 unit='G/s', note='one core, thread CPU time, best of tries'),
            dict(section='peaks', what='exp (encoder polynomial)', value=peaks.exps / 1e9,
                 unit='G/s', note=''),
            dict(section='peaks', what='read bandwidth, 256 KB (L2)', value=peaks.l2_bw / 1e9,
                 unit='GB/s', note=''),
            dict(section='peaks', what='read bandwidth, 256 MB (memory)',
                 value=peaks.mem_bw / 1e9, unit='GB/s', note='')]
    cpus = default_threads()          # the CPUs this process may run on
    together = measure_parallel_ops(bench, cpus, peaks.ops, tries=2 if quick else 3)
    cores = together / peaks.ops
    rows.append(dict(section='peaks', what=f'fp32 lane ops, {cpus} CPU(s) at once',
                     value=together / 1e9, unit='G/s',
                     note=f"wall clock, best of tries: {cores:.2f} cores' worth of the one-core "
                          'peak (steal and shared cores count here)'))
    enc = PointGNEncoder(threads=1)
    clouds = synthetic_clouds(8 if quick else 32, enc.cfg.num_points, seed=5)
    enc.encode(clouds[:1])
    best = None
    for _ in range(max(2, repeats)):
        for i in range(_PROF_LEN):
            prof[i] = 0.0
        t0 = time.thread_time()  # batch on the calling thread (threads=1)
        enc.encode(clouds)
        total = time.thread_time() - t0
        got = np.array([total] + [prof[i] for i in range(_PROF_LEN)]) / len(clouds)
        best = got if best is None else np.minimum(best, got)
    work = phase_work(enc.cfg)
    floors = {name: w.floor(peaks) for name, w in work.items()}
    for slot, name in PROFILE_SLOTS.items():
        rows.append(_roofline_row(name, float(best[slot + 1]), floors.get(name)))
    named = sum(float(best[slot + 1]) for slot in PROFILE_SLOTS)
    rows.append(_roofline_row('rest (copies, pe tables, calls)', float(best[0]) - named, None))
    floor = sum(floors.values())
    rows.append(_roofline_row('encoder, one cloud, all phases', float(best[0]), floor,
                              '1 thread, min over repeats'))
    # What batches could reach on all CPUs: this run's cloud cost and its floor, each spread
    # over the cores' worth measured above (against the 1,000 clouds/s goal).
    rows.append(dict(section='roofline', what=f'encoder, batched on {cpus} CPU(s): ceiling',
                     value=cores / floor, unit='clouds/s',
                     note=f"{cores:.2f} cores' worth / floor; at this run's phase times "
                          f'{cores / float(best[0]):.0f} clouds/s'))
    rows += search_roofline_rows(peaks, quick, repeats)
    return rows


def search_roofline_rows(peaks, quick: bool, repeats: int) -> list[Row]:
    """Lone-query classification against a 100k-entry bank (10k with --quick).

    Exact float32 scan and the two-stage search (bank/index.py), thread CPU time.
    """
    import numpy as np

    from point_gn_ros.bank.index import BankIndex
    from point_gn_ros.core.kernels.roofline import Work, bank_scan_work

    n, dims = (10_000 if quick else 100_000), 512
    feats, labels = synthetic_bank(n, dims, seed=3)
    index = BankIndex(feats, labels, num_classes=40)
    rng = np.random.default_rng(4)
    queries = feats[rng.integers(0, n, 8)]
    queries = queries + (rng.normal(0, 0.3, queries.shape)
                         * (1.0 + np.arange(dims)) ** -0.6).astype(np.float32)
    queries /= np.linalg.norm(queries, axis=1, keepdims=True)
    rows = []
    # floors: the float32 bank read once; the coarse codes read once plus the rescored rows
    exact_work = bank_scan_work(n, dims, 4.0)
    coarse_work = bank_scan_work(n, index.coarse_dims, index.code_bits / 8)
    rescore = bank_scan_work(index.candidates, dims, 4.0)
    two_stage = Work(ops=coarse_work.ops + rescore.ops, bytes=coarse_work.bytes + rescore.bytes,
                     memory=True)
    def exact(q: np.ndarray) -> int:
        """The nearest entry of q (1, d) by the exact float32 scan."""
        return int(np.argmax(index.dots(q[0], None)))

    def indexed(q: np.ndarray) -> int:
        """The nearest entry of q (1, d) among its coarse candidates, rescored exactly."""
        rows = index.candidates_many(q)[0]
        return int(rows[np.argmax(index.dots(q[0], rows))])

    for what, fn, work in (('classifier: exact float32 scan', exact, exact_work),
                           (f'classifier: int{index.code_bits} {index.coarse_dims}-d scan + '
                            f'{index.candidates} rescored', indexed, two_stage)):
        fn(queries[:1])
        best = float('inf')
        for _ in range(max(2, repeats)):
            t0 = time.thread_time()
            for q in queries:
                fn(q[None])
            best = min(best, (time.thread_time() - t0) / len(queries))
        floor = work.floor(peaks)
        rows.append(_roofline_row(what, best, floor, f'lone query, {n:,} x {dims} bank'))
    agree = np.array([exact(q[None]) == indexed(q[None]) for q in queries])
    rows[-1]['note'] += (f'; coarse energy {index.coarse_energy:.2f}, same nearest entry as '
                         f'exact {int(agree.sum())}/{len(agree)}')
    return rows
