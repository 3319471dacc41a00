"""The kernel vote: where a query's cosines come from, and the head that finishes them.

Product path: the compiled head (core/kernels/pgn_head.c, `CompiledHead`). Per query it
reads the cosines of the rows that vote (every entry for `ExactSearch`, the candidates of
bank/index.py's `IndexedSearch`) and computes the head's fused, calibrated probabilities and
novelty in one C call: the kernel vote (log domain, each entry floored at exp(LOGIT_FLOOR)
of the best, entries outside the candidates counted at that floor), the kernel ridge term,
the LDA and the temperature. A lone query is embedded in C as well; a batch is embedded in
torch and each of its rows finished in C.

Reference: `reference_head` with `log_vote_shares`, the same formulas in torch. The
tests hold the compiled head to it (probabilities within ~1e-6, the same labels); the
classifier runs it where the compiled head does not apply (no kernels, another device).

Invariant: a query's result does not depend on the batch it came in (each row's cosines are
the same bit for bit in any batch, and each row is finished alone).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
import ctypes
import math
import os
import threading
from collections.abc import Iterator
from typing import Any, Protocol

import numpy as np
import torch

from point_gn_ros.bank.model import _TINY, LOGIT_FLOOR, FeatureTransform, Gate, Head
from point_gn_ros.core import kernels
from point_gn_ros.core.encoder import default_threads
from point_gn_ros.core.threads import name_os_thread

# Upper bound on queries x bank entries held at once (float32 similarity block).
MAX_BLOCK = 1 << 24


# ---- the torch reference head

def reference_head(head: Head, z: torch.Tensor, search: 'VoteSearch',
                   x: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The head in torch (the reference the compiled head is held to).

    z: (B, d) transformed queries; search: where the vote's cosines come from (an
    `ExactSearch` for a ridge head); x: (B, D) standardised rows
    (`FeatureTransform.standardized`), read by a wide LDA. -> probability (B, C) float32
    (rows sum to 1), novelty (B,) float32.
    """
    if z.shape[0] == 0:
        return torch.zeros(0, search.num_classes), torch.zeros(0)
    u = head.vote_space(z)
    if head.has_ridge:
        if not isinstance(search, ExactSearch):
            raise ValueError('a kernel ridge head needs the exact search')
        fused, best, ridge = search.ridge_log_votes(u, head.gamma, head.ridge_coef,
                                                    head.ridge_gamma)
        fused = fused + head.ridge_weight * ridge
    else:
        fused, best = search.log_votes(u, head.gamma)
    if head.lda_wide and x is None:
        raise ValueError('a wide-LDA head needs the standardised rows x')
    lda = head.lda_log_probs(x if head.lda_wide else z)
    if lda is not None:
        fused = fused + head.fusion_weight * lda
    prob = torch.softmax(fused / head.temperature, dim=1)
    return prob, (1.0 - best).clamp_min(0.0)


def log_vote_shares(sims: torch.Tensor, bank_labels: torch.Tensor, num_classes: int,
                    gamma: float) -> torch.Tensor:
    """Log kernel-vote share of each class (the reference vote).

    sims: (B, N) cosine to each bank entry; bank_labels: (N,) int64 -> (B, C) float32,
    logsumexp over classes = 0. Each entry counts at least exp(LOGIT_FLOOR) of the best
    entry's vote (no float32 denormals); a class absent from the bank gets -inf.
    """
    logits = (sims - 1.0) * gamma
    top = logits.max(dim=1, keepdim=True).values
    votes = torch.zeros(sims.shape[0], num_classes, dtype=logits.dtype, device=logits.device)
    votes.index_add_(1, bank_labels, (logits - top).clamp_min_(LOGIT_FLOOR).exp_())
    present = torch.zeros(num_classes, dtype=torch.bool, device=sims.device)
    present[bank_labels] = True
    logv = votes.clamp_min(_TINY).log().masked_fill(~present, -float('inf'))
    return logv - torch.logsumexp(logv, dim=1, keepdim=True)


def ridge_scores(sims: torch.Tensor, coef: torch.Tensor, gamma: float) -> torch.Tensor:
    """sims: (B, N) cosines to the bank rows; coef: (N, C) -> (B, C) float32 ridge scores.

    The sum runs in float64: coefficients reach ~100 with cancelling signs. Pass coef as
    float64 to skip a per-call copy (Head.to does).
    """
    return (torch.exp(gamma * (sims.double() - 1.0)) @ coef.double()).float()


# ---- the exact search

class VoteSearch(Protocol):
    """Where the kernel vote's cosines come from.

    `ExactSearch` here, bank/index.py's `IndexedSearch`.

    compiled: whether its cosines come from compiled scans (what `CompiledHead` reads);
    label_array: (N,) int64 labels of the bank's rows.
    """

    num_classes: int
    compiled: bool
    label_array: np.ndarray

    def log_votes(self, u: torch.Tensor, gamma: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Vote of u: (B, d) vote-space unit rows -> log shares (B, C), best cosine (B,).

        The log shares follow `log_vote_shares` (floor per entry, -inf for absent classes).
        """
        ...

    def lone_cosines(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """u: (d,) vote-space query -> cosines (M,) float32 of the rows that vote, labels (M,)."""
        ...

    def batch_cosines(self, u: torch.Tensor) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """u: (B, d) -> per row, as `lone_cosines` (the same values bit for bit)."""
        ...


class ExactSearch:
    """Every bank entry votes: one (B, N) similarity block per group of queries.

    bank_u: (N, d) vote-space rows; bank_labels: (N,) int64. On the CPU the cosines come
    from the compiled scan (core/kernels/pgn_dots.c: the bank read once per batch, a query's
    cosines the same bit for bit in any batch; a BLAS GEMM reads a lone query's bank at a
    fraction of the bandwidth), from the int8 codes of a bank stored as int8 / int4 (rows =
    codes / ||codes||: a quarter of the bytes); elsewhere, or without a C compiler, torch.
    """

    def __init__(self, bank_u: torch.Tensor, bank_labels: torch.Tensor, num_classes: int
                 ) -> None:
        self.bank_u, self.bank_labels, self.num_classes = bank_u, bank_labels, int(num_classes)
        self._rows = _kernel_rows(bank_u)
        self.compiled = self._rows is not None
        self.label_array = np.ascontiguousarray(bank_labels.cpu().numpy(), dtype=np.int64)
        self._packed = None
        if self._rows is not None:
            rows, norms = self._rows
            # int4 codes (every value in [-8, 7]) scanned from nibbles: half the bytes
            if (norms is not None and rows.shape[1] % 16 == 0
                    and -8 <= rows.min() and rows.max() <= 7):
                self._packed = kernels.pack_nibbles(rows)

    @property
    def scans_codes(self) -> bool:
        """Whether the compiled scan reads int8 codes (else float32 rows or torch)."""
        return self._rows is not None and self._rows[1] is not None

    def similarities(self, q: torch.Tensor) -> torch.Tensor:
        """q: (B, d) vote-space rows -> (B, N) cosines to every bank entry."""
        if self._rows is None or q.device.type != 'cpu':
            return q @ self.bank_u.T
        rows, norms = self._rows
        return torch.from_numpy(kernels.bank_dots(rows, q.detach().float().numpy(), norms))

    def lone_cosines(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rows, norms = self._rows
        if self._packed is not None:
            return kernels.packed_dots_i4(self._packed, norms, u), self.label_array
        return kernels.bank_dots(rows, u[None], norms)[0], self.label_array

    def batch_cosines(self, u: torch.Tensor) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        step = max(1, MAX_BLOCK // max(1, self.bank_u.shape[0]))
        for q in u.split(step):
            for row in self.similarities(q).numpy():
                yield row, self.label_array

    def log_votes(self, u: torch.Tensor, gamma: float) -> tuple[torch.Tensor, torch.Tensor]:
        logv, best, _ = self.ridge_log_votes(u, gamma)
        return logv, best

    def ridge_log_votes(self, u: torch.Tensor, gamma: float, coef: torch.Tensor | None = None,
                        ridge_gamma: float = 0.0
                        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """`log_votes`, and the kernel ridge scores from the same cosines.

        coef: (N, C) ridge coefficients (bank/discriminant.py) -> third output (B, C); None: None.
        """
        step = max(1, MAX_BLOCK // max(1, self.bank_u.shape[0]))
        logv, best, ridge = [], [], []
        for q in u.split(step):
            sims = self.similarities(q)
            logv.append(log_vote_shares(sims, self.bank_labels, self.num_classes, gamma))
            best.append(sims.max(dim=1).values)
            if coef is not None:
                ridge.append(ridge_scores(sims, coef, ridge_gamma))
        return torch.cat(logv), torch.cat(best), torch.cat(ridge) if ridge else None


def _kernel_rows(bank_u: torch.Tensor) -> tuple[np.ndarray, np.ndarray | None] | None:
    """What the compiled scan reads for bank_u: (int8 codes, norms) or (float32 rows, None).

    Codes when every row is exactly normalize(codes) for int8 codes (a bank stored as int8
    or int4, bank/store.py); float32 rows otherwise (no copy when bank_u already is such
    rows). None off the CPU, without kernels, or for an empty bank.
    """
    if bank_u.device.type != 'cpu' or bank_u.ndim != 2 or bank_u.shape[0] == 0:
        return None
    if kernels.load() is None:
        return None
    rows = np.ascontiguousarray(bank_u.detach().numpy(), dtype=np.float32)
    codes = _stored_codes(rows)
    return (rows, None) if codes is None else codes


def _stored_codes(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(N, d) int8 codes and (N,) float32 norms with rows == normalize(codes), else None.

    An int4 / int8 row's largest coordinate is stored as +-7 / +-127 (bank/store.py), so its
    codes are rint(row x 7 / peak) or rint(row x 127 / peak); checked exactly, with the
    normalisation a loaded bank's rows come from (bank_file.from_stored).
    """
    peak = np.abs(rows).max(axis=1)
    if not (peak > 0).all():
        return None
    for top in (7.0, 127.0):
        codes = np.rint(rows * (np.float32(top) / peak)[:, None])
        c = torch.from_numpy(codes)
        if torch.equal(torch.nn.functional.normalize(c, dim=1), torch.from_numpy(rows)):
            norms = torch.linalg.vector_norm(c, dim=1).numpy()
            return np.ascontiguousarray(codes.astype(np.int8)), np.ascontiguousarray(norms)
    return None


# ---- the compiled head

def _f32(t: torch.Tensor | None) -> np.ndarray | None:
    """A C-contiguous float32 numpy array of t (no copy when t already is one), or None."""
    if t is None:
        return None
    return np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float32)


def _ptr(a: np.ndarray | None) -> int | None:
    return None if a is None else a.ctypes.data


class _Embedding:
    """x (D) raw -> standardised xs (D), transformed z (d), vote-space u (d) (pgn_head_embed)."""

    def __init__(self, lib: ctypes.CDLL, transform: Any, whiten: torch.Tensor | None) -> None:
        self.lib = lib
        self.mean, self.scale = _f32(transform.mean), _f32(transform.scale)
        self.proj, self.whiten = _f32(transform.projection), _f32(whiten)
        self.in_dim = int(self.mean.shape[0])
        self.out_dim = self.in_dim if self.proj is None else int(self.proj.shape[1])

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        xs = np.empty(self.in_dim, np.float32)
        z, u = np.empty(self.out_dim, np.float32), np.empty(self.out_dim, np.float32)
        self.lib.pgn_head_embed(x.ctypes.data, self.in_dim, self.mean.ctypes.data,
                                self.scale.ctypes.data, _ptr(self.proj), self.out_dim,
                                _ptr(self.whiten), xs.ctypes.data, z.ctypes.data, u.ctypes.data)
        return xs, z, u


class CompiledHead:
    """One section's head (transform, head, the rows that vote) in compiled code.

    `finish` ends every path in pgn_head_finish: a query's cosines (every entry's, or its
    candidates' with their labels) -> probability (C,), novelty. `evaluate` is a lone query
    from its raw features (embedded in C too); `finish_rows` a batch's rows after their
    search. Built by `CompiledHead.build`, which returns None where it does not apply.
    """

    def __init__(self, lib: ctypes.CDLL, transform: FeatureTransform, head: Head,
                 num_classes: int, search: 'ExactSearch | Any', ridge: np.ndarray | None
                 ) -> None:
        self.lib, self.embed = lib, _Embedding(lib, transform, head.whiten)
        self.num_classes = int(num_classes)
        self.gamma, self.temperature = float(head.gamma), float(head.temperature)
        self.ridge = ridge
        self.ridge_gamma, self.ridge_weight = float(head.ridge_gamma), float(head.ridge_weight)
        use_lda = head.lda_coef is not None and head.fusion_weight != 0
        self.lda_coef = _f32(head.lda_coef) if use_lda else None
        self.lda_bias = _f32(head.lda_bias) if use_lda else None
        self.lda_wide, self.fusion_weight = bool(head.lda_wide), float(head.fusion_weight)
        self.search = search
        self.labels = search.label_array
        self.counts = np.bincount(self.labels, minlength=self.num_classes).astype(np.int64)

    @classmethod
    def build(cls, transform: FeatureTransform, head: Head, num_classes: int,
              search: 'VoteSearch') -> 'CompiledHead | None':
        """The compiled head of a section, or None where it does not apply.

        It does not apply without kernels, without entries, to a search without compiled
        cosines, or to a ridge head whose coefficients are not float32 values (the C head
        reads them as float32).
        """
        lib = kernels.load()
        if lib is None or not search.compiled:
            return None
        ridge = None
        if head.has_ridge:
            if not isinstance(search, ExactSearch):
                return None
            coef = head.ridge_coef.detach().cpu()
            ridge = np.ascontiguousarray(coef.numpy(), dtype=np.float32)
            # float32 values read as float32 (half the bytes), summed in double as torch does
            if not np.array_equal(ridge.astype(coef.numpy().dtype), coef.numpy()):
                return None
        return cls(lib, transform, head, num_classes, search, ridge)

    def evaluate(self, x: np.ndarray) -> tuple[np.ndarray, float]:
        """x: (D,) float32 raw features -> probability (C,) float32, novelty."""
        xs, z, u = self.embed(x)
        sims, labels = self.search.lone_cosines(u)
        prob, novelty = np.empty(self.num_classes, np.float32), np.empty(1, np.float32)
        self.finish(sims, labels, xs if self.lda_wide else z, prob, novelty)
        return prob, float(novelty[0])

    def finish_rows(self, u: torch.Tensor, lda_in: torch.Tensor
                    ) -> tuple[np.ndarray, np.ndarray]:
        """A batch: u (B, d) vote-space rows -> probability (B, C), novelty (B,).

        lda_in (B, d'): the LDA's input rows (standardised for a wide LDA, else transformed).

        Each row's cosines from the search, then finished as `evaluate` finishes a lone query.
        """
        lda_in = np.ascontiguousarray(lda_in.detach().cpu().numpy(), dtype=np.float32)
        prob = np.empty((len(lda_in), self.num_classes), np.float32)
        novelty = np.empty(len(lda_in), np.float32)
        for b, (sims, labels) in enumerate(self.search.batch_cosines(u)):
            self.finish(sims, labels, lda_in[b], prob[b], novelty[b:b + 1])
        return prob, novelty

    def finish(self, sims: np.ndarray, labels: np.ndarray, lda_in: np.ndarray,
               prob: np.ndarray, novelty: np.ndarray) -> None:
        """pgn_head_finish of one query: cosines sims (M,) -> prob (C,), novelty (1,).

        labels (M,): the voting rows' classes; the bank's other entries vote at the floor.
        """
        c = self.num_classes
        sims = np.ascontiguousarray(sims, dtype=np.float32)
        work = np.empty(5 * c, np.float64)
        self.lib.pgn_head_finish(
            sims.ctypes.data, labels.ctypes.data, len(sims), c, self.counts.ctypes.data,
            self.gamma, _ptr(self.ridge), self.ridge_gamma, self.ridge_weight,
            lda_in.ctypes.data, len(lda_in), _ptr(self.lda_coef),
            _ptr(self.lda_bias), self.fusion_weight, self.temperature, work.ctypes.data,
            prob.ctypes.data, novelty.ctypes.data)


class CompiledGate:
    """The gate's p(scan) of one query (bank/model.py `Gate`) in compiled code."""

    def __init__(self, lib: ctypes.CDLL, gate: Gate) -> None:
        self.lib, self.embed = lib, _Embedding(lib, gate.transform, None)
        self.coef, self.bias = _f32(gate.coef), _f32(gate.bias)

    def __call__(self, x: np.ndarray) -> float:
        """x: (D,) float32 raw features -> probability that it is a single-view scan."""
        _, z, _ = self.embed(x)
        logits = np.empty(2, np.float64)
        self.lib.pgn_head_linear(z.ctypes.data, len(z), self.coef.ctypes.data, 2,
                                 self.bias.ctypes.data, logits.ctypes.data)
        d = float(logits[0] - logits[1])
        return 0.0 if d > 700.0 else 1.0 / (1.0 + math.exp(d))


# ---- the helper thread
# One helper thread for the independent halves of a query's work: a two-section bank
# evaluates its scan section there while the caller evaluates the complete section
# (bank/classifier.py); a lone query's coarse pass over a large index scans half of the rows
# there (bank/index.py). Both are compiled scans that release the GIL, and each half's result
# does not depend on which thread computed it. None on a one-CPU machine, and never used from
# the helper thread itself (one worker: it would wait for itself). Each use keeps the helper
# off the caller's CPU (Linux): otherwise, woken after an idle gap, it queues behind its busy
# caller on the same CPU while another CPU idles.

_NAME = 'pgn_helper'
_pool: ThreadPoolExecutor | None = None
_lock = threading.Lock()
_tid: int | None = None          # the helper's native thread id, once it has started
_cpus: set[int] = set()          # the CPUs this process may use (when the helper started)
_away_from = -1                  # the CPU the helper was last kept off


try:
    _sched_getcpu = ctypes.CDLL(None).sched_getcpu
    _sched_getcpu.restype = ctypes.c_int
    _sched_getcpu.argtypes = []
except (AttributeError, OSError):     # not glibc / not Linux: the helper stays where it is
    _sched_getcpu = None


def _keep_away() -> None:
    """Pin the helper to this process's CPUs other than the caller's (under _lock)."""
    global _away_from
    if _tid is None or _sched_getcpu is None:
        return
    cpu = _sched_getcpu()   # -1 on failure
    if cpu < 0 or cpu == _away_from or cpu not in _cpus or len(_cpus) < 2:
        return
    try:
        os.sched_setaffinity(_tid, _cpus - {cpu})
        _away_from = cpu
    except OSError:                      # the thread is gone, or a cpuset forbids it
        pass


def _forget_in_child() -> None:
    """A forked child has no helper thread: start its own on first use."""
    global _pool, _tid, _away_from, _lock
    _pool, _tid, _away_from, _lock = None, None, -1, threading.Lock()


if hasattr(os, 'register_at_fork'):
    os.register_at_fork(after_in_child=_forget_in_child)


def helper_thread() -> ThreadPoolExecutor | None:
    """The helper (started on first use), or None: one usable CPU, or called from it."""
    global _pool, _tid, _cpus
    if threading.current_thread().name.startswith(_NAME):
        return None
    with _lock:
        if _pool is None and default_threads() > 1:
            _pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=_NAME,
                                       initializer=name_os_thread)
            if hasattr(os, 'sched_setaffinity'):
                _cpus = set(os.sched_getaffinity(0))
                _tid = _pool.submit(threading.get_native_id).result()
        if _pool is not None:
            _keep_away()
        return _pool
