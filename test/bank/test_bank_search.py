"""Two-stage bank search (bank/index.py) against the full float32 search."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from point_gn_ros.bank.index import BankIndex
from point_gn_ros.bank.vote import log_vote_shares
from point_gn_ros.commands.bench_cmd import synthetic_bank
from point_gn_ros.core import kernels


def vote_shares_ref(query: torch.Tensor, feats: torch.Tensor, labels: torch.Tensor,
                    num_classes: int, gamma: float) -> torch.Tensor:
    """The reference kernel-vote shares (bank/vote.py `log_vote_shares`): (B, C)."""
    return log_vote_shares(query @ feats.T, labels, num_classes, gamma).exp()


def index_shares(index: BankIndex, q: np.ndarray, gamma: float, exact: bool = False
                 ) -> np.ndarray:
    """Vote shares (B, C) of each query's candidates (every entry when exact)."""
    q = index.check(q)
    out = np.zeros((len(q), index.num_classes), np.float32)
    for b, row in enumerate(q):
        rows = None if exact else index.candidates_for(row)
        sims = torch.from_numpy(index.dots(row, rows))[None]
        labels = index.labels if rows is None else index.labels[rows]
        out[b] = log_vote_shares(sims, torch.from_numpy(labels),
                                 index.num_classes, gamma).exp()[0].numpy()
    return out


def _queries(feats: np.ndarray, count: int, noise: float, seed: int) -> np.ndarray:
    """Bank entries plus noise with the bank's spectrum (see synthetic_bank), unit rows."""
    rng = np.random.default_rng(seed)
    q = feats[rng.integers(0, len(feats), count)]
    spectrum = (1.0 + np.arange(q.shape[1])) ** -0.6
    q = q + (rng.normal(0, noise, q.shape) * spectrum).astype(np.float32)
    return (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32)


def test_all_candidates_is_exact() -> None:
    # every entry rescored: the two-stage result is the full search's, label for label
    feats, labels = synthetic_bank(3_000, 96, seed=3, classes=10)
    index = BankIndex(feats, labels, 10, coarse_dims=32, candidates=3_000)
    q = _queries(feats, 20, 0.5, seed=4)
    exact = index_shares(index, q, 50.0, exact=True)
    np.testing.assert_allclose(index_shares(index, q, 50.0), exact, atol=1e-5)
    ref = vote_shares_ref(torch.from_numpy(q), torch.from_numpy(feats), torch.from_numpy(labels),
                       10, 50.0).numpy()
    np.testing.assert_allclose(exact, ref, atol=1e-5)


def test_candidates_hold_the_nearest_entries() -> None:
    feats, labels = synthetic_bank(20_000, 256, seed=5)
    index = BankIndex(feats, labels, 40, coarse_dims=64, candidates=256)
    q = _queries(feats, 30, 0.3, seed=6)
    hits = 0
    for row in q:
        cand = set(index.candidates_for(row).tolist())
        assert len(cand) == 256
        nearest = np.argsort(-(feats @ row))[:10]
        hits += sum(int(i) in cand for i in nearest)
    assert hits >= 0.95 * 30 * 10  # the coarse pass keeps (almost) all of the 10 nearest
    assert index.coarse_energy > 0.8
    got, exact = index_shares(index, q, 100.0), index_shares(index, q, 100.0, exact=True)
    assert (got.argmax(1) == exact.argmax(1)).all()


def test_batch_invariance_and_shapes() -> None:
    feats, labels = synthetic_bank(5_000, 128, seed=7)
    index = BankIndex(feats, labels, 40)
    q = _queries(feats, 6, 0.3, seed=8)
    together = index_shares(index, q, 50.0)
    alone = np.concatenate([index_shares(index, q[i:i + 1], 50.0) for i in range(len(q))])
    assert np.array_equal(together, alone)
    assert together.shape == (6, 40)
    np.testing.assert_allclose(together.sum(1), 1.0, atol=1e-5)
    assert index_shares(index, q[:0], 50.0).shape == (0, 40)
    with pytest.raises(ValueError):
        index_shares(index, q[:, :10], 50.0)
    with pytest.raises(ValueError):
        BankIndex(feats, labels[:10], 40)


def test_top_m_kernel_ties_to_lowest_index() -> None:
    lib = kernels.load()
    if lib is None:
        pytest.skip(f'compiled kernels unavailable: {kernels.last_error()}')
    rng = np.random.default_rng(9)
    # many ties (100 values); a coarse pass's spread (80k scores, a long upper tail); the
    # extremes of int32; all equal
    cases = [rng.integers(-50, 50, 10_000), np.rint(rng.standard_t(5, 80_000) * 4000),
             rng.choice([np.iinfo(np.int32).min, np.iinfo(np.int32).max, 0], 3_000),
             np.full(1_000, 7)]
    for s in cases:
        s = s.astype(np.int32)
        for m in (1, 37, 500, min(1_024, len(s) - 2), len(s) - 1):
            idx = np.empty(m, np.int32)
            keys = np.empty(len(s), np.int64)
            got = lib.pgn_top_m(s.ctypes.data, len(s), m, idx.ctypes.data, keys.ctypes.data)
            # by score desc, then index (negated in int64: -INT32_MIN overflows int32)
            expect = np.lexsort((np.arange(len(s)), -s.astype(np.int64)))[:m]
            # exactly those, in ascending index order (numpy's pass in search.py gives that)
            assert got == m and idx.tolist() == sorted(expect.tolist()), (len(s), m)
