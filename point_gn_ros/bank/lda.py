"""The LDA's closed-form algebra under a shared, shrunk covariance (bank/head.py's LDA).

CovarianceFit: class means and the pooled within-class covariance of rows, its whitening,
LDA and precision; ScatterStats: running sufficient statistics of the same, so an enrollment
refits the LDA without a pass over the bank; lda_from_means / lda_noise_trace /
wide_means_*: a wide LDA's closed-form refit under its kept precision (bank/refit.py).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:
    from point_gn_ros.bank.head import Head

_ABSENT_LOG_PRIOR = -1e4


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

    def precision(self, alpha: float) -> torch.Tensor:
        """Sigma_alpha^-1: (d, d) float64, symmetric."""
        lam, lam_perp = self.shrunk(alpha)
        v = self.evecs
        p = (v * (1.0 / lam - 1.0 / lam_perp)) @ v.T
        return p + torch.eye(v.shape[0], dtype=p.dtype) / lam_perp


def lda_from_means(means: torch.Tensor, precision: torch.Tensor, counts: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """LDA of class means (C, d) under a kept precision (d, d), priors = count shares.

    -> coef (C, d) float32, bias (C,) float32, as CovarianceFit.lda (float64 inside).
    """
    m64 = means.double()
    coef = m64 @ precision.double()
    n = counts.double()
    bias = -0.5 * (m64 * coef).sum(1) + (n / n.sum()).log()
    return coef.float(), bias.float()


def lda_noise_trace(precision: torch.Tensor, alpha: float) -> float:
    """tr(Sigma_a^-1 Sigma) of a kept precision Sigma_a^-1 (d, d) and its shrinkage alpha.

    A class mean estimated from n rows is off by noise of covariance Sigma / n, which inflates
    its LDA quadratic term mu Sigma_a^-1 mu by tr(Sigma_a^-1 Sigma) / n on average: a class
    taught from 5 examples is penalised by ~d / 10 logits for the noise of its own mean.
    Sigma is recovered from Sigma_a's eigenvalues (tr Sigma_a = tr Sigma). 0 for alpha >= 1.
    """
    if not 0.0 <= alpha < 1.0:
        return 0.0
    lam = 1.0 / torch.linalg.eigvalsh(precision.double()).clamp_min(1e-300)
    tau = float(lam.mean())
    sigma = ((lam - alpha * tau) / (1.0 - alpha)).clamp_min(0.0)
    return float((sigma / lam).sum())


def wide_means_add(head: Head | None, x: torch.Tensor, class_id: int, count: int
                   ) -> Head | None:
    """A wide-LDA head whose class `class_id` mean takes in standardised rows x (m, D).

    count: the class's entries before (0, and class_id == C: a new class). Other heads are
    returned as they are.
    """
    if head is None or not head.lda_wide:
        return head
    means = head.lda_means
    if class_id == len(means):
        means = torch.cat([means, torch.zeros(1, means.shape[1])])
    means = means.clone()
    total = means[class_id].double() * count + x.double().sum(0)
    means[class_id] = (total / (count + len(x))).float()
    return replace(head, lda_means=means)


def wide_means_remove(head: Head | None, class_id: int) -> Head | None:
    """A wide-LDA head without class `class_id`'s mean (later ids shift down)."""
    if head is None or not head.lda_wide:
        return head
    keep = torch.arange(len(head.lda_means)) != class_id
    return replace(head, lda_means=head.lda_means[keep])


@dataclass(frozen=True)
class ScatterStats:
    """Sufficient statistics of the bank's rows z for the LDA: updated per enrollment.

    gram (d, d) float64 = sum_i z_i z_i^T over every row; sums (C, d) float64 per class;
    counts (C,) float64. The pooled within-class scatter of the classes S is
    gram - sum_c sums_c sums_c^T / counts_c, so adding examples costs (m, d) x (d, m) and
    one (d, d) eigen-decomposition instead of a pass over the whole bank.
    """

    gram: torch.Tensor
    sums: torch.Tensor
    counts: torch.Tensor

    @classmethod
    def of(cls, z: torch.Tensor, labels: torch.Tensor, num_classes: int) -> 'ScatterStats':
        z64 = z.double()
        sums = torch.zeros(num_classes, z.shape[1], dtype=torch.float64)
        sums.index_add_(0, labels, z64)
        counts = torch.bincount(labels, minlength=num_classes).double()
        return cls(z64.T @ z64, sums, counts)

    def merge(self, other: 'ScatterStats') -> 'ScatterStats':
        """The statistics of both sets of rows (same classes)."""
        return ScatterStats(self.gram + other.gram, self.sums + other.sums,
                            self.counts + other.counts)

    def add(self, z: torch.Tensor, class_id: int) -> 'ScatterStats':
        """Rows z (m, d) joining class `class_id` (== C: a new class) -> new stats."""
        z64 = z.double()
        sums, counts = self.sums, self.counts
        if class_id == len(counts):
            sums = torch.cat([sums, torch.zeros(1, sums.shape[1], dtype=torch.float64)])
            counts = torch.cat([counts, torch.zeros(1, dtype=torch.float64)])
        sums, counts = sums.clone(), counts.clone()
        sums[class_id] += z64.sum(0)
        counts[class_id] += len(z64)
        return ScatterStats(self.gram + z64.T @ z64, sums, counts)

    def remove(self, z: torch.Tensor, class_id: int) -> 'ScatterStats':
        """Every row z (m, d) of class `class_id` leaves; later class ids shift down."""
        z64 = z.double()
        keep = torch.arange(len(self.counts)) != class_id
        return ScatterStats(self.gram - z64.T @ z64, self.sums[keep], self.counts[keep])

    def lda(self, present: np.ndarray, alpha: float
            ) -> tuple[torch.Tensor, torch.Tensor] | None:
        """LDA of the classes `present` under Sigma_alpha (as CovarianceFit.lda), or None.

        -> coef (P, d) float32, bias (P,) float32. Solved with one Cholesky factorisation
        of Sigma_alpha = (1 - alpha) Sigma + alpha tr(Sigma)/d I (no eigen-decomposition).
        None when the stats cannot give it exactly (rows of other classes in the gram, fewer
        rows than dimensions: CovarianceFit.fit's low-rank path) or Sigma_alpha is singular.
        """
        idx = torch.from_numpy(present)
        n = self.counts[idx]
        others = torch.ones(len(self.counts), dtype=torch.bool)
        others[idx] = False
        total, d = float(n.sum()), self.gram.shape[0]
        if bool((self.counts[others] > 0).any()) or total < d:
            return None
        means = self.sums[idx] / n[:, None]
        scatter = self.gram - (self.sums[idx].T / n) @ self.sums[idx]
        cov = (scatter + scatter.T) / (2 * max(1.0, total - len(present)))
        tau = float(torch.diagonal(cov).sum()) / d
        shrunk = (1.0 - alpha) * cov + alpha * tau * torch.eye(d, dtype=torch.float64)
        chol, info = torch.linalg.cholesky_ex(shrunk)
        if int(info) != 0:
            return None
        coef = torch.cholesky_solve(means.T, chol).T                     # Sigma_a^-1 mu_c
        bias = -0.5 * (means * coef).sum(1) + (n / total).log()
        return coef.float(), bias.float()
