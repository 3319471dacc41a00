"""The LDA bias an enrollment gives the classes it creates (a wide LDA's mean-noise correction).

A class taught from n examples has its mean off by noise of covariance Sigma / n, which costs
it t / (2 n) logits on average (t = tr(Sigma_a^-1 Sigma), `Head.lda_trace`, bank/lda.py
`lda_noise_trace`). An enrollment gives back a share f of it: bias_c += f t / (2 n_c).
- Uniform: every taught class gets f = policy.lda_debias.
- Steal budget rho (policy.lda_steal_budget > 0): each taught class gets the largest
  f <= policy.lda_debias on a 0.05 grid whose *steal rate* stays <= rho. A class taught near
  a dense category ("my table" beside 'table') then gets less, a distinct one more.

Steal rate of taught class c: the share of built-class examples the LDA would give to c,
under the LDA's own Gaussian model (class k ~ N(mu_k, Sigma), Sigma the unshrunk pooled
covariance, pi_k the built classes' entry shares), pairwise against each one's own class:
  rate_c = sum_k pi_k Phi((l_c(mu_k) - l_k(mu_k)) / sd_ck)
  sd_ck^2 = (coef_c - coef_k) Sigma (coef_c - coef_k) = (v.Pv - a tau |Pv|^2) / (1 - a)
with P = Sigma_a^-1 the kept precision, coef = P mu, v = mu_c - mu_k (so Pv = coef_c - coef_k),
a the LDA shrinkage and tau = tr(Sigma_a) / D: no (D, D) product per enrollment, one
Cholesky of P per head (cached). It models the LDA part of the fused score only; the budget
itself is chosen by train-only CV (experiments/instance_cv.py --budgets).
"""

from __future__ import annotations

import threading

import numpy as np
import torch

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
