"""Refitting what depends on a bank's entries after they changed (bank/enroll.py calls it).

`refit()` is the single place that knows which fitted parts of a bank depend on its entries:
gamma and the discriminant head's knobs (kept, or re-chosen by stratified k-fold CV on the
bank), the head itself (bank/discriminant.py, refitted in closed form) and the open-set thresholds
(recalibrated on held-out folds, or kept). The feature transform is always kept: refitting it
would need the raw encoder features of the whole bank, which the file does not hold.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import copy
from typing import Any, Literal, get_args

import numpy as np
import torch

from point_gn_ros.bank.discriminant import (CovarianceFit, ScatterStats, check_policy as
                                            check_debias, fit_head, fit_ridge, lda_from_means,
                                            taught_shares, vote_to_z)
from point_gn_ros.bank.model import Head
from point_gn_ros.bank.selection import (DEFAULT_GAMMAS, calibrate_novelty, calibrate_unknown,
                                         select)
from point_gn_ros.bank.store import FeatureBank, rounded_head, stored_rows
from point_gn_ros.core.augment import variants_per_example
from point_gn_ros.errors import PointGNError

# Cosine (in the bank's transformed space) at or above which two examples are reported as
# near-duplicates: the same scan sent twice, or a frame that did not move.
DUPLICATE_COSINE = 0.9995
# 'auto' refits gamma by CV only on banks up to this many entries: on the 9,843-entry default
# bank a CV pass costs seconds and the choice is dominated by the existing classes anyway.
AUTO_CV_MAX_ENTRIES = 2000
# LDA bias of a class that cannot be predicted (below min_examples): finite, never wins.
_ABSENT_BIAS = -1e4

GammaPolicy = Literal['keep', 'cv', 'auto']
LdaPrior = Literal['entries', 'balanced', 'typical']
LDA_PRIORS: tuple[str, ...] = get_args(LdaPrior)
CalibrationPolicy = Literal['keep', 'recalibrate', 'auto']


class RefitError(PointGNError):
    """No class of the bank can be predicted under the policy."""


@dataclass(frozen=True)
class RefitPolicy:
    """What `refit()` re-decides after the bank's entries changed.

    gamma: 'keep' the bank's gamma, 'cv' re-choose it by stratified k-fold CV over the bank's
    gamma grid, 'auto' = 'cv' when every predictable class has >= `folds` examples and the
    bank has <= cv_max_entries entries, else 'keep'.
    calibration (open-set threshold): 'recalibrate' from held-out CV scores, 'keep' the stored
    one, 'auto' = recalibrate exactly when gamma was re-chosen by CV (the scores come free).
    min_examples: classes with fewer examples are kept in the bank but not predicted (see
    `active_view`) and do not take part in the fit.
    lda_prior: the LDA class priors of the refitted head: 'entries' (each class's share of
    the bank's entries, as built), 'balanced' (equal priors: a 5-example class is not
    penalised against 250-example ones; class sizes reflect how many examples were
    collected, not how often a class is seen) or 'typical' (the built classes keep their
    entry shares, so their answers do not move; each enrolled class, one not in the build's
    provenance, gets the mean share of a built class).
    lda_debias: share f of the mean-noise correction a wide LDA gives each enrolled class
    (one not in the build's provenance): its LDA bias += f tr(Sigma_a^-1 Sigma) / (2 n), n
    its entries (bank/discriminant.py `lda_noise_trace`). 0 (default): none; built classes never.
    lda_steal_budget: rho > 0 makes lda_debias a cap: each enrolled class gets the largest
    share <= lda_debias whose predicted steal rate from the built classes is <= rho
    (bank/discriminant.py). 0 (default): every enrolled class gets lda_debias.
    """

    gamma: GammaPolicy = 'auto'
    calibration: CalibrationPolicy = 'auto'
    min_examples: int = 1
    folds: int = 5
    cv_max_entries: int = AUTO_CV_MAX_ENTRIES
    duplicate_cosine: float = DUPLICATE_COSINE
    lda_prior: LdaPrior = 'entries'
    lda_debias: float = 0.0
    lda_steal_budget: float = 0.0

    def __post_init__(self) -> None:
        check_debias(self.lda_debias, self.lda_steal_budget)
        if self.lda_prior not in LDA_PRIORS:
            raise ValueError(f'lda_prior must be one of {", ".join(LDA_PRIORS)}, got '
                             f'{self.lda_prior!r}')
        if self.gamma not in ('keep', 'cv', 'auto'):
            raise ValueError(f'gamma policy must be keep, cv or auto, got {self.gamma!r}')
        if self.calibration not in ('keep', 'recalibrate', 'auto'):
            raise ValueError(f'calibration policy must be keep, recalibrate or auto, got '
                             f'{self.calibration!r}')
        if self.min_examples < 1 or self.folds < 2:
            raise ValueError('min_examples must be >= 1 and folds >= 2')


def copy_meta(meta: dict[str, Any]) -> dict[str, Any]:
    """A deep copy of bank metadata (the enrollment log is a FeatureBank field, not in it)."""
    return copy.deepcopy(meta)


def example_counts(bank: FeatureBank) -> torch.Tensor:
    """Examples per class (C,) int64: entries, less the extra frames of augmented enrollments.

    An example enrolled with augmentation (core/augment.py) is k entries; the bank's meta
    `augmented_entries` field {class: entries beyond one per example} records the difference.
    """
    counts = torch.bincount(bank.labels, minlength=bank.num_classes)
    for name, extra in bank.augmented_entries.items():
        if name in bank.class_names:
            counts[bank.class_names.index(name)] -= int(extra)
    return counts


def example_groups(bank: FeatureBank) -> np.ndarray | None:
    """(N,) int64 group per entry (the k frames of an augmented example share one), or None.

    None when nothing was augmented (every entry is its own example).

    Rebuilt from the enrollment log: an add appends its rows example-major at the end, a
    removal drops the whole class, so a class's rows are its built rows, then each add since
    its last removal in log order. CV (`refit`) keeps a group in one fold: a held-out example
    must not be matched by its own mirror. A class whose log does not add up stays ungrouped.
    """
    aug = bank.augmented_entries
    if not aug:
        return None
    labels = bank.labels.numpy()
    groups = np.arange(len(labels))
    for name in aug:
        if name not in bank.class_names:
            continue
        rows = np.flatnonzero(labels == bank.class_names.index(name))
        adds: list[tuple[int, int]] = []
        for e in bank.enrollments:
            if e.class_name == name:
                adds = [] if e.action == 'remove' else [
                    *adds, (e.count, variants_per_example(e.augment or 'none'))]
        pos = len(rows) - sum(n for n, _ in adds)
        if pos < 0:
            continue
        for n, k in adds:
            groups[rows[pos:pos + n]] = rows[pos + (np.arange(n) // k) * k]
            pos += n
    return groups


def active_view(bank: FeatureBank, min_examples: int) -> FeatureBank:
    """The bank a classifier should use: entries of classes with >= min_examples examples.

    Class names (and so class ids) are unchanged; a class below the minimum simply gets no
    votes. Returns `bank` itself when every class qualifies (the common case: no copy).
    """
    ok = example_counts(bank) >= min_examples
    if bool(ok.all()):
        return bank
    keep = ok[bank.labels]
    if not bool(keep.any()):
        raise RefitError(f'no class has {min_examples} example(s) yet: nothing to predict')
    views = None
    if bank.views is not None:     # the same classes in the scan section (counted here)
        vkeep = ok[bank.views.labels]
        views = replace(bank.views, features=bank.views.features[vkeep],
                        labels=bank.views.labels[vkeep],
                        head=_head_subset(bank.views.head, vkeep))
    return replace(bank, features=bank.features[keep], labels=bank.labels[keep], views=views,
                   head=_head_subset(bank.head, keep))


def refit(bank: FeatureBank, policy: RefitPolicy = RefitPolicy(),
          stats: ScatterStats | None = None) -> tuple[FeatureBank, bool]:
    """Re-decide what depends on the bank's entries -> (new bank, whether rows were re-whitened).

    The single hook where a bank's fitted parts are refreshed after its entries changed
    (meta['refit'] records what was done):
    - gamma and the head's knobs (whitening / LDA shrinkage, fusion weight, temperature) are
      kept, or re-chosen by stratified k-fold CV on the bank (policy.gamma);
    - the head (bank/model.py) is refitted in closed form on the bank's entries: with kept
      knobs, the LDA class means, priors and pooled covariance (the vote's whitening is kept,
      so stored rows do not move); after CV, the whole head, and every row is re-whitened;
    - the open-set thresholds are recalibrated on held-out folds or kept (policy.calibration).
    Classes below policy.min_examples take no part and can never win (see `active_view`).
    The feature transform is always kept (see the module docstring). stats: the bank's
    ScatterStats (same rows), which make the kept-knobs LDA refit cheap.
    """
    head = bank.head
    view = active_view(bank, policy.min_examples)
    meta = copy_meta(bank.meta)
    labels_all = view.labels.numpy()
    present = np.flatnonzero(np.bincount(labels_all, minlength=bank.num_classes) > 0)
    counts = example_counts(view).numpy()                 # examples, not augmented frames
    groups = example_groups(view)                         # whole classes: rows keep order
    compact = torch.from_numpy(np.searchsorted(present, labels_all))
    gamma, gamma_reason, sel = bank.gamma, 'kept', None
    wide_counts, shares = None, None       # a kept wide LDA: its classes' entries (debias)
    want_cv = policy.gamma == 'cv' or (
        policy.gamma == 'auto' and len(view) <= policy.cv_max_entries
        and counts[present].min() >= policy.folds)
    grid = meta.get('selection', {}).get('grid', {})
    folds = _folds(counts[present], policy.folds)
    z_view = None
    if want_cv and len(present) >= 2:
        z_view = vote_to_z(view.features, head)
        sel = select(z_view, np.asarray(compact), len(present),
                     tuple(grid.get('gammas') or DEFAULT_GAMMAS), ('none',), (None,), folds,
                     alphas=tuple(grid.get('alphas') or ()),
                     lda_alphas=tuple(grid.get('lda_alphas') or grid.get('alphas') or ()),
                     weights=tuple(grid.get('weights') or (0.0,)), groups=groups)
        gamma, gamma_reason = float(sel.gamma), (
            f'{sel.folds_used}-fold CV on the bank: {100 * sel.cv_accuracy:.1f} %')
        new_head = rounded_head(fit_head(z_view, compact, len(present), sel.gamma, sel.alpha,
                                         sel.lda_alpha, sel.fusion_weight, sel.temperature),
                                meta.get('matrix_dtype', 'float32'))
        meta['head'] = {**meta.get('head', {}), **sel.head_meta()}
    else:
        if want_cv:
            gamma_reason = 'kept (CV needs two classes)'
        elif policy.gamma == 'auto':
            gamma_reason = 'kept (auto: bank too large or a class too small for CV)'
        new_head = head
        if head is not None and head.lda_wide:
            # Wide LDA: the class means (updated by the add) under the kept precision.
            n = torch.from_numpy(np.bincount(labels_all, minlength=bank.num_classes)[present])
            coef, bias = lda_from_means(head.lda_means[torch.from_numpy(present)],
                                        head.lda_precision, n)
            new_head, wide_counts = replace(head, lda_coef=coef, lda_bias=bias), n
        elif head is not None and head.lda_coef is not None:
            # Closed-form LDA refit with the CV-chosen shrinkage kept.
            lda_alpha = float(meta.get('head', {}).get('lda_alpha') or 0.0)
            lda = stats.lda(present, lda_alpha) if stats is not None else None
            if lda is None:
                z_view = vote_to_z(view.features, head)
                lda = CovarianceFit.fit(z_view, compact, len(present)).lda(lda_alpha)
            coef, bias = lda
            new_head = replace(head, lda_coef=coef, lda_bias=bias)
    if new_head is not None and new_head.lda_bias is not None and policy.lda_prior != 'entries':
        # Both fits above use entry-share priors: swap them (bank/refit.py RefitPolicy).
        new_head = replace(new_head, lda_bias=new_head.lda_bias + _prior_shift(
            policy.lda_prior, np.bincount(labels_all)[present], _taught(bank, meta, present)))
    if wide_counts is not None and policy.lda_debias > 0:   # classes enrollments created
        new_head, shares = enrolled_debias(new_head, wide_counts, present, bank, meta, policy)
    if new_head is not None:
        new_head = _expand_lda(replace(new_head, gamma=gamma), present, bank.num_classes)
    rewhiten = sel is not None and (
        (head is not None and head.whiten is not None)
        or (new_head is not None and new_head.whiten is not None))
    features = bank.features
    if rewhiten:
        z_all = vote_to_z(bank.features, head)
        features = z_all if new_head is None else new_head.vote_space(z_all)
    ridge_how = None
    if head is not None and head.ridge_coef is not None:   # the ridge's knobs are kept
        new_head, features, ridge_how = _refit_ridge(
            head, new_head or Head(gamma), features, bank.labels, bank.num_classes, rewhiten,
            str(meta.get('stored_dtype', 'float32')))
    if new_head is not None and new_head.is_plain_vote and new_head.temperature == 1.0:
        new_head = None
    cal_reason = _recalibrate(meta, bank, view, compact, present, gamma, new_head, sel, policy,
                              folds, z_view, groups)
    meta['refit'] = {'version': int(meta.get('bank_version', 0)), 'gamma': gamma,
                     'gamma_reason': gamma_reason,
                     'head': ('none (plain kernel vote)' if new_head is None else
                              'refitted in closed form' + (', knobs by CV' if sel else
                                                           ', knobs kept')),
                     'calibration_reason': cal_reason, 'min_examples': policy.min_examples,
                     'lda_prior': policy.lda_prior,
                     'lda_debias': policy.lda_debias,
                     'lda_steal_budget': policy.lda_steal_budget,
                     **({} if shares is None else {'lda_debias_shares': shares}),
                     'predicted_classes': int(len(present)),
                     **({} if ridge_how is None else {'ridge': ridge_how})}
    return replace(bank, features=features, gamma=gamma, meta=meta, head=new_head), rewhiten


def enrolled_debias(head: Head, n: torch.Tensor, present: np.ndarray, bank: FeatureBank,
                    meta: dict, policy: RefitPolicy) -> tuple[Head, dict[str, float]]:
    """A kept wide LDA with its enrolled classes' mean-noise correction (bank/discriminant.py).

    head: over the present classes (class ids `present`), priors applied; n: their entries;
    enrolled = not in meta's build provenance -> (head, share per enrolled class by name).
    """
    taught = torch.from_numpy(_taught(bank, meta, present))
    f = taught_shares(head.lda_means[torch.from_numpy(present)], head.lda_coef, head.lda_bias,
                      head.lda_precision, float(meta.get('head', {}).get('lda_alpha') or 0.0),
                      head.lda_trace, n, taught, policy.lda_debias, policy.lda_steal_budget)
    bias = head.lda_bias + (f * head.lda_trace / (2 * n.double())).float()
    return replace(head, lda_bias=bias), {bank.class_names[c]: float(f[i])
                                          for i, c in enumerate(present) if taught[i]}


def _taught(bank: FeatureBank, meta: dict, present: np.ndarray) -> np.ndarray:
    """(len(present),) bool: the classes an enrollment created (not in the build's provenance)."""
    built = bank.built_classes
    return np.array([bank.class_names[c] not in built for c in present], dtype=bool)


def _prior_shift(prior: LdaPrior, n: np.ndarray, taught: np.ndarray) -> torch.Tensor:
    """Log-prior change from entry shares n / sum(n) to `prior`'s, per class: (C,) float32.

    n: (C,) entries of the present classes; taught: (C,) bool, the enrolled ones.
    'balanced': 1 / C each. 'typical': the built classes keep n_c / N, an enrolled class gets
    their mean share, (sum of built n) / (B N) for B built classes (the priors need not sum
    to one: the softmax over classes normalises them).
    """
    n = torch.from_numpy(np.asarray(n)).double()
    if prior == 'balanced':
        return ((n.sum() / n).log() - np.log(len(n))).float()
    built = ~torch.from_numpy(np.asarray(taught, dtype=bool))
    if not bool(built.any()):                     # nothing built left: as 'balanced'
        return _prior_shift('balanced', n.numpy(), taught)
    typical = n[built].sum() / int(built.sum())   # a built class's mean entries
    return torch.where(built, 0.0, (typical / n).log()).float()


def _head_subset(head: Head | None, keep: torch.Tensor | np.ndarray) -> Head | None:
    """The head with the ridge coefficients of the kept rows (bool (N,)) only.

    Heads without a ridge: as they are.
    """
    if head is None or head.ridge_coef is None:
        return head
    return replace(head, ridge_coef=head.ridge_coef[
        torch.as_tensor(keep, dtype=torch.bool)[:len(head.ridge_coef)]])


def _refit_ridge(head: Head, new_head: Head, rows: torch.Tensor, labels: torch.Tensor,
                 num_classes: int, moved: bool, dtype: str) -> tuple[Head, torch.Tensor, str]:
    """The kernel ridge part of `refit`, the other knobs of new_head already set.

    head: the section's head before; its coefficients are kept only if rows (N, d) are still
    the rows they were fitted on (same count, no class removed or added), else refitted in
    full on the rows as the file stores them (moved: rows were re-whitened; appended rows
    are stored values already). -> (new_head, those rows, what was done). A published bank
    version always has its ridge term fitted.
    """
    same = not moved and head.ridge_coef.shape[0] == len(rows) and \
        head.ridge_coef.shape[1] == num_classes
    knobs = dict(ridge_gamma=head.ridge_gamma, ridge_lambda=head.ridge_lambda,
                 ridge_weight=head.ridge_weight)
    if same:
        return replace(new_head, ridge_coef=head.ridge_coef, **knobs), rows, 'kept'
    if moved:
        rows = stored_rows(rows, dtype)
    coef = fit_ridge(rows, labels, num_classes, head.ridge_gamma, head.ridge_lambda)
    return replace(new_head, ridge_coef=coef, **knobs), rows, 'refitted in full'


def _expand_lda(head: Head, present: np.ndarray, num_classes: int) -> Head:
    """LDA rows fitted on the present classes -> one row per class; absent classes never win."""
    if head.lda_coef is None or head.lda_coef.shape[0] == num_classes:
        return head
    coef = torch.zeros(num_classes, head.lda_coef.shape[1])
    bias = torch.full((num_classes,), _ABSENT_BIAS)
    idx = torch.from_numpy(present)
    coef[idx], bias[idx] = head.lda_coef, head.lda_bias
    return replace(head, lda_coef=coef, lda_bias=bias)


def _recalibrate(meta: dict, bank: FeatureBank, view: FeatureBank, compact: torch.Tensor,
                 present: np.ndarray, gamma: float, head: Head | None, sel: Any,
                 policy: RefitPolicy, folds: int, z_view: torch.Tensor | None,
                 groups: np.ndarray | None = None) -> str:
    """Update meta's open-set calibration per policy; -> what was done."""
    calib = meta.get('unknown_calibration')
    recal = policy.calibration == 'recalibrate' or (policy.calibration == 'auto'
                                                    and sel is not None)
    if not recal or len(present) < 2:
        return 'kept' if calib else 'none'
    if sel is None and head is not None and head.lda_wide:
        # Held-out scores of a wide LDA need every entry's standardised row: not in the file.
        return 'kept (a wide-LDA head cannot be re-scored from the stored rows)'
    if sel is None:      # held-out scores with every knob pinned at its kept value
        hm = meta.get('head', {})
        z_view = vote_to_z(view.features, bank.head) if z_view is None else z_view
        alpha, lda_alpha = hm.get('alpha'), hm.get('lda_alpha')
        w = float(head.fusion_weight) if head is not None else 0.0
        sel = select(z_view, np.asarray(compact), len(present), (gamma,), ('none',), (None,),
                     folds, alphas=() if alpha is None else (float(alpha),),
                     lda_alphas=() if lda_alpha is None or w == 0 else (float(lda_alpha),),
                     weights=(w,), whiten_options=(alpha is not None,), groups=groups)
    rate = float((calib or {}).get('false_reject_rate', 0.05))
    # Whatever measure each stored rule thresholds stays the same (the unknown rule is the
    # calibrated probability by default; older banks thresholded novelty there).
    novelty = calibrate_novelty(sel.heldout_novelty, rate) \
        if sel.heldout_novelty is not None else None
    probability = calibrate_unknown(sel.heldout_scores, rate)
    if (calib or {}).get('measure') == 'novelty' and novelty is not None:
        meta['unknown_calibration'] = novelty
    else:
        meta['unknown_calibration'] = probability
    for key, value in (('novelty_calibration', novelty),
                       ('probability_calibration', probability)):
        if key in meta and value is not None:
            meta[key] = value
    return f'recalibrated ({100 * rate:g} % false rejects on held-out folds)'


def _folds(counts: np.ndarray, folds: int) -> int:
    """Fewer folds when the smallest class is small (>= 2 so every fold trains)."""
    return int(max(2, min(folds, int(counts.min()))))
