"""Closed-form discriminant head on bank features: whitened kernel vote fused with LDA.

Fitted from the bank alone (no gradient training). On transformed bank features z
(standardised, optionally PCA-projected, L2-normalised: `FeatureTransform`):

  Sigma        pooled within-class covariance of z, (d, d)
  Sigma_a      (1 - a) Sigma + a tr(Sigma)/d I             shrinkage a in (0, 1]
  W            Sigma_a^(-1/2) (symmetric)                  whitening
  u            normalize(z W)                              whitened, re-normalised
  log_vote_c   log share of class c in sum_i exp(gamma (cos(u, u_i) - 1))
  lda_c        z Sigma_a^-1 mu_c - mu_c Sigma_a^-1 mu_c / 2 + log prior_c
  fused_c      log_vote_c + w log_softmax(lda)_c
  probability  softmax(fused / T)                          T: temperature by CV log-loss
  novelty      1 - max_i cos(u, u_i)                       in [0, 2]; 0 = a bank entry

A kernel ridge term (bank/ridge.py, `ridge_coef`) adds ridge_weight x sum_i k(u, u_i) A_ic
to fused: per-entry coefficients A (N, C) fitted in closed form so the bank reproduces its
own labels under a wide kernel k; it needs every entry's cosine (the exact search).

A wide LDA (`lda_wide`) fits the LDA on the transform's standardised rows before the PCA
projection (x = `FeatureTransform.standardized`, all D encoder dims) instead of on z: the PCA
keeps the directions of most spread, not those that separate classes best. Its coefficients
are (C, D); it keeps its precision Sigma_a^-1 (D, D) and class means (C, D) so an enrollment
can add a class in closed form under the kept covariance (bank/refit.py).

The plain kernel vote is the case W = None (vote on z), w = 0, T = 1: its
probability is exactly the vote share. The bank stores its entries already
whitened (u_i), so a query costs one (d, d) product more than the plain vote.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np
import torch

# The LDA's algebra lives in bank/lda.py (CovarianceFit re-exported for the head's users).
from point_gn_ros.bank.lda import CovarianceFit
from point_gn_ros.bank.ridge import ridge_scores

# Upper bound on queries x bank entries held at once (float32 similarity block).
_MAX_BLOCK = 1 << 24
# exp() of a kernel logit this far below the best entry underflows float32: floor there.
_TINY = float(torch.finfo(torch.float32).tiny)
# Kernel logits are floored here (relative to the best entry) before exp(): below it
# exp() gives float32 denormals, which are many times slower to add, and the mass is
# negligible beside the best entry's 1.
_LOGIT_FLOOR = -80.0
_EXP_FLOOR = float(np.exp(_LOGIT_FLOOR))


@dataclass
class Head:
    """A fitted head (see module docstring). Tensors float32 on one device.

    whiten: (d, d) or None; lda_coef: (C, d) or None ((C, D) when lda_wide); lda_bias:
    (C,) or None. lda_wide: the LDA reads the standardised rows x (B, D), not z;
    lda_precision (D, D) and lda_means (C, D): what an enrollment refits it from.
    """

    gamma: float
    whiten: torch.Tensor | None = None
    lda_coef: torch.Tensor | None = None
    lda_bias: torch.Tensor | None = None
    fusion_weight: float = 0.0
    temperature: float = 1.0
    lda_wide: bool = False
    lda_precision: torch.Tensor | None = None
    lda_means: torch.Tensor | None = None
    lda_trace: float = 0.0       # wide LDA: tr(Sigma_a^-1 Sigma), see bank/lda.py lda_noise_trace
    ridge_coef: torch.Tensor | None = None   # (N, C): one row per bank entry (bank/ridge.py)
    ridge_gamma: float = 0.0
    ridge_lambda: float = 0.0
    ridge_weight: float = 0.0

    @property
    def is_plain_vote(self) -> bool:
        return self.whiten is None and (self.lda_coef is None or self.fusion_weight == 0) \
            and not self.has_ridge

    @property
    def has_ridge(self) -> bool:
        return self.ridge_coef is not None and self.ridge_weight > 0

    def to(self, device: torch.device | str) -> 'Head':
        def mv(t: torch.Tensor | None) -> torch.Tensor | None:
            return None if t is None else t.to(device)
        return Head(self.gamma, mv(self.whiten), mv(self.lda_coef), mv(self.lda_bias),
                    self.fusion_weight, self.temperature, self.lda_wide,
                    mv(self.lda_precision), mv(self.lda_means), self.lda_trace,
                    # float64 once here: the ridge sum runs in float64 (bank/ridge.py)
                    None if self.ridge_coef is None else self.ridge_coef.to(device, torch.float64),
                    self.ridge_gamma, self.ridge_lambda, self.ridge_weight)

    def vote_space(self, z: torch.Tensor) -> torch.Tensor:
        """z: (B, d) transformed unit rows -> (B, d) rows the kernel vote compares."""
        if self.whiten is None:
            return z
        return torch.nn.functional.normalize(z @ self.whiten, dim=1, eps=1e-12)

    def lda_log_probs(self, z: torch.Tensor) -> torch.Tensor | None:
        """z: (B, d) -> (B, C) LDA log-posteriors, or None without an LDA part."""
        if self.lda_coef is None or self.fusion_weight == 0:
            return None
        return torch.log_softmax(z @ self.lda_coef.T + self.lda_bias, dim=1)

    def evaluate(self, z: torch.Tensor, bank_u: torch.Tensor, bank_labels: torch.Tensor,
                 num_classes: int, x: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        """z: (B, d) transformed queries; bank_u: (N, d) vote-space bank rows.

        x: (B, D) standardised rows, needed by a wide LDA. -> probability (B, C) float32
        (rows sum to 1), novelty (B,) float32.
        """
        return self.evaluate_with(z, ExactSearch(bank_u, bank_labels, num_classes), x=x)

    def evaluate_with(self, z: torch.Tensor, search: 'VoteSearch',
                      x: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """`evaluate` with the kernel vote from `search` (exact or bank/search.py's index).

        z: (B, d) transformed queries -> probability (B, C), novelty (B,), float32.
        x: (B, D) standardised rows (`FeatureTransform.standardized`), read by a wide LDA.
        """
        if z.shape[0] == 0:
            return torch.zeros(0, search.num_classes), torch.zeros(0)
        u = self.vote_space(z)
        if self.has_ridge:
            if not isinstance(search, ExactSearch):
                raise ValueError('a kernel ridge head needs the exact search')
            fused, best, ridge = search.ridge_log_votes(u, self.gamma, self.ridge_coef,
                                                        self.ridge_gamma)
            fused = fused + self.ridge_weight * ridge
        else:
            fused, best = search.log_votes(u, self.gamma)
        if self.lda_wide and x is None:
            raise ValueError('a wide-LDA head needs the standardised rows x')
        lda = self.lda_log_probs(x if self.lda_wide else z)
        if lda is not None:
            fused = fused + self.fusion_weight * lda
        prob = torch.softmax(fused / self.temperature, dim=1)
        return prob, (1.0 - best).clamp_min(0.0)


class VoteSearch(Protocol):
    """Where the kernel vote of vote-space queries comes from (ExactSearch, IndexedSearch)."""

    num_classes: int

    def log_votes(self, u: torch.Tensor, gamma: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Vote of u: (B, d) vote-space unit rows -> log shares (B, C), best cosine (B,).

        The log shares follow `log_vote_shares` (floor per entry, -inf for absent classes).
        """
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

    @property
    def scans_codes(self) -> bool:
        """Whether the compiled scan reads int8 codes (else float32 rows or torch)."""
        return self._rows is not None and self._rows[1] is not None

    def similarities(self, q: torch.Tensor) -> torch.Tensor:
        """q: (B, d) vote-space rows -> (B, N) cosines to every bank entry."""
        if self._rows is None or q.device.type != 'cpu':
            return q @ self.bank_u.T
        from point_gn_ros.core import kernels
        rows, norms = self._rows
        return torch.from_numpy(kernels.bank_dots(rows, q.detach().float().numpy(), norms))

    def log_votes(self, u: torch.Tensor, gamma: float) -> tuple[torch.Tensor, torch.Tensor]:
        logv, best, _ = self.ridge_log_votes(u, gamma)
        return logv, best

    def ridge_log_votes(self, u: torch.Tensor, gamma: float, coef: torch.Tensor | None = None,
                        ridge_gamma: float = 0.0
                        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """`log_votes`, and the kernel ridge scores from the same cosines.

        coef: (N, C) ridge coefficients (bank/ridge.py) -> third output (B, C); None: None.
        """
        step = max(1, _MAX_BLOCK // max(1, self.bank_u.shape[0]))
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
    or int4, bank/quant.py); float32 rows otherwise (no copy when bank_u already is such
    rows). None off the CPU, without kernels, or for an empty bank.
    """
    if bank_u.device.type != 'cpu' or bank_u.ndim != 2 or bank_u.shape[0] == 0:
        return None
    from point_gn_ros.core import kernels
    if kernels.load() is None:
        return None
    rows = np.ascontiguousarray(bank_u.detach().numpy(), dtype=np.float32)
    codes = _stored_codes(rows)
    return (rows, None) if codes is None else codes


def _stored_codes(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(N, d) int8 codes and (N,) float32 norms with rows == normalize(codes), else None.

    An int4 / int8 row's largest coordinate is stored as +-7 / +-127 (bank/quant.py), so its
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


def log_vote_shares(sims: torch.Tensor, bank_labels: torch.Tensor, num_classes: int,
                    gamma: float) -> torch.Tensor:
    """Log kernel-vote share of each class.

    sims: (B, N) cosine to each bank entry; bank_labels: (N,) int64 -> (B, C) float32,
    logsumexp over classes = 0. Each entry counts at least exp(-80) of the best entry's
    vote (no float32 denormals); a class absent from the bank gets -inf.
    """
    logits = (sims - 1.0) * gamma
    top = logits.max(dim=1, keepdim=True).values
    votes = torch.zeros(sims.shape[0], num_classes, dtype=logits.dtype, device=logits.device)
    votes.index_add_(1, bank_labels, (logits - top).clamp_min_(_LOGIT_FLOOR).exp_())
    present = torch.zeros(num_classes, dtype=torch.bool, device=sims.device)
    present[bank_labels] = True
    logv = votes.clamp_min(_TINY).log().masked_fill(~present, -float('inf'))
    return logv - torch.logsumexp(logv, dim=1, keepdim=True)


def log_vote_shares_grid(sims: torch.Tensor, bank_labels: torch.Tensor, num_classes: int,
                         gammas: tuple[float, ...]) -> list[torch.Tensor]:
    """`log_vote_shares` for every gamma of a grid, one exp() per run of doublings.

    exp(2 g (s - s_max)) = exp(g (s - s_max))^2, so a grid whose steps double costs one
    exp and a squaring per further gamma (CV spends most of its time here).
    """
    present = torch.zeros(num_classes, dtype=torch.bool, device=sims.device)
    present[bank_labels] = True
    gap = sims - sims.max(dim=1, keepdim=True).values             # (B, N) <= 0
    out, e, prev = [], None, None
    for g in gammas:
        if e is not None and prev is not None and abs(g - 2 * prev) < 1e-9 * g:
            e.square_().clamp_min_(_EXP_FLOOR)
        else:
            e = (gap * g).clamp_min_(_LOGIT_FLOOR).exp_()
        prev = g
        votes = torch.zeros(sims.shape[0], num_classes, dtype=sims.dtype, device=sims.device)
        votes.index_add_(1, bank_labels, e)
        logv = votes.clamp_min(_TINY).log().masked_fill(~present, -float('inf'))
        out.append(logv - torch.logsumexp(logv, dim=1, keepdim=True))
    return out


def fit_head(z: torch.Tensor, labels: torch.Tensor, num_classes: int, gamma: float,
             alpha: float | None = None, lda_alpha: float | None = None,
             fusion_weight: float = 0.0, temperature: float = 1.0,
             x: torch.Tensor | None = None) -> Head:
    """Fit the head on transformed bank rows z (N, d) with knobs chosen by CV.

    alpha: shrinkage of the vote's whitening (None: vote on z); lda_alpha: shrinkage
    of the LDA covariance (used when fusion_weight > 0); x: (N, D) standardised rows: the
    LDA is fitted on them instead (a wide LDA, module docstring).
    """
    use_lda = lda_alpha is not None and fusion_weight > 0
    if alpha is None and not use_lda:
        return Head(gamma, temperature=float(temperature))
    fit = CovarianceFit.fit(z, labels, num_classes) if alpha is not None or x is None else None
    whiten = fit.whitening(alpha) if fit is not None and alpha is not None else None
    head = Head(gamma, whiten, None, None, float(fusion_weight) if use_lda else 0.0,
                float(temperature))
    if not use_lda:
        return head
    if x is None:
        coef, bias = fit.lda(lda_alpha)
        return replace(head, lda_coef=coef, lda_bias=bias)
    wide = CovarianceFit.fit(x, labels, num_classes)
    coef, bias = wide.lda(lda_alpha)
    lam, _ = wide.shrunk(lda_alpha)
    return replace(head, lda_coef=coef, lda_bias=bias, lda_wide=True,
                   lda_precision=wide.precision(lda_alpha).float(),
                   lda_means=wide.means.float(), lda_trace=float((wide.evals / lam).sum()))


def best_temperature(fused: np.ndarray | torch.Tensor, labels: np.ndarray) -> tuple[float, float]:
    """Temperature minimising the log-loss of softmax(fused / T) on held-out rows.

    fused: (N, C) held-out fused scores; labels: (N,) int -> (T, mean log-loss).
    Golden-section search on log T over [1e-3, 1e4] after a coarse grid.
    """
    s = torch.as_tensor(fused, dtype=torch.float64)
    y = torch.as_tensor(np.asarray(labels), dtype=torch.int64)
    finite = torch.isfinite(s.gather(1, y[:, None]))[:, 0]
    s, y = s[finite], y[finite]
    if len(y) == 0:
        return 1.0, float('nan')

    def loss(log_t: float) -> float:
        lp = torch.log_softmax(s / np.exp(log_t), dim=1)
        return float(-lp.gather(1, y[:, None]).mean())

    grid = np.linspace(np.log(1e-3), np.log(1e4), 57)
    i = int(np.argmin([loss(g) for g in grid]))
    lo, hi = grid[max(0, i - 1)], grid[min(len(grid) - 1, i + 1)]
    r = (np.sqrt(5) - 1) / 2
    for _ in range(30):
        a, b = hi - r * (hi - lo), lo + r * (hi - lo)
        if loss(a) < loss(b):
            hi = b
        else:
            lo = a
    t = float(np.exp((lo + hi) / 2))
    return t, loss(np.log(t))
