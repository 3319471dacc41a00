"""A lone query through a section's head in compiled code (core/kernels/pgn_head.c).

A node at a sensor's rate classifies one object at a time, with the CPUs idle in between.
The torch path (bank/head.py) spends a lone query in ~40 small ops, and after 33 ms of
idle time each starts with its code and data out of cache: the shipped bank's complete
section took 2.9-3.5 ms instead of 1.2-1.8 back to back, a tiny softmax 135 us instead of
3 (benchmarks/log, "Second session of 2026-12-03"). Here a section is two C calls around
its search (the exact scan of bank_dots or the index's candidates), with the same
formulas: probabilities within ~1e-6 of the torch path, labels the same.

`LoneSection.build` returns None for what it does not cover (off the CPU, no kernels, a
search without compiled rows, a ridge head whose coefficients are not float32 values); the
classifier then keeps the torch path. A batch takes the torch path up to its exact scan's
cosines, then `finish_rows` (bank/classifier.py `compiled_finish`).
"""

from __future__ import annotations

import ctypes
import math
from typing import Any

import numpy as np
import torch

from point_gn_ros.core import kernels


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


class LoneSection:
    """One section of a Classifier (its transform, head, search and vote bias) for one query."""

    def __init__(self, lib: ctypes.CDLL, clf: Any, ridge: np.ndarray | None) -> None:
        head, search = clf.head, clf.search
        self.lib, self.embed = lib, _Embedding(lib, clf.transform, head.whiten)
        self.num_classes = int(clf.bank.num_classes)
        self.gamma, self.temperature = float(head.gamma), float(head.temperature)
        self.ridge = ridge
        self.ridge_gamma, self.ridge_weight = float(head.ridge_gamma), float(head.ridge_weight)
        use_lda = head.lda_coef is not None and head.fusion_weight != 0
        self.lda_coef = _f32(head.lda_coef) if use_lda else None
        self.lda_bias = _f32(head.lda_bias) if use_lda else None
        self.lda_wide, self.fusion_weight = bool(head.lda_wide), float(head.fusion_weight)
        self.index = getattr(search, 'index', None)         # IndexedSearch, else ExactSearch
        self.packed = None
        if self.index is None:
            self.rows, self.norms = search._rows
            # int4 codes (every value in [-8, 7]) scanned from nibbles: half the bytes
            if (self.norms is not None and self.rows.shape[1] % 16 == 0
                    and -8 <= self.rows.min() and self.rows.max() <= 7):
                self.packed = kernels.pack_nibbles(self.rows)
            self.labels = np.ascontiguousarray(clf.labels.cpu().numpy(), dtype=np.int64)
        else:
            self.labels = np.ascontiguousarray(self.index.labels, dtype=np.int64)
        self.counts = np.bincount(self.labels, minlength=self.num_classes).astype(np.int64)

    @classmethod
    def build(cls, clf: Any) -> 'LoneSection | None':
        """The compiled path of Classifier section clf, or None where it does not apply."""
        lib = kernels.load()
        head, search = clf.head, clf.search
        if lib is None or clf.device.type != 'cpu' or len(clf.labels) == 0:
            return None
        if getattr(search, 'index', None) is None:
            if getattr(search, '_rows', None) is None:
                return None
        elif search.index._lib is None:
            return None
        ridge = None
        if head.has_ridge:
            if getattr(search, 'index', None) is not None:
                return None
            coef = head.ridge_coef.detach().cpu()
            ridge = np.ascontiguousarray(coef.numpy(), dtype=np.float32)
            # float32 values read as float32 (half the bytes), summed in double as torch does
            if not np.array_equal(ridge.astype(coef.numpy().dtype), coef.numpy()):
                return None
        return cls(lib, clf, ridge)

    def evaluate(self, x: np.ndarray) -> tuple[np.ndarray, float]:
        """x: (D,) float32 raw features -> probability (C,) float32, novelty."""
        xs, z, u = self.embed(x)
        if self.packed is not None:
            sims = kernels.packed_dots_i4(self.packed, self.norms, u)
            labels = self.labels
        elif self.index is None:
            sims = kernels.bank_dots(self.rows, u[None], self.norms)[0]
            labels = self.labels
        else:
            rows = self.index.candidates_many(u[None])[0]
            sims = self.index._dots(u, rows)
            labels = np.ascontiguousarray(self.labels[rows])
        prob, novelty = np.empty(self.num_classes, np.float32), np.empty(1, np.float32)
        self._finish(sims, labels, xs if self.lda_wide else z, prob, novelty)
        return prob, float(novelty[0])

    def finish_rows(self, sims: np.ndarray, lda_in: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A batch's head after its exact scan -> probability (B, C), novelty (B,).

        sims (B, N): cosines to every entry (the search's own scan, in the section's row
        order); lda_in (B, d): the LDA's input rows (standardised for a wide LDA, else
        transformed). Each row as `evaluate` finishes a lone query: the torch path's ~20
        ops over (B, N) took ~0.15 ms a row at the shipped bank, this one ~0.08
        (benchmarks/log, "third session of 2026-12-05"). Exact sections only (index None).
        """
        sims = np.ascontiguousarray(sims, dtype=np.float32)
        lda_in = np.ascontiguousarray(lda_in, dtype=np.float32)
        prob = np.empty((len(sims), self.num_classes), np.float32)
        novelty = np.empty(len(sims), np.float32)
        for b in range(len(sims)):
            self._finish(sims[b], self.labels, lda_in[b], prob[b], novelty[b:b + 1])
        return prob, novelty

    def _finish(self, sims: np.ndarray, labels: np.ndarray, lda_in: np.ndarray,
                prob: np.ndarray, novelty: np.ndarray) -> None:
        """pgn_head_finish of one query's cosines into prob (C,) and novelty (1,)."""
        c = self.num_classes
        work = np.empty(5 * c, np.float64)
        self.lib.pgn_head_finish(
            sims.ctypes.data, labels.ctypes.data, len(sims), c, self.counts.ctypes.data,
            self.gamma, _ptr(self.ridge), self.ridge_gamma, self.ridge_weight,
            lda_in.ctypes.data, len(lda_in), _ptr(self.lda_coef),
            _ptr(self.lda_bias), self.fusion_weight, self.temperature, work.ctypes.data,
            prob.ctypes.data, novelty.ctypes.data)


class LoneGate:
    """The gate's p(scan) of one query (bank/gate.py) in compiled code."""

    def __init__(self, lib: ctypes.CDLL, gate: Any) -> None:
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
