"""Enrolled classes' LDA mean-noise correction under a steal budget (bank/discriminant.py)."""

import numpy as np
import pytest
import torch

from point_gn_ros.bank.discriminant import steal_rates, taught_shares
from point_gn_ros.bank.discriminant import lda_from_means

D, ALPHA = 12, 0.1


def _lda(taught_mean: torch.Tensor) -> tuple:
    """Three built classes of 200 entries and one taught class of 5 under a shrunk LDA."""
    g = torch.Generator().manual_seed(0)
    a = torch.randn(D, D, generator=g, dtype=torch.float64)
    sigma = a @ a.T / D + 0.1 * torch.eye(D, dtype=torch.float64)
    tau = float(sigma.diagonal().mean())
    precision = torch.linalg.inv((1 - ALPHA) * sigma + ALPHA * tau * torch.eye(D,
                                                                            dtype=torch.float64))
    means = torch.cat([2.0 * torch.randn(3, D, generator=g, dtype=torch.float64),
                       taught_mean[None]])
    counts = torch.tensor([200.0, 200.0, 200.0, 5.0], dtype=torch.float64)
    coef, bias = lda_from_means(means, precision, counts)
    return sigma, precision, means, counts, coef.double(), bias.double()


def test_steal_rate_matches_sampling_under_the_lda_model() -> None:
    base = _lda(torch.zeros(D))
    sigma, precision, means, counts, coef, bias = _lda(base[2][0] * 0.7)   # near class 0
    built = torch.tensor([True, True, True, False])
    shifts = torch.tensor([3.0, 5.0, 8.0])
    rates = steal_rates(means, coef, bias, precision, ALPHA, counts, built, 3, shifts)
    chol = torch.linalg.cholesky(sigma)
    g = torch.Generator().manual_seed(1)
    for s, rate in zip(shifts.tolist(), rates.tolist(), strict=True):
        got = 0.0
        for k in range(3):
            x = means[k] + torch.randn(40_000, D, generator=g, dtype=torch.float64) @ chol.T
            logits = x @ coef.T + bias
            got += (1 / 3) * float((logits[:, 3] + s > logits[:, k]).double().mean())
        assert abs(got - rate) < 0.01, (s, got, rate)
    assert rates[0] < rates[1] < rates[2] and rates[0] > 0.01    # a real, rising rate


def test_budget_gives_a_class_near_a_built_one_less_than_a_distinct_one() -> None:
    ref = _lda(torch.zeros(D))[2]
    near, far = _lda(ref[0] * 0.8), _lda(ref[0] * 0.8 + 6.0)
    taught = torch.tensor([False, False, False, True])
    trace = 30.0
    shares = {}
    for name, (_, precision, means, counts, coef, bias) in (('near', near), ('far', far)):
        f = taught_shares(means, coef, bias, precision, ALPHA, trace, counts, taught, 2.0, 0.01)
        assert torch.equal(f[:3], torch.zeros(3, dtype=torch.float64))      # built: none
        shares[name] = float(f[3])
        # within budget at the share given, over it one grid step further (or at the cap)
        at = steal_rates(means, coef, bias, precision, ALPHA, counts, ~taught, 3,
                         torch.tensor([shares[name], shares[name] + 0.05]) * trace / 10)
        assert at[0] <= 0.01 and (shares[name] == 2.0 or at[1] > 0.01)
        uniform = taught_shares(means, coef, bias, precision, ALPHA, trace, counts, taught,
                                1.5, 0.0)
        assert float(uniform[3]) == 1.5 and float(uniform[:3].abs().sum()) == 0
    assert shares['near'] < shares['far'] == 2.0
    assert 0 < shares['near']


@pytest.mark.parametrize('share, budget', [(-0.1, 0.0), (2.5, 0.0), (1.0, -1e-3), (1.0, 0.6),
                                           (np.nan, 0.0)])
def test_policy_ranges_are_checked(share: float, budget: float) -> None:
    from point_gn_ros.bank.refit import RefitPolicy
    with pytest.raises(ValueError, match='lda_debias|lda_steal_budget'):
        RefitPolicy(lda_debias=share, lda_steal_budget=budget)
