"""The classifier's fast paths: batched exact scans, the same results in any batch.

pgn_dots.c (the exact vote's cosines), pgn_search.c's pgn_scan_i8_multi (the indexed
search's coarse pass over a batch of queries), and a two-section bank's scan section on a
helper thread.
"""

from __future__ import annotations

import ctypes
from pathlib import Path
import threading

from conftest import kernel_build
import numpy as np
import pytest
import torch

import point_gn_ros.bank.classifier as classifier_mod

from point_gn_ros.bank.enroll import from_stored
from point_gn_ros.bank.vote import ExactSearch, _stored_codes, log_vote_shares
from point_gn_ros.bank.store import quantized
from point_gn_ros.bank.index import BankIndex, IndexedSearch
from point_gn_ros.commands.bench_cmd import synthetic_bank
from point_gn_ros.core import kernels


@pytest.fixture(scope='module')
def lib():
    lib = kernels.load()
    if lib is None:
        pytest.skip(f'compiled kernels unavailable: {kernels.last_error()}')
    return lib


def _unit(rng: np.random.Generator, n: int, d: int) -> np.ndarray:
    x = rng.normal(size=(n, d)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


@pytest.mark.parametrize('d', [512, 320, 37, 8, 3])
def test_bank_dots_exact_and_batch_invariant(lib, d: int) -> None:
    # odd row counts, widths off the 8- and 16-lane steps, every query-group size
    rng = np.random.default_rng(d)
    feats, q = _unit(rng, 101, d), _unit(rng, 11, d)
    got = kernels.bank_dots(feats, q)
    ref = q.astype(np.float64) @ feats.T.astype(np.float64)
    np.testing.assert_allclose(got, ref, atol=2e-6, rtol=0)
    for b in range(len(q)):
        assert np.array_equal(kernels.bank_dots(feats, q[b:b + 1])[0], got[b])
    for lo, hi in ((0, 2), (3, 6), (2, 9), (5, 11)):
        assert np.array_equal(kernels.bank_dots(feats, q[lo:hi]), got[lo:hi])
    # a row's cosines do not depend on the rows beside it either
    assert np.array_equal(kernels.bank_dots(feats[7:40], q), got[:, 7:40])


def test_bank_dots_refuses_rows_it_would_copy(lib) -> None:
    feats = _unit(np.random.default_rng(0), 10, 16)
    with pytest.raises(ValueError, match='C-contiguous float32'):
        kernels.bank_dots(feats.astype(np.float64), feats)
    with pytest.raises(ValueError, match='C-contiguous float32'):
        kernels.bank_dots(np.asfortranarray(feats), feats)
    with pytest.raises(ValueError, match=r'\(B, 16\)'):
        kernels.bank_dots(feats, feats[:, :8])


@pytest.mark.parametrize('r', [32, 288, 40])
def test_scan_i8_multi_equals_one_query_at_a_time(lib, r: int) -> None:
    # integer sums: a batch's pass must give each query exactly its own pass
    rng = np.random.default_rng(r)
    codes = rng.integers(-127, 128, (1_000, r)).astype(np.int8)
    q = rng.integers(-127, 128, (9, r)).astype(np.int8)
    one = np.empty(len(codes), np.int32)
    for nq in (1, 2, 3, 4, 5, 9):
        out = np.empty((nq, len(codes)), np.int32)
        lib.pgn_scan_i8_multi(codes.ctypes.data, len(codes), r, q.ctypes.data, nq,
                              out.ctypes.data)
        for b in range(nq):
            lib.pgn_scan_i8(codes.ctypes.data, len(codes), r, q[b].ctypes.data, one.ctypes.data)
            assert np.array_equal(out[b], one)
            assert np.array_equal(one, codes.astype(np.int32) @ q[b].astype(np.int32))


@pytest.mark.parametrize('bits', [4, 8])
def test_candidates_of_a_batch_are_each_querys_own(monkeypatch, bits: int) -> None:
    feats, labels = synthetic_bank(5_000, 128, seed=5, classes=12)
    index = BankIndex(feats, labels, 12, candidates=300, code_bits=bits)
    assert index.code_bits == bits and index.codes.nbytes == 5_000 * index.coarse_dims * bits // 8
    q = _unit(np.random.default_rng(6), 7, 128)
    many = index.candidates_many(q)
    assert many.shape == (7, 300)
    for b in range(len(q)):
        assert np.array_equal(np.sort(many[b]), np.sort(index.candidates_for(q[b])))
    # a lone query split over two threads (large indexes): the same scores, hence candidates
    import point_gn_ros.bank.index as search_mod
    pool = search_mod.helper_thread()
    if pool is not None:
        used: list[int] = []

        class Counting:
            def submit(self, *a):
                used.append(1)
                return pool.submit(*a)

        monkeypatch.setattr(search_mod, 'SPLIT_MIN_ROWS', 1)
        monkeypatch.setattr(search_mod, 'spare_cpu', lambda: True)
        monkeypatch.setattr(search_mod, 'helper_thread', lambda: Counting())
        for b in range(len(q)):
            assert np.array_equal(index.candidates_many(q[b:b + 1])[0], many[b])
        assert len(used) == len(q)
        monkeypatch.undo()
    # without a C compiler: numpy's pass finds the same candidates
    index._lib = None
    assert np.array_equal(np.sort(index.candidates_many(q), axis=1), np.sort(many, axis=1))
    index._lib = kernels.load()
    # and the search's votes: a query's row is the same alone and in the batch
    search = IndexedSearch(torch.from_numpy(feats), torch.from_numpy(labels), 12,
                           candidates=300, code_bits=bits)
    for b, (sims, rows_labels) in enumerate(search.batch_cosines(torch.from_numpy(q))):
        sims1, labels1 = search.lone_cosines(q[b])
        assert np.array_equal(sims1, sims) and np.array_equal(labels1, rows_labels)


def test_exact_search_on_the_kernel_matches_torch_and_any_batch(lib) -> None:
    rng = np.random.default_rng(7)
    feats = _unit(rng, 3_001, 96)
    labels = torch.from_numpy(rng.integers(0, 9, len(feats)))
    search = ExactSearch(torch.from_numpy(feats), labels, 9)
    q = torch.from_numpy(_unit(rng, 13, 96))
    logv, best = search.log_votes(q, 80.0)
    sims = q @ torch.from_numpy(feats).T      # torch's GEMM: the same cosines within rounding
    torch.testing.assert_close(logv, log_vote_shares(sims, labels, 9, 80.0), atol=2e-4,
                               rtol=0)
    torch.testing.assert_close(best, sims.max(dim=1).values, atol=2e-6, rtol=0)
    one = torch.cat([search.log_votes(q[i:i + 1], 80.0)[0] for i in range(len(q))])
    assert torch.equal(one, logv)


@pytest.mark.parametrize('dtype', ['int4', 'int8'])
def test_exact_search_reads_the_codes_of_an_integer_bank(lib, dtype: str) -> None:
    # a bank stored as int4 / int8 is scanned from its int8 codes (a quarter of the bytes):
    # the same cosines within float32 rounding, and still the same in any batch
    rng = np.random.default_rng(8)
    rows = from_stored(quantized(torch.from_numpy(_unit(rng, 2_001, 100)), dtype))
    labels = torch.from_numpy(rng.integers(0, 6, len(rows)))
    search = ExactSearch(rows, labels, 6)
    assert search.scans_codes
    codes, norms = search._rows
    assert codes.dtype == np.int8 and np.abs(codes).max() == (7 if dtype == 'int4' else 127)
    q = torch.from_numpy(_unit(rng, 9, 100))
    sims = search.similarities(q)
    torch.testing.assert_close(sims, q @ rows.T, atol=2e-6, rtol=0)
    one = torch.cat([search.similarities(q[i:i + 1]) for i in range(len(q))])
    assert torch.equal(one, sims)
    # rows that are not normalised codes (a float bank) are scanned as float32 rows
    assert _stored_codes(_unit(rng, 50, 100)) is None
    assert not ExactSearch(torch.from_numpy(_unit(rng, 50, 100)), labels[:50], 6).scans_codes


def test_two_sections_on_two_threads_give_the_one_thread_answer(monkeypatch) -> None:
    # the shipped bank; demo objects whose gate is unsure need both sections: the scan
    # section then runs on the helper thread, with the same probabilities to the bit
    from point_gn_ros.clients.node_client import load_demo_objects, place_in_sensor_frame
    from point_gn_ros.recognizer import Recognizer

    if classifier_mod.helper_thread() is None:
        pytest.skip('one usable CPU: no helper thread to test')
    rec = Recognizer.from_bank(None, threads=1)
    rng = np.random.default_rng(0)
    feats = rec.encode([place_in_sensor_frame(x, rng) for x in load_demo_objects().xyz])
    p = rec.classifier.gate.scan_probability(feats)
    mixed = (p > classifier_mod.GATE_SKIP) & (p < 1 - classifier_mod.GATE_SKIP)
    assert mixed.sum() >= 2 and (~mixed).sum() >= 2
    views = rec.classifier.views
    seen: list[str] = []
    evaluate = views.evaluate
    monkeypatch.setattr(views, 'evaluate',
                        lambda f: (seen.append(threading.current_thread().name), evaluate(f))[1])
    batch = torch.cat([feats[mixed][:2], feats[~mixed][:2]])
    two = [rec.classifier.classify(batch), rec.classifier.classify(feats[mixed][:1])]
    assert seen and all(name.startswith('pgn_helper') for name in seen)
    monkeypatch.setattr(classifier_mod, 'helper_thread', lambda: None)
    one = [rec.classifier.classify(batch), rec.classifier.classify(feats[mixed][:1])]
    assert not seen[-1].startswith('pgn_helper')
    for a, b in zip(two, one, strict=True):
        assert np.array_equal(a.probability, b.probability)
        assert np.array_equal(a.novelty, b.novelty) and np.array_equal(a.labels, b.labels)


def test_the_helper_thread_is_kept_off_its_callers_cpu() -> None:
    # woken on its caller's CPU, the helper waited behind the busy caller for up to a
    # scheduler tick: each use pins it to the process's other CPUs
    import os

    from point_gn_ros.bank import vote as helper_mod

    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else []
    if len(cpus) < 2 or helper_mod._sched_getcpu is None:
        pytest.skip('needs Linux (sched_getcpu, sched_setaffinity) and two usable CPUs')
    seen: dict[int, set[int]] = {}

    def caller(cpu: int) -> None:
        os.sched_setaffinity(0, {cpu})          # this thread only: runs on `cpu` now
        pool = helper_mod.helper_thread()
        assert pool is not None
        seen[cpu] = pool.submit(lambda: os.sched_getaffinity(0)).result()

    for cpu in cpus[:2]:
        th = threading.Thread(target=caller, args=(cpu,))
        th.start()
        th.join()
    for cpu in cpus[:2]:
        assert seen[cpu] == set(cpus) - {cpu}   # everywhere but where its caller runs


def _check_nibbles(dots_i8, dots_i4, seed: int) -> None:
    rng = np.random.default_rng(seed)
    for n, d in ((9843, 512), (13, 16), (1, 32), (100, 320), (9, 48)):
        codes = rng.integers(-8, 8, (n, d)).astype(np.int8)
        codes[0] = 7
        codes[-1] = -8                                  # both nibbles' extremes
        norms = (np.linalg.norm(codes.astype(np.float32), axis=1) + 0.5).astype(np.float32)
        q = rng.normal(size=d).astype(np.float32)
        assert np.array_equal(dots_i4(kernels.pack_nibbles(codes), norms, q),
                              dots_i8(codes, norms, q)), (n, d)


def test_lone_scan_of_nibbles_is_the_int8_scan_bit_for_bit(lib) -> None:
    _check_nibbles(lambda c, nrm, q: kernels.bank_dots(c, q[None], nrm)[0],
                   kernels.packed_dots_i4, seed=1)
    codes = np.zeros((2, 24), np.int8)
    with pytest.raises(ValueError, match='16 a group'):
        kernels.pack_nibbles(codes)
    with pytest.raises(ValueError, match='do not fit'):
        kernels.packed_dots_i4(kernels.pack_nibbles(codes[:, :16]), np.ones(2, np.float32),
                             np.zeros(8, np.float32))


@pytest.mark.parametrize('build', ['portable', 'avx2'])
def test_lone_scan_of_nibbles_in_other_builds(build: str, tmp_path: Path) -> None:
    """CI machines differ in the path pgn_dots.c takes: each must equal its own int8 scan."""
    one = kernel_build('bank/pgn_dots.c', build, tmp_path,
                       ('-fno-fast-math', '-ffp-contract=off'))
    p, i64 = ctypes.c_void_p, ctypes.c_int64
    one.pgn_dots_i8.argtypes = [p, p, i64, i64, p, i64, p]
    one.pgn_dots_i4.argtypes = [p, p, i64, i64, p, p]

    def dots_i8(codes: np.ndarray, norms: np.ndarray, q: np.ndarray) -> np.ndarray:
        out = np.empty(len(codes), np.float32)
        one.pgn_dots_i8(codes.ctypes.data, norms.ctypes.data, *codes.shape, q.ctypes.data, 1,
                        out.ctypes.data)
        return out

    def dots_i4(packed: np.ndarray, norms: np.ndarray, q: np.ndarray) -> np.ndarray:
        out = np.empty(len(packed), np.float32)
        one.pgn_dots_i4(packed.ctypes.data, norms.ctypes.data, len(packed), 2 * packed.shape[1],
                        q.ctypes.data, out.ctypes.data)
        return out

    _check_nibbles(dots_i8, dots_i4, seed=2)
