"""Two-stage search for large banks: an int8 coarse scan, then exact rescoring.

The kernel vote of a query, sum over entries of exp(-gamma (1 - cos)) per class, is
dominated by the nearest entries at the gammas the banks use (40-200): an entry 0.1
below the best cosine weighs e^-4 (gamma 40) to e^-20 (gamma 200) of it. A lone query
against a float32 bank must read the whole bank (100k x 512 x 4 B = 205 MB: ~7 ms at
this core's ~28 GB/s). Instead:

1. coarse pass: the bank rotated onto its principal axes (an orthogonal rotation, so
   dot products are unchanged), the leading `coarse_dims` coordinates kept as int8 (a
   scale per coordinate; as many as hold 90 % of the bank's energy); one int32 dot
   product per entry reads a quarter of the bytes per coordinate kept;
2. the `candidates` best coarse scores are rescored exactly (float32, the full rows);
3. votes come from those candidates only; every other entry's vote counts as 0
   (`BankIndex.scores`) or as the classifier's floor exp(-80) (`IndexedSearch`).

Entries outside the candidates are far enough below the best that their votes barely
count; when one would have changed the label, the labels differ: `bench` and
`scripts/search_agreement.py` report how often against the full float32 search.

Use: `IndexedSearch` is the classifier's vote for large banks (bank/classifier.py picks
it by bank size, `search='auto'`); `BankIndex.scores` gives plain vote shares like
`classifier.class_scores`, for scripts and benchmarks.
"""

from __future__ import annotations

import threading

import numpy as np
import torch

from point_gn_ros.bank.head import _LOGIT_FLOOR, _TINY
from point_gn_ros.core import kernels

# Default coarse width: the fewest coordinates (a multiple of 32) holding this share of the
# bank's energy: 128 of 512 for issue 13's synthetic bank, 192 of 224 for the whitened
# sensor bank, 512 of 640 for the shipped (whitened) one (BENCHMARKS.md "Large banks").
COARSE_ENERGY = 0.9
# Entries rescored exactly per query. 512 left up to 5 of 2,468 single-view labels
# different from the exact search on the shipped bank even at full width; 1,024 none.
CANDIDATES = 1024
# Rows used to find the principal axes (a sample: the rotation only steers the coarse
# pass, the rescoring is exact whatever it is).
_PCA_ROWS = 20_000


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


class BankIndex:
    """Two-stage search over a bank's (transformed, unit-row) features.

    features: (N, d) float32 unit rows; labels: (N,) int class ids in [0, num_classes);
    coarse_dims: int8 coordinates per entry in the coarse pass (a multiple of 32, <= d;
    None: the fewest holding `COARSE_ENERGY` of the bank's energy, so a flat spectrum, e.g.
    a whitened vote space, keeps more); candidates: entries rescored exactly per query.
    Memory: N x coarse_dims bytes beside the float32 features (kept by reference when
    already float32 and C-contiguous).
    """

    def __init__(self, features: np.ndarray, labels: np.ndarray, num_classes: int,
                 coarse_dims: int | None = None, candidates: int = CANDIDATES) -> None:
        feats = np.ascontiguousarray(features, dtype=np.float32)
        if feats.ndim != 2 or feats.shape[0] == 0:
            raise ValueError(f'features must be (N, d) with N >= 1, got {feats.shape}')
        n, d = feats.shape
        labels = np.asarray(labels).astype(np.int64, copy=False).reshape(-1)
        if labels.shape[0] != n:
            raise ValueError(f'{labels.shape[0]} labels for {n} entries')
        if labels.min() < 0 or labels.max() >= num_classes:
            raise ValueError(f'labels outside [0, {num_classes})')
        self.features, self.labels, self.num_classes = feats, labels, int(num_classes)
        self.candidates = max(1, int(candidates))
        self._lib = kernels.load()
        self._local = threading.local()
        # Principal axes of the (uncentred) second moment: they carry the most of every
        # dot product, so the leading coordinates approximate the cosines best.
        # In torch, on its thread budget (the node's torch_threads): numpy's BLAS threads
        # spin-wait on a loaded machine, which made a build cost several times its work.
        sample = torch.from_numpy(feats[::max(1, n // _PCA_ROWS)])
        evals, evecs = torch.linalg.eigh((sample.T @ sample).double())
        evals, evecs = evals.flip(0).clamp_min(0.0), evecs.flip(1)      # descending
        if coarse_dims is None:
            share = (evals.cumsum(0) / evals.sum().clamp_min(1e-30)).numpy()
            coarse_dims = 32 * (int(np.searchsorted(share, COARSE_ENERGY - 1e-9)) // 32 + 1)
        r = min(d, max(32, coarse_dims // 32 * 32))
        order = torch.arange(r)
        self.rotation = evecs[:, order].float().contiguous().numpy()     # (d, r)
        # share of the bank's squared norms on the coarse coordinates: the closer to 1,
        # the better the coarse pass ranks (issue 13's 512-d bank, 128 coords: 0.93)
        self.coarse_energy = float(evals[order].sum() / evals.sum().clamp_min(1e-30))
        z = (torch.from_numpy(feats) @ torch.from_numpy(self.rotation)).numpy()  # (N, r)
        self.scale = np.maximum(np.abs(z).max(axis=0), 1e-12) / 127.0     # (r,)
        self.codes = np.ascontiguousarray(np.rint(z / self.scale), dtype=np.int8)

    @property
    def coarse_dims(self) -> int:
        return int(self.codes.shape[1])

    def candidates_for(self, q: np.ndarray) -> np.ndarray:
        """Coarse pass for one query q (d,) float32 -> (M,) int32 entry ids, unordered."""
        n, m = self.codes.shape[0], min(self.candidates, self.codes.shape[0])
        qs = (q @ self.rotation) * self.scale            # coarse score = codes @ qs
        top = float(np.abs(qs).max())
        q8 = np.rint(qs * (127.0 / top) if top > 0 else qs).astype(np.int8)
        if self._lib is None:  # no C compiler: the same pass in numpy
            coarse = self.codes.astype(np.int32) @ q8.astype(np.int32)
            return np.sort(np.argsort(-coarse, kind='stable')[:m]).astype(np.int32)
        coarse, keys = self._scratch()
        self._lib.pgn_scan_i8(self.codes.ctypes.data, n, self.coarse_dims, q8.ctypes.data,
                              coarse.ctypes.data)
        idx = np.empty(m, np.int32)
        got = self._lib.pgn_top_m(coarse.ctypes.data, n, m, idx.ctypes.data, keys.ctypes.data)
        return idx[:got]

    def _scratch(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-thread (N,) int32 scores and (N,) int64 keys, reused across queries.

        Fresh arrays of a large bank's size cost page faults on every query.
        """
        bufs = getattr(self._local, 'bufs', None)
        if bufs is None:
            n = self.codes.shape[0]
            bufs = self._local.bufs = (np.empty(n, np.int32), np.empty(n, np.int64))
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
        for b in range(q.shape[0]):
            rows = self.candidates_for(q[b])
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
                 coarse_dims: int | None = None, candidates: int = CANDIDATES) -> None:
        self.num_classes = int(num_classes)
        self.index = BankIndex(bank_u.detach().cpu().float().numpy(),
                               bank_labels.detach().cpu().numpy(), num_classes,
                               coarse_dims=coarse_dims, candidates=candidates)
        self.counts = np.bincount(self.index.labels, minlength=self.num_classes)   # (C,)
        self.absent = self.counts == 0

    def log_votes(self, u: torch.Tensor, gamma: float) -> tuple[torch.Tensor, torch.Tensor]:
        """u: (B, d) vote-space unit rows -> log vote shares (B, C), best cosine (B,)."""
        q = self.index._check(u.detach().cpu().float().numpy())
        c, floor = self.num_classes, float(np.exp(_LOGIT_FLOOR))
        logv = np.empty((q.shape[0], c), np.float64)
        best = np.empty(q.shape[0], np.float32)
        for b in range(q.shape[0]):
            rows = self.index.candidates_for(q[b])
            sims = self.index._dots(q[b], rows)                          # (M,) float32
            lab = self.index.labels[rows]
            best[b] = sims.max()
            w = np.exp(np.maximum((sims.astype(np.float64) - best[b]) * gamma, _LOGIT_FLOOR))
            votes = np.bincount(lab, weights=w, minlength=c)
            votes += (self.counts - np.bincount(lab, minlength=c)) * floor  # the others
            logv[b] = np.log(np.maximum(votes, _TINY))
        logv[:, self.absent] = -np.inf
        logv -= np.logaddexp.reduce(logv, axis=1, keepdims=True) if c else 0.0
        return (torch.from_numpy(logv.astype(np.float32)).to(u.device),
                torch.from_numpy(best).to(u.device))
