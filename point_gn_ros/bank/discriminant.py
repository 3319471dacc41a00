"""The discriminant algebra of a bank, fitted in closed form from the bank alone.

One module for every fit (as sklearn's discriminant_analysis keeps LDA, shrinkage and the
eigen solver together): the pooled within-class covariance with its shrinkage, whitening,
LDA and precision (`CovarianceFit`, `ScatterStats`); the head (`fit_head`) and its
temperature; a wide LDA's closed-form refit (`lda_from_means`, `wide_means_*`) and the
enrolled classes' debias; the kernel ridge coefficients; the gate's two-class LDA
(`fit_gate`); the object test's shrunk generalised eigenproblem (`fit_object_test`); and the
inverse of the vote's whitening (`vote_to_z`). The fitted objects are bank/model.py's.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import threading

import numpy as np
import torch

from point_gn_ros.bank.model import (GATE_DIMS, GATE_SHRINKAGE, OBJECT_ALPHA, OBJECT_LAM,
                                     OBJECT_RANK, OBJECT_THETA, FeatureTransform, Gate, Head,
                                     ObjectTest)

# ---- shrunk pooled covariance and LDA
# The LDA's closed-form algebra under a shared, shrunk covariance (bank/model.py's LDA).
#
# CovarianceFit: class means and the pooled within-class covariance of rows, its whitening,
# LDA and precision; ScatterStats: running sufficient statistics of the same, so an enrollment
# refits the LDA without a pass over the bank; lda_from_means / lda_noise_trace /
# wide_means_*: a wide LDA's closed-form refit under its kept precision (bank/refit.py).

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


# ---- the head
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


# ---- the enrolled classes' LDA debias
# The LDA bias an enrollment gives the classes it creates (a wide LDA's mean-noise correction).
#
# A class taught from n examples has its mean off by noise of covariance Sigma / n, which costs
# it t / (2 n) logits on average (t = tr(Sigma_a^-1 Sigma), `Head.lda_trace`, bank/discriminant.py
# `lda_noise_trace`). An enrollment gives back a share f of it: bias_c += f t / (2 n_c).
# - Uniform: every taught class gets f = policy.lda_debias.
# - Steal budget rho (policy.lda_steal_budget > 0): each taught class gets the largest
#   f <= policy.lda_debias on a 0.05 grid whose *steal rate* stays <= rho. A class taught near
#   a dense category ("my table" beside 'table') then gets less, a distinct one more.
#
# Steal rate of taught class c: the share of built-class examples the LDA would give to c,
# under the LDA's own Gaussian model (class k ~ N(mu_k, Sigma), Sigma the unshrunk pooled
# covariance, pi_k the built classes' entry shares), pairwise against each one's own class:
#   rate_c = sum_k pi_k Phi((l_c(mu_k) - l_k(mu_k)) / sd_ck)
#   sd_ck^2 = (coef_c - coef_k) Sigma (coef_c - coef_k) = (v.Pv - a tau |Pv|^2) / (1 - a)
# with P = Sigma_a^-1 the kept precision, coef = P mu, v = mu_c - mu_k (so Pv = coef_c - coef_k),
# a the LDA shrinkage and tau = tr(Sigma_a) / D: no (D, D) product per enrollment, one
# Cholesky of P per head (cached). It models the LDA part of the fused score only; the budget
# itself is chosen by train-only CV (experiments/instance_cv.py --budgets).

SHARE_STEP = 0.05
MAX_SHARE = 2.0
MAX_BUDGET = 0.5

_TAU: dict[int, tuple[torch.Tensor, float]] = {}
_TAU_LOCK = threading.Lock()


def _tau(precision: torch.Tensor) -> float:
    """tr(P^-1) / D of a kept precision (D, D), cached per tensor (heads are immutable)."""
    with _TAU_LOCK:
        hit = _TAU.get(id(precision))
    if hit is not None and hit[0] is precision:
        return hit[1]
    chol, info = torch.linalg.cholesky_ex(precision.double())
    if int(info) == 0:
        tau = float(torch.cholesky_inverse(chol).diagonal().mean())
    else:     # not numerically positive definite (a rounded precision): from its spectrum
        tau = float((1.0 / torch.linalg.eigvalsh(precision.double()).clamp_min(1e-300)).mean())
    with _TAU_LOCK:
        if len(_TAU) >= 4:
            _TAU.pop(next(iter(_TAU)))
        _TAU[id(precision)] = (precision, tau)
    return tau


def steal_rates(means: torch.Tensor, coef: torch.Tensor, bias: torch.Tensor,
                precision: torch.Tensor, alpha: float, counts: torch.Tensor,
                built: torch.Tensor, target: int, shifts: torch.Tensor) -> torch.Tensor:
    """Steal rate of class `target` from the built classes at each bias shift (docstring).

    means, coef: (C, D) the LDA's class means and coefficients; bias, counts: (C,);
    built: (C,) bool, at least one; shifts: (S,) logits added to target's bias -> (S,)
    float64.
    """
    m64, c64, b64 = means.double(), coef.double(), bias.double()
    k = torch.nonzero(built).flatten()
    pi = counts.double()[k] / counts.double()[k].sum()
    own = (c64[k] * m64[k]).sum(1) + b64[k]                               # l_k(mu_k), (K,)
    pv = c64[target] - c64[k]                                              # (K, D)
    var = ((m64[target] - m64[k]) * pv).sum(1) - alpha * _tau(precision) * (pv * pv).sum(1)
    sd = (var / (1.0 - alpha)).clamp_min(1e-12).sqrt()
    gap = m64[k] @ c64[target] + b64[target] - own                         # (K,)
    z = (gap[None, :] + shifts.double()[:, None]) / sd[None, :]            # (S, K)
    return (torch.special.ndtr(z) * pi[None, :]).sum(1)


def taught_shares(means: torch.Tensor, coef: torch.Tensor, bias: torch.Tensor,
                  precision: torch.Tensor, alpha: float, trace: float, counts: torch.Tensor,
                  taught: torch.Tensor, share: float, budget: float) -> torch.Tensor:
    """Share f of the correction for each class (C,) float64: 0 for built classes.

    taught: (C,) bool; share: the uniform share, or the cap under a budget; budget: 0 =
    uniform. The bias is the LDA's before any correction (priors included).
    """
    f = torch.zeros(len(counts), dtype=torch.float64)
    if share <= 0 or not bool(taught.any()):
        return f
    if budget <= 0 or bool(taught.all()):
        f[taught] = share
        return f
    grid = torch.arange(0.0, share + 1e-9, SHARE_STEP, dtype=torch.float64)
    for c in torch.nonzero(taught).flatten().tolist():
        rates = steal_rates(means, coef, bias, precision, alpha, counts, ~taught, c,
                            grid * trace / (2.0 * float(counts[c])))
        # The largest share whose rate is within budget (rates rise with the share).
        within = int((rates <= budget).double().cumprod(0).sum())
        f[c] = grid[within - 1] if within else 0.0
    return f


def check_policy(share: float, budget: float) -> None:
    """Raise ValueError unless share in [0, MAX_SHARE] and budget in [0, MAX_BUDGET]."""
    if not (np.isfinite(share) and 0.0 <= share <= MAX_SHARE):
        raise ValueError(f'lda_debias must be in [0, {MAX_SHARE:g}], got {share!r}')
    if not (np.isfinite(budget) and 0.0 <= budget <= MAX_BUDGET):
        raise ValueError(f'lda_steal_budget must be in [0, {MAX_BUDGET:g}], got {budget!r}')


# ---- the kernel ridge coefficients (the query-time sum: bank/vote.py `ridge_scores`)
# Kernel ridge term of the head: a closed-form regression of class indicators on the bank.
#
# The kernel vote gives every bank entry the same say. Kernel ridge regression (KRR) on the
# same kernel, fitted in closed form from the bank alone, gives each entry its own
# coefficients instead, so that the bank's entries reproduce their own labels:
#
#   k(u, u')  = exp(g (cos(u, u') - 1))           = exp(-g |u - u'|^2 / 2) on unit rows
#   A         = (K + lambda I)^-1 Y                (N, C); K (N, N) over the bank's rows,
#                                                   Y the one-hot labels
#   ridge_c   = sum_i k(q, u_i) A_ic               (B, C) for queries q
#
# The head adds ridge_weight x ridge to its fused scores (bank/vote.py). g is small (chosen
# by CV) where the vote's gamma is large: the regression needs a wide kernel to have anything
# to fit. Invariants: A is fitted on the rows exactly as the bank file stores them (int4
# rounding moves K far enough to undo a fit on float rows), so builder and enrollment pass
# the stored rows; and every published bank version has A fitted on its own rows (an
# enrollment or removal refits it in full, bank/refit.py; docs/METHOD.md, "The kernel ridge
# term").

# Largest bank a ridge is fitted for: its (N, N) float32 kernel is 1 GB at 16,000 entries.
RIDGE_MAX_ENTRIES = 16000
# Kernel rows built per block when fitting.
_RIDGE_BLOCK = 2048


def fit_ridge(rows: torch.Tensor, labels: torch.Tensor, num_classes: int, gamma: float,
        lam: float) -> torch.Tensor:
    """Coefficients A = (K + lam I)^-1 Y for unit rows (N, d), labels (N,) -> (N, C) float32.

    float32 Cholesky in place (one (N, N) buffer, 390 MB at 9,843 rows: an enrollment's
    refit runs beside the node), as CV ranked the knobs; float64 if that factorisation fails.
    """
    y = torch.nn.functional.one_hot(labels.long(), num_classes)
    for dtype in (torch.float32, torch.float64):
        n = len(labels)
        k = torch.empty(n, n, dtype=dtype)
        r = rows.to(dtype)
        for i in range(0, n, _RIDGE_BLOCK):      # in place, a block of rows at a time
            torch.mm(r[i:i + _RIDGE_BLOCK], r.T, out=k[i:i + _RIDGE_BLOCK])
        k.sub_(1.0).mul_(gamma).exp_()
        k.diagonal().add_(lam)
        chol, info = torch.linalg.cholesky_ex(k, out=(k, torch.empty((), dtype=torch.int32)))
        if int(info) == 0:
            return torch.cholesky_solve(y.to(dtype), chol).float()
        del k, chol
    raise ValueError(f'kernel ridge: K + {lam:g} I is not positive definite')


def ridge_cv_scores(u_train: torch.Tensor, u_val: torch.Tensor, labels: torch.Tensor,
              num_classes: int, gammas: tuple[float, ...], lams: tuple[float, ...]
              ) -> dict[tuple[float, float], torch.Tensor]:
    """One fold: ridge scores of u_val (M, d) from a ridge fitted on u_train (N, d).

    -> {(gamma, lambda): (M, C) float32}. float32 Cholesky: CV only ranks knobs.
    """
    y = torch.nn.functional.one_hot(labels.long(), num_classes).float()
    s_tr, s_val = u_train.float() @ u_train.float().T, u_val.float() @ u_train.float().T
    out = {}
    eye = torch.eye(len(labels))
    for g in gammas:
        k, kv = torch.exp(g * (s_tr - 1.0)), torch.exp(g * (s_val - 1.0))
        for lam in lams:
            chol, info = torch.linalg.cholesky_ex(k + lam * eye)
            out[g, lam] = (kv @ torch.cholesky_solve(y, chol)) if int(info) == 0 else \
                torch.full((len(u_val), num_classes), float('nan'))
    return out


# ---- the gate: a two-class LDA, complete objects vs single-view scans (bank/model.py Gate)

def fit_gate(feats: torch.Tensor, is_scan: np.ndarray, dims: int | None = GATE_DIMS,
        shrinkage: float = GATE_SHRINKAGE) -> Gate:
    """feats: (N, D) raw encoder features; is_scan: (N,) bool (both kinds present)."""
    scan = torch.from_numpy(np.asarray(is_scan, dtype=np.int64))
    if int(scan.min()) == int(scan.max()):
        raise ValueError('the gate needs complete objects and scans')
    dims = None if dims is None or dims >= feats.shape[1] else dims
    tf = FeatureTransform.fit(feats, 'standardize', dims)
    fit = CovarianceFit.fit(tf(feats), scan, 2)
    fit.log_prior = torch.full((2,), float(np.log(0.5)), dtype=torch.float64)
    coef, bias = fit.lda(shrinkage)
    return Gate(tf, coef, bias)


# ---- the object test: generalised eigenvectors of between- vs within-object scatter
_ROWS = 8192      # rows a block while the scatter is summed (float64 blocks of ~100 MB)


def fit_object_test(x: torch.Tensor, groups: np.ndarray, labels: np.ndarray,
        class_names: list[str], rank: int = OBJECT_RANK, alpha: float = OBJECT_ALPHA,
        lam: float = OBJECT_LAM, theta: float = OBJECT_THETA) -> ObjectTest:
    """x: (N, D) standardised scan rows; groups: (N,) source object; labels: (N,) class id.

    Every object needs >= 2 scans (its within scatter); an object's class is its first
    row's.
    """
    _, obj, counts = np.unique(np.asarray(groups), return_inverse=True, return_counts=True)
    if len(counts) < 2 or counts.min() < 2 or not 0 < rank <= x.shape[1]:
        raise ValueError(f'object test: needs >= 2 objects of >= 2 scans and 0 < rank <= '
                         f'{x.shape[1]}, got {len(counts)} objects, rank {rank}')
    k, d = len(counts), x.shape[1]
    idx = torch.from_numpy(obj.astype(np.int64))
    sums = torch.zeros(k, d, dtype=torch.float64)
    for rows in torch.arange(len(x)).split(_ROWS):
        sums.index_add_(0, idx[rows], x[rows].double())
    m = sums / torch.from_numpy(counts)[:, None].double()          # (K, D)
    sw = torch.zeros(d, d, dtype=torch.float64)
    for rows in torch.arange(len(x)).split(_ROWS):
        c = x[rows].double() - m[idx[rows]]
        sw += c.T @ c
    sw /= float(len(x) - k)
    mc = m - m.mean(0)
    sb = mc.T @ mc / k
    sw = (1 - alpha) * sw + alpha * torch.trace(sw) / d * torch.eye(d, dtype=sw.dtype)
    inv = torch.linalg.solve_triangular(torch.linalg.cholesky(sw),
                                        torch.eye(d, dtype=sw.dtype), upper=False)
    w = (torch.linalg.eigh(inv @ sb @ inv.T)[1][:, -rank:].T @ inv)    # (r, D)
    first = np.zeros(k, dtype=np.int64)
    first[obj[::-1]] = np.arange(len(obj))[::-1]                       # first row per object
    return ObjectTest(w.float(), (m @ w.T).float(),
               torch.from_numpy(np.asarray(labels, dtype=np.int64)[first]),
               torch.from_numpy(counts.astype(np.int64)), tuple(class_names),
               float(lam), float(theta), float(alpha))


# ---- back from the vote's whitened space
def vote_to_z(u: torch.Tensor, head: Head | None) -> torch.Tensor:
    """Bank rows in the vote's space (N, d) -> the transformed rows z (N, d) they came from.

    u = normalize(z W) with W the head's (invertible, symmetric) whitening, z unit rows, so
    z = normalize(u W^-1) (exact up to the stored precision). Without whitening u is z.
    """
    if head is None or head.whiten is None:
        return u
    return torch.nn.functional.normalize(u.double() @ _unwhitening(head.whiten), dim=1).float()


# (whitening tensor, its float64 inverse) by id: every enrollment maps its new rows back to
# z with the section's unchanged whitening; inverting it each time cost 20 ms per section.
_INVERSES: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
_MAX_INVERSES = 8
_INVERSES_LOCK = threading.Lock()


def _unwhitening(whiten: torch.Tensor) -> torch.Tensor:
    """W^-1 (d, d) float64 of a whitening W, cached (heads are immutable once fitted)."""
    with _INVERSES_LOCK:
        hit = _INVERSES.get(id(whiten))
    if hit is not None and hit[0] is whiten:
        return hit[1]
    inv = torch.linalg.inv(whiten.double())
    with _INVERSES_LOCK:
        if len(_INVERSES) >= _MAX_INVERSES:
            _INVERSES.pop(next(iter(_INVERSES)))
        _INVERSES[id(whiten)] = (whiten, inv)   # holding whiten keeps its id unique
    return inv
