"""Kernel ridge term of the head: a closed-form regression of class indicators on the bank.

The kernel vote gives every bank entry the same say. Kernel ridge regression (KRR) on the
same kernel, fitted in closed form from the bank alone, gives each entry its own
coefficients instead, so that the bank's entries reproduce their own labels:

  k(u, u')  = exp(g (cos(u, u') - 1))           = exp(-g |u - u'|^2 / 2) on unit rows
  A         = (K + lambda I)^-1 Y                (N, C); K (N, N) over the bank's rows,
                                                  Y the one-hot labels
  ridge_c   = sum_i k(q, u_i) A_ic               (B, C) for queries q

The head adds ridge_weight x ridge to its fused scores (bank/head.py). g is small (0.25-2,
chosen by CV) where the vote's gamma is 20-160: the regression needs a wide kernel to have
anything to fit. A is fitted on the rows exactly as the bank file stores them (int4 rounding
moves K far enough to undo the fit: a ridge fitted on float rows and queried against int4
rows lost 2-15 points by CV), so builder and enrollment pass the stored rows.

An enrollment cannot keep A cheaply: solving only for the new rows with the old ones held
fixed (the m x m block step) cost held-out complete objects 1.0-1.3 points and, with the
default's wide kernel, pulled others to the enrolled classes, while the full refit cost
nothing (benchmarks/log); the full refit takes seconds on 10k entries. So an enrollment
(`RefitPolicy.ridge`) either refits A in full ('full': `point_gn bank add`), or serves the
head without the term at once, with that head's own CV temperature, and marks the full refit
pending ('off': the node; bank/live.py runs `refit_pending` in the background and publishes
the result as the next version). A removal does the same.
"""

from __future__ import annotations

import copy
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
import torch

from point_gn_ros.bank.quant import quantized

if TYPE_CHECKING:
    from point_gn_ros.bank.head import Head
    from point_gn_ros.bank.store import FeatureBank

# Largest bank a ridge is fitted for: its (N, N) float32 kernel is 1 GB at 16,000 entries.
MAX_ENTRIES = 16000
# Kernel rows built per block when fitting.
_BLOCK = 2048


def ridge_scores(sims: torch.Tensor, coef: torch.Tensor, gamma: float) -> torch.Tensor:
    """sims: (B, N) cosines to the bank rows; coef: (N, C) -> (B, C) float32 ridge scores.

    The sum runs in float64: coefficients reach ~100 with cancelling signs. Pass coef as
    float64 to skip a per-call copy (Head.to does).
    """
    return (torch.exp(gamma * (sims.double() - 1.0)) @ coef.double()).float()


def fit(rows: torch.Tensor, labels: torch.Tensor, num_classes: int, gamma: float,
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
        for i in range(0, n, _BLOCK):      # in place, a block of rows at a time
            torch.mm(r[i:i + _BLOCK], r.T, out=k[i:i + _BLOCK])
        k.sub_(1.0).mul_(gamma).exp_()
        k.diagonal().add_(lam)
        chol, info = torch.linalg.cholesky_ex(k, out=(k, torch.empty((), dtype=torch.int32)))
        if int(info) == 0:
            return torch.cholesky_solve(y.to(dtype), chol).float()
        del k, chol
    raise ValueError(f'kernel ridge: K + {lam:g} I is not positive definite')


def cv_scores(u_train: torch.Tensor, u_val: torch.Tensor, labels: torch.Tensor,
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


def stored_rows(rows: torch.Tensor, dtype: str) -> torch.Tensor:
    """Unit rows (N, d) as a bank file of `dtype` gives them back (bank/quant.py, load)."""
    return torch.nn.functional.normalize(
        torch.from_numpy(quantized(rows, dtype).astype(np.float32)), dim=1)


def head_subset(head: 'Head | None', keep: torch.Tensor | np.ndarray) -> 'Head | None':
    """The head with the ridge coefficients of the kept rows (bool (N,)) only.

    Heads without a ridge: as they are.
    """
    if head is None or head.ridge_coef is None:
        return head
    # Rows appended by an enrollment not yet refitted have no coefficients: only the first.
    return replace(head, ridge_coef=head.ridge_coef[
        torch.as_tensor(keep, dtype=torch.bool)[:len(head.ridge_coef)]])


def refit(head: 'Head', new_head: 'Head', rows: torch.Tensor, labels: torch.Tensor,
          num_classes: int, moved: bool, dtype: str, mode: str, meta: dict
          ) -> tuple['Head', torch.Tensor, str]:
    """The ridge part of bank/refit.py's refit, the other knobs of new_head already set.

    head: the section's head before (its coefficients are kept only if rows (N, d) are still
    the rows they were fitted on: same count, no class removed or added); moved:
    rows were re-whitened; mode: RefitPolicy.ridge; meta: the section's metadata (updated:
    head.ridge.pending). -> (new_head, rows as the file stores them, what was done).
    """
    same = not moved and head.ridge_coef.shape[0] == len(rows) and \
        head.ridge_coef.shape[1] == num_classes
    if same:
        kept = replace(new_head, ridge_coef=head.ridge_coef, ridge_gamma=head.ridge_gamma,
                       ridge_lambda=head.ridge_lambda, ridge_weight=head.ridge_weight)
        return kept, rows, 'kept'
    settings = meta.setdefault('head', {}).setdefault('ridge', {})
    if mode == 'full':
        if moved:    # re-whitened rows: as the file will store them (appended ones already are)
            rows = stored_rows(rows, dtype)
        settings['pending'] = False
        return replace(new_head, ridge_coef=fit(rows, labels, num_classes, head.ridge_gamma,
                                                head.ridge_lambda),
                       ridge_gamma=head.ridge_gamma, ridge_lambda=head.ridge_lambda,
                       ridge_weight=head.ridge_weight), rows, 'refitted in full'
    settings.update({'pending': True, 'gamma': head.ridge_gamma, 'lambda': head.ridge_lambda,
                     'weight': 0.0, 'weight_pending': head.ridge_weight,
                     'temperature': settings.get('temperature') or head.temperature})
    t0 = settings.get('temperature_without')
    off = replace(new_head, ridge_coef=None, ridge_weight=0.0,
                  temperature=float(t0) if t0 else new_head.temperature)
    return off, rows, 'off until refitted in full (pending)'


def is_pending(meta: dict) -> bool:
    """Whether a section's ridge term waits for its full refit (`refit` mode 'off')."""
    return bool(meta.get('head', {}).get('ridge', {}).get('pending'))


def refit_pending(bank: 'FeatureBank') -> 'FeatureBank':
    """The section with its pending ridge term fitted in full on its rows, else itself.

    The rows are the stored ones already (enrollment appends rounded rows), so the file's
    values do not change. Restores the term's weight and temperature; bumps the version.
    """
    if not is_pending(bank.meta) or bank.head is None:
        return bank
    meta = copy.deepcopy(bank.meta)
    settings = meta['head']['ridge']
    g, lam, w = (float(settings[k]) for k in ('gamma', 'lambda', 'weight_pending'))
    coef = fit(bank.features, bank.labels, bank.num_classes, g, lam)
    settings.update(pending=False, weight=w)
    settings.pop('weight_pending', None)
    meta['bank_version'] = int(meta.get('bank_version', 0)) + 1
    meta.setdefault('refit', {})['ridge'] = 'refitted in full (pending refit)'
    head = replace(bank.head, ridge_coef=coef, ridge_gamma=g, ridge_lambda=lam, ridge_weight=w,
                   temperature=float(settings.get('temperature') or bank.head.temperature))
    return replace(bank, head=head, meta=meta)
