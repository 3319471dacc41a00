"""Two-stage search for large banks: a coarse scan of integer codes, then exact rescoring.

The kernel vote of a query, sum over entries of exp(-gamma (1 - cos)) per class, is
dominated by the nearest entries at the gammas the banks use (40-200): an entry 0.1
below the best cosine weighs e^-4 (gamma 40) to e^-20 (gamma 200) of it. A lone query
against a float32 bank must read the whole bank (100k x 512 x 4 B = 205 MB: ~7 ms at
this core's ~28 GB/s). Instead:

1. coarse pass: the bank rotated onto its principal axes (an orthogonal rotation, so
   dot products are unchanged), the leading `coarse_dims` coordinates kept as 4-bit codes
   (8 with `code_bits=8`; a scale per coordinate; as many coordinates as hold 90 % of the
   bank's energy); one int32 dot product per entry with the query's int8 codes reads an
   eighth of the bytes per coordinate kept (pgn_scan4.c; pgn_search.c at 8 bits);
2. the `candidates` best coarse scores are rescored exactly (float32, the full rows);
3. votes come from those candidates only; every other entry's vote counts as 0
   (`BankIndex.scores`) or as the classifier's floor exp(-80) (`IndexedSearch`).

Entries outside the candidates are far enough below the best that their votes barely
count; when one would have changed the label, the labels differ: `bench` and
`benchmarks/search_agreement.py` report how often against the full float32 search.

Enrollment: a new bank version that only appends rows or drops a class derives its index
from the previous one (`BankIndex.derive`: the basis, i.e. rotation and int8 scales, is
kept, the new rows' codes are computed alone; pgn_project.c makes a row's projection
independent of the batch), identical to a fresh build on that basis. A fresh basis is
fitted when the rows changed otherwise or drifted by `BASIS_DRIFT` since it was fitted.

Use: `IndexedSearch` is the classifier's vote for large banks (bank/classifier.py picks
it by bank size, `search='auto'`); `BankIndex.scores` gives plain vote shares like
`classifier.class_scores`, for scripts and benchmarks.
"""

from __future__ import annotations

import threading

import numpy as np
import torch

from point_gn_ros.bank.head import _LOGIT_FLOOR, _TINY
from point_gn_ros.bank.helper import helper_thread
# The coarse coordinates (re-exported: scripts and tests import them from here).
from point_gn_ros.bank.index_basis import (COARSE_BITS, COARSE_ENERGY, IndexBasis,  # noqa: F401
                                           _project)
from point_gn_ros.core import kernels
from point_gn_ros.core.encoder import spare_cpu

# Entries rescored exactly per query. 512 left up to 5 of 2,468 single-view labels
# different from the exact search on the shipped bank even at full width; 1,024 none.
CANDIDATES = 1024
# A lone query's coarse pass is split over two threads from this many entries (below it the
# hand-over costs about what the second thread saves).
SPLIT_MIN_ROWS = 20_000
# A derived index (`BankIndex.derive`: enrollments append rows, removals drop a class) keeps
# its basis until this share of the rows it was fitted on was appended or removed; then the
# next version fits a fresh one. (20 new examples on the 39k-entry scan section: 0.05 %.)
BASIS_DRIFT = 0.1


def vote_shares(sims: np.ndarray, labels: np.ndarray, num_classes: int,
                gamma: float) -> np.ndarray:
    """Kernel-vote shares like classifier.votes_from_similarity, for one query.

    sims: (M,) cosines of the entries that vote; labels: (M,) int -> (C,) float32, sums
    to 1. Evaluated in the log domain (the best entry weighs exp(0)) so large gammas
    do not underflow.
    """
    logits = (sims.astype(np.float64) - 1.0) * gamma
    w = np.exp(logits - logits.max())
    votes = np.bincount(labels, weights=w, minlength=num_classes)
    return (votes / votes.sum()).astype(np.float32)


def _check_rows(features: np.ndarray, labels: np.ndarray, num_classes: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """-> (N, d) C-contiguous float32 rows (N >= 1), (N,) int64 labels in [0, num_classes)."""
    feats = np.ascontiguousarray(features, dtype=np.float32)
    if feats.ndim != 2 or feats.shape[0] == 0:
        raise ValueError(f'features must be (N, d) with N >= 1, got {feats.shape}')
    labels = np.asarray(labels).astype(np.int64, copy=False).reshape(-1)
    if labels.shape[0] != feats.shape[0]:
        raise ValueError(f'{labels.shape[0]} labels for {feats.shape[0]} entries')
    if labels.min() < 0 or labels.max() >= num_classes:
        raise ValueError(f'labels outside [0, {num_classes})')
    return feats, labels


def _same_rows(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two (N, d) float32 arrays hold the same values (the same memory: at once)."""
    if a.shape != b.shape:
        return False
    if a.ctypes.data == b.ctypes.data and a.strides == b.strides:
        return True     # banks are copy-on-write: memory once published never changes
    return bool(np.array_equal(a, b))


class BankIndex:
    """Two-stage search over a bank's (transformed, unit-row) features.

    features: (N, d) float32 unit rows; labels: (N,) int class ids in [0, num_classes);
    coarse_dims: coordinates per entry in the coarse pass (a multiple of 32, <= d; None:
    the fewest holding `COARSE_ENERGY` of the bank's energy, so a flat spectrum, e.g. a
    whitened vote space, keeps more); candidates: entries rescored exactly per query;
    code_bits: 4 or 8 bits a coarse code (`COARSE_BITS`); basis: the coarse coordinates to
    use (another index's, see `derive`, with its code width; None: fitted on these
    features). Memory: N x coarse_dims x code_bits / 8 bytes beside the float32 features
    (kept by reference when already float32 and C-contiguous).
    """

    def __init__(self, features: np.ndarray, labels: np.ndarray, num_classes: int,
                 coarse_dims: int | None = None, candidates: int = CANDIDATES,
                 basis: IndexBasis | None = None, code_bits: int = COARSE_BITS) -> None:
        feats, labels = _check_rows(features, labels, num_classes)
        self.features, self.labels, self.num_classes = feats, labels, int(num_classes)
        self.candidates = max(1, int(candidates))
        self._lib = kernels.load()
        self._local = threading.local()
        if basis is None:
            self.basis, z = IndexBasis.fit(feats, coarse_dims, self._lib, code_bits)
            self.codes = self.basis.quantize(z)
        else:
            self.basis = basis
            self.codes = basis.encode(feats, self._lib)
        # entries appended or removed since the basis was fitted (see `derive`)
        self.changed = 0

    @property
    def rotation(self) -> np.ndarray:
        return self.basis.rotation

    @property
    def scale(self) -> np.ndarray:
        return self.basis.scale

    @property
    def coarse_energy(self) -> float:
        return self.basis.energy

    def derive(self, features: np.ndarray, labels: np.ndarray, num_classes: int,
               max_drift: float = BASIS_DRIFT) -> 'BankIndex | None':
        """The index of a next bank version built from this one, or None (build it afresh).

        features (N', d), labels (N',): the new version's rows. Derived when they are this
        index's rows with rows appended (an enrollment) or with one class's rows removed
        (later ids shift down), checked on the data; the new rows' codes are computed, the
        others reused. Identical to `BankIndex(features, labels, num_classes,
        basis=self.basis)`. None when the rows changed otherwise (a refit re-whitened them),
        without the row-exact kernel, or once more than `max_drift` x the basis's rows were
        appended or removed since it was fitted (then a fresh basis follows the bank).
        """
        feats, labels = _check_rows(features, labels, num_classes)
        n0, n1 = len(self.labels), len(labels)
        if self._lib is None or feats.shape[1] != self.features.shape[1] or \
                self.changed + abs(n1 - n0) > max_drift * self.basis.rows:
            return None
        if n1 >= n0 and num_classes >= self.num_classes:
            if not (np.array_equal(labels[:n0], self.labels)
                    and _same_rows(feats[:n0], self.features)):
                return None
            codes = np.concatenate([self.codes, self.basis.encode(feats[n0:], self._lib)])
        else:
            keep = self._removal(feats, labels, num_classes)
            if keep is None:
                return None
            codes = self.codes[keep]
        out = object.__new__(BankIndex)
        out.features, out.labels, out.num_classes = feats, labels, int(num_classes)
        out.candidates, out._lib, out._local = self.candidates, self._lib, threading.local()
        out.basis, out.codes, out.changed = self.basis, codes, self.changed + abs(n1 - n0)
        return out

    def _removal(self, feats: np.ndarray, labels: np.ndarray, num_classes: int
                 ) -> np.ndarray | None:
        """(N,) bool rows kept when `feats, labels` are these rows less one class, else None."""
        if num_classes != self.num_classes - 1:
            return None
        counts = np.bincount(self.labels, minlength=self.num_classes)
        for c in np.flatnonzero(counts == len(self.labels) - len(labels)):
            keep = self.labels != c
            kept = self.labels[keep]
            if np.array_equal(kept - (kept > c), labels) and \
                    np.array_equal(self.features[keep], feats):
                return keep
        return None

    @property
    def coarse_dims(self) -> int:
        return self.basis.dims

    @property
    def code_bits(self) -> int:
        return self.basis.bits

    def candidates_for(self, q: np.ndarray) -> np.ndarray:
        """Coarse pass for one query q (d,) float32 -> (M,) int32 entry ids, unordered."""
        return self.candidates_many(q[None])[0]

    def _query_codes(self, q: np.ndarray) -> np.ndarray:
        """Queries q (B, d) -> int8 codes (B, r), each from its own row alone.

        8 bits whatever the bank's codes: the coarse score is bank codes . query codes.
        """
        out = np.empty((q.shape[0], self.coarse_dims), np.int8)
        for b in range(q.shape[0]):
            qs = (q[b] @ self.rotation) * self.scale     # coarse score = codes @ qs
            top = float(np.abs(qs).max())
            out[b] = np.rint(qs * (127.0 / top) if top > 0 else qs).astype(np.int8)
        return out

    def candidates_many(self, q: np.ndarray) -> np.ndarray:
        """Coarse pass for queries q (B, d) float32 -> (B, M) int32 entry ids, rows unordered.

        One pass over the codes for the whole batch (pgn_scan_i4_multi / pgn_scan_i8_multi:
        integer sums, so each query's candidates are those of its own pass, in any batch).
        """
        n, m = self.codes.shape[0], min(self.candidates, self.codes.shape[0])
        q8 = self._query_codes(q)
        if self._lib is None:  # no C compiler: the same pass in numpy
            coarse = q8.astype(np.int32) @ self.basis.unpacked(self.codes).astype(np.int32).T
            order = np.argsort(-coarse, axis=1, kind='stable')[:, :m]
            return np.sort(order, axis=1).astype(np.int32)
        coarse, keys = self._scratch(len(q))
        self._coarse_pass(q8, coarse)
        idx = np.empty((len(q), m), np.int32)
        for b in range(len(q)):
            got = self._lib.pgn_top_m(coarse[b].ctypes.data, n, m, idx[b].ctypes.data,
                                      keys.ctypes.data)
            assert got == m, (got, m)   # m <= n: pgn_top_m returns exactly m
        return idx

    def _coarse_pass(self, q8: np.ndarray, coarse: np.ndarray) -> None:
        """coarse[:B] = codes . q8 (B, r) for every entry: one pass for the batch.

        A lone query against a large index scans the second half of the rows on the helper
        thread (bank/helper.py) while this one scans the first, when a CPU is to spare (as
        for a lone cloud, core/encoder.py `spare_cpu`): the pass is bound by memory, which
        two cores read faster. Integer sums: the same scores either way.
        """
        n, r, nq = self.codes.shape[0], self.coarse_dims, len(q8)
        lib = self._lib
        one, many = ((lib.pgn_scan_i4, lib.pgn_scan_i4_multi) if self.code_bits == 4 else
                     (lib.pgn_scan_i8, lib.pgn_scan_i8_multi))
        helper = helper_thread() if nq == 1 and n >= SPLIT_MIN_ROWS and spare_cpu() else None
        if helper is None:
            many(self.codes.ctypes.data, n, r, q8.ctypes.data, nq, coarse.ctypes.data)
            return
        h = n // 2
        second = helper.submit(one, self.codes[h:].ctypes.data, n - h, r, q8.ctypes.data,
                               coarse[0, h:].ctypes.data)
        one(self.codes.ctypes.data, h, r, q8.ctypes.data, coarse.ctypes.data)
        second.result()

    def _scratch(self, batch: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Per-thread (B, N) int32 scores and (N,) int64 keys, reused across queries.

        Fresh arrays of a large bank's size cost page faults on every query; they grow to
        the largest batch seen.
        """
        bufs = getattr(self._local, 'bufs', None)
        if bufs is None or bufs[0].shape[0] < batch:
            n = self.codes.shape[0]
            bufs = self._local.bufs = (np.empty((batch, n), np.int32), np.empty(n, np.int64))
        return bufs

    def _dots(self, q: np.ndarray, rows: np.ndarray | None) -> np.ndarray:
        """Exact float32 cosines of q (d,) with the given rows (all when None)."""
        if self._lib is None:
            return (self.features if rows is None else self.features[rows]) @ q
        m = self.features.shape[0] if rows is None else rows.shape[0]
        out = np.empty(m, np.float32)
        self._lib.pgn_scan_f32(self.features.ctypes.data, self.features.shape[1],
                               None if rows is None else rows.ctypes.data, m, q.ctypes.data,
                               out.ctypes.data)
        return out

    def _check(self, query: np.ndarray) -> np.ndarray:
        q = np.ascontiguousarray(np.asarray(query, dtype=np.float32))
        if q.ndim != 2 or q.shape[1] != self.features.shape[1]:
            raise ValueError(f'expected queries (B, {self.features.shape[1]}), got {q.shape}')
        return q

    def scores(self, query: np.ndarray, gamma: float) -> np.ndarray:
        """Two-stage vote shares: query (B, d) unit rows -> (B, C) float32, rows sum to 1.

        Each query is searched alone, so a result never depends on the batch.
        """
        q = self._check(query)
        out = np.empty((q.shape[0], self.num_classes), np.float32)
        for b, rows in enumerate(self.candidates_many(q) if len(q) else ()):
            out[b] = vote_shares(self._dots(q[b], rows), self.labels[rows], self.num_classes,
                                 gamma)
        return out

    def exact_scores(self, query: np.ndarray, gamma: float) -> np.ndarray:
        """Reference: every entry votes, float32 cosines. (B, d) -> (B, C) float32."""
        q = self._check(query)
        return np.stack([vote_shares(self._dots(row, None), self.labels, self.num_classes,
                                     gamma) for row in q]) if len(q) else \
            np.zeros((0, self.num_classes), np.float32)


class IndexedSearch:
    """The head's kernel vote (`head.VoteSearch`) from a BankIndex's candidates.

    Same semantics as `head.log_vote_shares` over the whole bank, evaluated on the
    candidates of each query.

    Every entry outside a query's candidates counts the floor vote exp(_LOGIT_FLOOR) of
    the best entry, exactly as an entry that far below the best does in the full search;
    classes absent from the bank get -inf. Each query is searched alone, so its result
    never depends on the batch. bank_u: (N, d) vote-space unit rows; bank_labels: (N,).
    """

    def __init__(self, bank_u: torch.Tensor, bank_labels: torch.Tensor, num_classes: int,
                 coarse_dims: int | None = None, candidates: int = CANDIDATES,
                 basis: IndexBasis | None = None, code_bits: int = COARSE_BITS) -> None:
        self._adopt(BankIndex(bank_u.detach().cpu().float().numpy(),
                              bank_labels.detach().cpu().numpy(), num_classes,
                              coarse_dims=coarse_dims, candidates=candidates, basis=basis,
                              code_bits=code_bits))
        self.derived = False

    @classmethod
    def derive(cls, previous: 'IndexedSearch', bank_u: torch.Tensor, bank_labels: torch.Tensor,
               num_classes: int) -> 'IndexedSearch':
        """The search of the next bank version, from `previous`'s where that is exact.

        From previous's index when the rows only gained rows or lost a class
        (`BankIndex.derive`: identical to a build on previous's basis), else built afresh.
        `derived` says which.
        """
        u, y = bank_u.detach().cpu().float().numpy(), bank_labels.detach().cpu().numpy()
        index = previous.index.derive(u, y, num_classes)
        if index is None:
            return cls(bank_u, bank_labels, num_classes, candidates=previous.index.candidates,
                       code_bits=previous.index.code_bits)
        out = object.__new__(cls)
        out._adopt(index)
        out.derived = True
        return out

    def _adopt(self, index: BankIndex) -> None:
        self.index, self.num_classes = index, index.num_classes
        self.counts = np.bincount(index.labels, minlength=self.num_classes)   # (C,)
        self.absent = self.counts == 0

    def log_votes(self, u: torch.Tensor, gamma: float) -> tuple[torch.Tensor, torch.Tensor]:
        """u: (B, d) vote-space unit rows -> log vote shares (B, C), best cosine (B,)."""
        q = self.index._check(u.detach().cpu().float().numpy())
        c, floor, nq = self.num_classes, float(np.exp(_LOGIT_FLOOR)), q.shape[0]
        if nq == 0:
            return torch.zeros(0, c).to(u.device), torch.zeros(0).to(u.device)
        rows = self.index.candidates_many(q)                             # (B, M)
        sims = np.stack([self.index._dots(q[b], rows[b]) for b in range(nq)])   # float32
        lab = self.index.labels[rows]                                    # (B, M)
        best = sims.max(axis=1)
        w = np.exp(np.maximum((sims.astype(np.float64) - best[:, None]) * gamma, _LOGIT_FLOOR))
        # one bincount over (query, class) bins: each query's sums in its own entries' order
        flat = (lab + c * np.arange(nq)[:, None]).ravel()
        votes = np.bincount(flat, weights=w.ravel(), minlength=nq * c).reshape(nq, c)
        seen = np.bincount(flat, minlength=nq * c).reshape(nq, c)
        votes += (self.counts - seen) * floor                            # the others
        logv = np.log(np.maximum(votes, _TINY))
        logv[:, self.absent] = -np.inf
        logv -= np.logaddexp.reduce(logv, axis=1, keepdims=True) if c else 0.0
        return (torch.from_numpy(logv.astype(np.float32)).to(u.device),
                torch.from_numpy(best).to(u.device))
