"""Roofline pieces of `point_gn bench --profile`: peaks and per-phase work counts."""

from __future__ import annotations

import pytest

from point_gn_ros.commands.bench_cmd import PROFILE_SLOTS
from point_gn_ros.core import kernels
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.core.kernels.roofline import Peaks, Work, bank_scan_work, phase_work


def test_phase_work_counts() -> None:
    cfg = EncoderConfig()
    work = phase_work(cfg)
    # every timed phase with a floor is a profile slot name
    assert set(work) <= set(PROFILE_SLOTS.values())
    # the aggregation of each default stage covers S K 2D = 3.3 M elements (issue 13)
    for st in range(1, 5):
        assert work[f'aggregation stage {st}'].ops == pytest.approx(512 * 120 * 27 * 11)
    # FPS: S n distances per stage
    fps = sum(n // 2 * n * 10 for n in (1024, 512, 256, 128))
    assert work['FPS'].ops == pytest.approx(fps)
    small = phase_work(EncoderConfig(num_points=64, init_dim=6, stages=2, k=100))
    assert small['kNN'].ops == pytest.approx((32 * 64 + 16 * 32) * 9)  # k above n is capped


def test_floor_is_the_slower_of_compute_and_bytes() -> None:
    peaks = Peaks(ops=1e9, exps=1e8, l2_bw=1e9, mem_bw=1e8)
    assert Work(ops=1e9, exps=1e8).floor(peaks) == pytest.approx(2.0)
    assert Work(ops=1e6, bytes=1e9).floor(peaks) == pytest.approx(1.0)       # from L2
    assert bank_scan_work(1000, 100, 4.0).floor(peaks) == pytest.approx(4e-3)  # memory


def test_measured_peaks_are_plausible() -> None:
    from point_gn_ros.core.kernels.roofline import measure_peaks

    lib = kernels.load()
    if lib is None:
        pytest.skip(f'compiled kernels unavailable: {kernels.last_error()}')
    p = measure_peaks(lib, min_seconds=0.01, tries=1)
    # thread CPU time: other processes on the core do not lower these
    assert 1e9 < p.ops < 1e12 and 1e8 < p.exps < p.ops
    assert 1e9 < p.mem_bw < p.l2_bw < 1e12


def test_cpus_at_once_are_measured_in_wall_time() -> None:
    from point_gn_ros.core.kernels.roofline import measure_parallel_ops, measure_peaks

    lib = kernels.load()
    if lib is None:
        pytest.skip(f'compiled kernels unavailable: {kernels.last_error()}')
    one = measure_peaks(lib, min_seconds=0.01, tries=1).ops
    # wall time is never shorter than the thread CPU time of the same work, so n threads give
    # at most about n cores' worth (a margin for the noise between the two measurements)
    for n in (1, 2):
        got = measure_parallel_ops(lib, n, one, seconds=0.02, tries=1)
        assert 0.05 * one < got < 1.3 * n * one, (n, got / one)
