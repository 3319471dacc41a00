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

The plain kernel vote is the case W = None (vote on z), w = 0, T = 1: its
probability is exactly the vote share. The bank stores its entries already
whitened (u_i), so a query costs one (d, d) product more than the plain vote.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

# Upper bound on queries x bank entries held at once (float32 similarity block).
_MAX_BLOCK = 1 << 24
# exp() of a kernel logit this far below the best entry underflows float32: floor there.
_TINY = float(torch.finfo(torch.float32).tiny)
_ABSENT_LOG_PRIOR = -1e4
# Kernel logits are floored here (relative to the best entry) before exp(): below it
# exp() gives float32 denormals, which are many times slower to add, and the mass is
# negligible beside the best entry's 1.
_LOGIT_FLOOR = -80.0
_EXP_FLOOR = float(np.exp(_LOGIT_FLOOR))


@dataclass
class Head:
    """A fitted head (see module docstring). Tensors float32 on one device.

    whiten: (d, d) or None; lda_coef: (C, d) or None; lda_bias: (C,) or None.
    """

    gamma: float
    whiten: torch.Tensor | None = None
    lda_coef: torch.Tensor | None = None
    lda_bias: torch.Tensor | None = None
    fusion_weight: float = 0.0
    temperature: float = 1.0

    @property
    def is_plain_vote(self) -> bool:
        return self.whiten is None and (self.lda_coef is None or self.fusion_weight == 0)

    def to(self, device: torch.device | str) -> 'Head':
        def mv(t: torch.Tensor | None) -> torch.Tensor | None:
            return None if t is None else t.to(device)
        return Head(self.gamma, mv(self.whiten), mv(self.lda_coef), mv(self.lda_bias),
                    self.fusion_weight, self.temperature)

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
                 num_classes: int) -> tuple[torch.Tensor, torch.Tensor]:
        """z: (B, d) transformed queries; bank_u: (N, d) vote-space bank rows.

        -> probability (B, C) float32 (rows sum to 1), novelty (B,) float32.
        """
        return self.evaluate_with(z, ExactSearch(bank_u, bank_labels, num_classes))

    def evaluate_with(self, z: torch.Tensor, search: 'VoteSearch',
                      vote_bias: torch.Tensor | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor]:
        """`evaluate` with the kernel vote from `search` (exact or bank/search.py's index).

        z: (B, d) transformed queries -> probability (B, C), novelty (B,), float32.
        vote_bias: optional (C,) added to the log vote (bank/vote_prior.py); None: none.
        """
        if z.shape[0] == 0:
            return torch.zeros(0, search.num_classes), torch.zeros(0)
        fused, best = search.log_votes(self.vote_space(z), self.gamma)
        if vote_bias is not None:    # a class-size prior on the vote (-inf stays -inf)
            fused = fused + vote_bias.to(fused.device)
        lda = self.lda_log_probs(z)
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

    bank_u: (N, d) vote-space rows; bank_labels: (N,) int64.
    """

    def __init__(self, bank_u: torch.Tensor, bank_labels: torch.Tensor, num_classes: int
                 ) -> None:
        self.bank_u, self.bank_labels, self.num_classes = bank_u, bank_labels, int(num_classes)

    def log_votes(self, u: torch.Tensor, gamma: float) -> tuple[torch.Tensor, torch.Tensor]:
        step = max(1, _MAX_BLOCK // max(1, self.bank_u.shape[0]))
        logv, best = [], []
        for q in u.split(step):
            sims = q @ self.bank_u.T
            logv.append(log_vote_shares(sims, self.bank_labels, self.num_classes, gamma))
            best.append(sims.max(dim=1).values)
        return torch.cat(logv), torch.cat(best)


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


@dataclass
class CovarianceFit:
    """Class means and the eigen-decomposed pooled within-class covariance of z.

    means (C, d) float64; evals (r,) >= 0 and evecs (d, r): the covariance's eigenpairs
    (r = d, or the rank of a bank smaller than d: the other eigenvalues are 0);
    log_prior (C,); tau = tr(Sigma)/d (the shrinkage target's scale). Vectors are
    handled in the coordinates (z V, z - z V V^T): the whitened cosine is exact and a
    small bank never needs a (d, d) eigen-decomposition.
    """

    means: torch.Tensor
    evals: torch.Tensor
    evecs: torch.Tensor
    log_prior: torch.Tensor
    tau: float

    @classmethod
    def fit(cls, z: torch.Tensor, labels: torch.Tensor, num_classes: int) -> 'CovarianceFit':
        """z: (N, d) float32; labels: (N,) int64 (classes without entries: prior ~0)."""
        z64 = z.double()
        counts = torch.bincount(labels, minlength=num_classes).double()
        means = torch.zeros(num_classes, z.shape[1], dtype=torch.float64)
        means.index_add_(0, labels, z64)
        means /= counts.clamp_min(1)[:, None]
        centred = z64 - means[labels]
        dof = max(1, len(labels) - num_classes)      # pooled, unbiased
        if len(labels) < z.shape[1]:                 # low rank: SVD of the N rows
            _, sv, vh = torch.linalg.svd(centred, full_matrices=False)
            keep = sv > 1e-10 * max(1.0, float(sv.max()) if len(sv) else 1.0)
            evals, evecs = sv[keep] ** 2 / dof, vh[keep].T.contiguous()
        else:
            evals, evecs = torch.linalg.eigh(centred.T @ centred / dof)
            evals = evals.clamp_min(0.0)
        tau = float(evals.sum() / z.shape[1])
        # A class without entries gets a finite, overwhelming penalty instead of log(0).
        log_prior = (counts / counts.sum()).log().clamp_min(_ABSENT_LOG_PRIOR)
        return cls(means, evals, evecs, log_prior, tau)

    @property
    def full_rank(self) -> bool:
        return self.evecs.shape[1] == self.evecs.shape[0]

    def shrunk(self, alpha: float) -> tuple[torch.Tensor, float]:
        """Eigenvalues of Sigma_alpha: (r,) on the eigenvectors, one value on the rest.

        Floored so a zero covariance stays invertible.
        """
        lam = (1.0 - alpha) * self.evals + alpha * self.tau
        floor = max(1e-12, 1e-9 * max(float(lam.max()) if len(lam) else 0.0, self.tau))
        return lam.clamp_min(floor), max(alpha * self.tau, floor)

    def coords(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """z: (N, d) -> (z V (N, r), z - z V V^T (N, d) or None when r = d), float64."""
        z64 = z.double()
        p = z64 @ self.evecs
        return p, None if self.full_rank else z64 - p @ self.evecs.T

    def whitened(self, coords: tuple[torch.Tensor, torch.Tensor | None], alpha: float
                 ) -> torch.Tensor:
        """Whitened rows z Sigma_alpha^(-1/2) in an orthonormal basis: (N, r [+ d]) float32."""
        lam, lam_perp = self.shrunk(alpha)
        p, c = coords
        u = p * lam.rsqrt()
        return (u if c is None else torch.cat([u, c * lam_perp ** -0.5], dim=1)).float()

    def lda_logits(self, coords: tuple[torch.Tensor, torch.Tensor | None], alpha: float
                   ) -> torch.Tensor:
        """LDA logits z Sigma_a^-1 mu_c - mu_c Sigma_a^-1 mu_c / 2 + log prior_c: (N, C)."""
        lam, lam_perp = self.shrunk(alpha)
        pm, cm = self.coords(self.means)
        p, c = coords
        logits = (p / lam) @ pm.T - 0.5 * (pm * pm / lam).sum(1) + self.log_prior
        if c is not None:
            logits = logits + (c @ cm.T - 0.5 * (cm * cm).sum(1)) / lam_perp
        return logits

    def _lda64(self, alpha: float) -> tuple[torch.Tensor, torch.Tensor]:
        lam, lam_perp = self.shrunk(alpha)
        pm, cm = self.coords(self.means)
        coef = (pm / lam) @ self.evecs.T
        quad = (pm * pm / lam).sum(1)
        if cm is not None:
            coef = coef + cm / lam_perp
            quad = quad + (cm * cm).sum(1) / lam_perp
        return coef, -0.5 * quad + self.log_prior

    def whitening(self, alpha: float) -> torch.Tensor:
        """Sigma_alpha^(-1/2): (d, d) float32, symmetric."""
        lam, lam_perp = self.shrunk(alpha)
        v = self.evecs
        w = (v * (lam.rsqrt() - lam_perp ** -0.5)) @ v.T
        return (w + torch.eye(v.shape[0], dtype=w.dtype) * lam_perp ** -0.5).float()

    def lda(self, alpha: float) -> tuple[torch.Tensor, torch.Tensor]:
        """LDA under Sigma_alpha: coef (C, d) float32, bias (C,) float32 (see module doc)."""
        coef, bias = self._lda64(alpha)
        return coef.float(), bias.float()


def fit_head(z: torch.Tensor, labels: torch.Tensor, num_classes: int, gamma: float,
             alpha: float | None = None, lda_alpha: float | None = None,
             fusion_weight: float = 0.0, temperature: float = 1.0) -> Head:
    """Fit the head on transformed bank rows z (N, d) with knobs chosen by CV.

    alpha: shrinkage of the vote's whitening (None: vote on z); lda_alpha: shrinkage
    of the LDA covariance (used when fusion_weight > 0).
    """
    use_lda = lda_alpha is not None and fusion_weight > 0
    if alpha is None and not use_lda:
        return Head(gamma, temperature=float(temperature))
    fit = CovarianceFit.fit(z, labels, num_classes)
    whiten = fit.whitening(alpha) if alpha is not None else None
    coef, bias = fit.lda(lda_alpha) if use_lda else (None, None)
    return Head(gamma, whiten, coef, bias, float(fusion_weight) if use_lda else 0.0,
                float(temperature))


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
