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
   eighth of the bytes per coordinate kept (pgn_scan_i4.c; pgn_search.c at 8 bits);
2. the `candidates` best coarse scores are rescored exactly (float32, the full rows);
3. votes come from those candidates only; every other entry's vote counts as the vote's
   floor exp(LOGIT_FLOOR) of the best entry (bank/vote.py `CompiledHead.finish`).

Entries outside the candidates are far enough below the best that their votes barely
count; when one would have changed the label, the labels differ: `bench` and
`benchmarks/search_agreement.py` report how often against the full float32 search.

Enrollment: a new bank version that only appends rows or drops a class derives its index
from the previous one (`BankIndex.derive`: the basis, i.e. rotation and int8 scales, is
kept, the new rows' codes are computed alone; pgn_project.c makes a row's projection
independent of the batch), identical to a fresh build on that basis. A fresh basis is
fitted when the rows changed otherwise or drifted by `BASIS_DRIFT` since it was fitted.

`IndexedSearch` is the classifier's vote search for large banks (bank/classifier.py picks
it by bank size, search='auto'); `CompiledHead` (bank/vote.py) finishes its candidates.
"""

from __future__ import annotations

from collections.abc import Iterator
import threading
from typing import Any

import numpy as np
import torch

from point_gn_ros.bank.vote import helper_thread
from point_gn_ros.core import kernels
from point_gn_ros.core.encoder import spare_cpu

# ---- the coarse coordinates: principal axes and integer scales
# IndexBasis rotates vote-space rows onto the bank's leading principal axes (an orthogonal
# rotation: dot products unchanged) and keeps the leading coordinates as 4-bit (packed two a
# byte, `pack_codes`) or 8-bit integer codes; `_project` computes each row's coordinates
# independently of the rows beside it (pgn_project.c), so an index's appended codes equal a
# fresh build's.

# Default coarse width: the fewest coordinates (a multiple of 32) holding this share of the
# bank's energy (512 of 640 for the shipped, whitened, bank).
COARSE_ENERGY = 0.9
# Bits a coarse code: 4 (codes in [-7, 7], half the bytes of 8) or 8 ([-127, 127]). On the
# shipped scan section 4 bits keep 8 bits' labels against the exact search
# (benchmarks/search_agreement.py) at about half the coarse pass's time.
COARSE_BITS = 4
_CODE_TOP = {4: 7, 8: 127}      # bits -> the largest |code|
# Rows used to find the principal axes (a sample: the rotation only steers the coarse
# pass, the rescoring is exact whatever it is).
_PCA_ROWS = 20_000
# Rows per block when quantizing or encoding many rows (bounds the float temporaries).
_BLOCK_ROWS = 8192


class IndexBasis:
    """The coarse pass's coordinates: the bank's leading principal axes, integer scales.

    rotation (d, r) float32 orthonormal columns; scale (r,) float32 per coordinate (a
    coordinate's largest |value| over the rows it was fitted on maps to the largest code,
    7 or 127); energy: share of those rows' squared norms on the r coordinates; rows: how
    many rows it was fitted on; bits: 4 or 8 a code.
    """

    def __init__(self, rotation: np.ndarray, scale: np.ndarray, energy: float, rows: int,
                 bits: int = COARSE_BITS) -> None:
        if bits not in _CODE_TOP:
            raise ValueError(f'coarse codes have 4 or 8 bits, got {bits}')
        self.rotation, self.scale, self.energy, self.rows = rotation, scale, energy, rows
        self.bits = bits

    @classmethod
    def fit(cls, feats: np.ndarray, coarse_dims: int | None, lib: Any,
            bits: int = COARSE_BITS) -> tuple['IndexBasis', np.ndarray]:
        """Fit on feats (N, d) float32 -> (basis, the rows' coordinates (N, r) float32)."""
        n, d = feats.shape
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
        rotation = evecs[:, order].float().contiguous().numpy()          # (d, r)
        # share of the bank's squared norms on the coarse coordinates: the closer to 1,
        # the better the coarse pass ranks
        energy = float(evals[order].sum() / evals.sum().clamp_min(1e-30))
        z = _project(feats, rotation, lib)
        # The largest |value| by blocks of rows: no second (N, r) float32 temporary.
        top = np.zeros(r, np.float32)
        for i in range(0, n, _BLOCK_ROWS):
            np.maximum(top, np.abs(z[i:i + _BLOCK_ROWS]).max(axis=0), out=top)
        scale = np.maximum(top, 1e-12) / _CODE_TOP[bits]                     # (r,)
        return cls(rotation, scale, energy, n, bits), z

    @property
    def dims(self) -> int:
        return int(self.rotation.shape[1])

    def quantize(self, z: np.ndarray) -> np.ndarray:
        """Coordinates (M, r) float32 -> stored codes, saturated at the largest code.

        (M, r) int8 at 8 bits, (M, r / 2) uint8 (`pack_codes`) at 4. In blocks of rows: a
        large bank's float temporaries stay small.
        """
        top, r = _CODE_TOP[self.bits], z.shape[1]
        out = np.empty((len(z), r if self.bits == 8 else r // 2), np.int8 if self.bits == 8
                       else np.uint8)
        for i in range(0, len(z), _BLOCK_ROWS):
            blk = z[i:i + _BLOCK_ROWS] / self.scale
            np.rint(blk, out=blk)
            codes = np.clip(blk, -top, top, out=blk).astype(np.int8)
            out[i:i + _BLOCK_ROWS] = pack_codes(codes) if self.bits == 4 else codes
        return out

    def unpacked(self, codes: np.ndarray) -> np.ndarray:
        """Stored codes -> (M, r) int8 code values (no copy at 8 bits)."""
        return unpack_codes(codes, self.dims) if self.bits == 4 else codes

    def encode(self, feats: np.ndarray, lib: Any) -> np.ndarray:
        """Rows (M, d) float32 -> stored codes (see quantize); the same rows in any batch."""
        if len(feats) <= _BLOCK_ROWS:
            return self.quantize(_project(feats, self.rotation, lib))
        return np.concatenate([self.encode(feats[i:i + _BLOCK_ROWS], lib)
                               for i in range(0, len(feats), _BLOCK_ROWS)])


# Packed 4-bit rows, in chunks of up to 64 bytes: in a chunk of L bytes starting at byte
# b, byte b + t holds code 2b + t in its low 4 bits and code 2b + L + t in its high ones, each
# + 8. So a chunk's two halves meet contiguous slices of the query (pgn_scan_i4.c).
_PACK_CHUNK = 64


def pack_codes(codes: np.ndarray) -> np.ndarray:
    """(M, r) int8 codes in [-8, 7], r a multiple of 32 -> (M, r / 2) uint8 packed rows."""
    m, r = codes.shape
    if r % 32:
        raise ValueError(f'4-bit codes need a multiple of 32 a row, got {r}')
    u = (codes.astype(np.int16) + 8).astype(np.uint8)
    out, p = np.empty((m, r // 2), np.uint8), r // 2
    for b in range(0, p, _PACK_CHUNK):
        n = min(_PACK_CHUNK, p - b)
        out[:, b:b + n] = u[:, 2 * b:2 * b + n] | (u[:, 2 * b + n:2 * b + 2 * n] << 4)
    return out


def unpack_codes(packed: np.ndarray, dims: int) -> np.ndarray:
    """pack_codes's inverse: (M, dims / 2) uint8 -> (M, dims) int8."""
    out, p = np.empty((packed.shape[0], dims), np.int8), dims // 2
    for b in range(0, p, _PACK_CHUNK):
        n = min(_PACK_CHUNK, p - b)
        out[:, 2 * b:2 * b + n] = (packed[:, b:b + n] & 15).astype(np.int8) - 8
        out[:, 2 * b + n:2 * b + 2 * n] = (packed[:, b:b + n] >> 4).astype(np.int8) - 8
    return out


def _project(feats: np.ndarray, rotation: np.ndarray, lib: Any) -> np.ndarray:
    """Rows feats (N, d) @ rotation (d, r) -> (N, r) float32.

    With the C kernels each row's result does not depend on the others (pgn_project.c), so
    an index's appended codes equal a fresh build's; torch's GEMM otherwise.
    """
    if lib is None:
        return (torch.from_numpy(feats) @ torch.from_numpy(rotation)).numpy()
    feats = np.ascontiguousarray(feats, dtype=np.float32)
    out = np.empty((feats.shape[0], rotation.shape[1]), np.float32)
    lib.pgn_project_f32(feats.ctypes.data, feats.shape[0], feats.shape[1],
                        rotation.ctypes.data, rotation.shape[1], out.ctypes.data)
    return out


# ---- the two-stage index

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
        self.compiled = self._lib is not None
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
        out.compiled = self.compiled
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
        thread (bank/vote.py `helper_thread`) while this one scans the first, when a CPU is
        to spare (as for a lone cloud, core/encoder.py `spare_cpu`): the pass is bound by
        memory, which two cores read faster. Integer sums: the same scores either way.
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

    def dots(self, q: np.ndarray, rows: np.ndarray | None) -> np.ndarray:
        """Exact float32 cosines of q (d,) with the given rows (all when None)."""
        if self._lib is None:
            return (self.features if rows is None else self.features[rows]) @ q
        m = self.features.shape[0] if rows is None else rows.shape[0]
        out = np.empty(m, np.float32)
        self._lib.pgn_scan_f32(self.features.ctypes.data, self.features.shape[1],
                               None if rows is None else rows.ctypes.data, m, q.ctypes.data,
                               out.ctypes.data)
        return out

    def check(self, query: np.ndarray) -> np.ndarray:
        q = np.ascontiguousarray(np.asarray(query, dtype=np.float32))
        if q.ndim != 2 or q.shape[1] != self.features.shape[1]:
            raise ValueError(f'expected queries (B, {self.features.shape[1]}), got {q.shape}')
        return q


class IndexedSearch:
    """The vote's cosines (bank/vote.py `VoteSearch`) from a BankIndex's candidates.

    Every entry outside a query's candidates counts the floor vote exp(LOGIT_FLOOR) of
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

    @property
    def compiled(self) -> bool:
        """Whether the index's scans are compiled (the compiled head needs them)."""
        return self.index.compiled

    @property
    def label_array(self) -> np.ndarray:
        return self.index.labels

    def lone_cosines(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """u: (d,) -> exact cosines (M,) of its candidates, their labels (M,)."""
        rows = self.index.candidates_many(u[None])[0]
        return self.index.dots(u, rows), np.ascontiguousarray(self.index.labels[rows])

    def batch_cosines(self, u: torch.Tensor) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """u: (B, d) -> per row, its candidates' cosines and labels (as `lone_cosines`)."""
        q = self.index.check(u.detach().cpu().float().numpy())
        if not len(q):
            return
        for b, rows in enumerate(self.index.candidates_many(q)):
            yield self.index.dots(q[b], rows), np.ascontiguousarray(self.index.labels[rows])
