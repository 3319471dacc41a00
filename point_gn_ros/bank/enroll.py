"""Online enrollment: add examples to a bank, remove a class, refit what depends on the bank.

Every operation is copy-on-write: it returns a NEW FeatureBank and never mutates the one it was
given, so a reader holding the old bank (the node's worker, mid micro-batch) keeps computing
with one consistent version. `LiveBank` (bank/live.py) serialises writers and swaps versions.

The bank stores transformed features (bank/store.py), so new examples go through the bank's own
transform; the transform itself is kept (refitting it would need the raw features of the whole
bank, which the file does not hold). What is refitted lives in `refit()`, the single place that
knows which knobs depend on the bank's entries.

Metadata added (JSON, in the bank file):
  bank_version   int, +1 per add/remove (0 = as built)
  enrollments    list of {version, action, class, count, time, source, near_duplicates}
  refit          how gamma / calibration were last decided {version, gamma, calibration, ...}
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from datetime import datetime, UTC
import copy
import os
import threading
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from point_gn_ros.bank.head import CovarianceFit, Head, fit_head
from point_gn_ros.bank.selection import (DEFAULT_GAMMAS, calibrate_novelty, calibrate_unknown,
                                         select)
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.errors import PointGNError

# Cosine (in the bank's transformed space) at or above which two examples are reported as
# near-duplicates: the same scan sent twice, or a frame that did not move.
DUPLICATE_COSINE = 0.9995
# 'auto' refits gamma by CV only on banks up to this many entries: on the 9,843-entry default
# bank a CV pass costs seconds and the choice is dominated by the existing classes anyway.
AUTO_CV_MAX_ENTRIES = 2000
# LDA bias of a class that cannot be predicted (below min_examples): finite, never wins.
_ABSENT_BIAS = -1e4
# At most this many near-duplicate pairs are listed (the count is always exact).
_MAX_LISTED = 20

GammaPolicy = Literal['keep', 'cv', 'auto']
CalibrationPolicy = Literal['keep', 'recalibrate', 'auto']


class EnrollError(PointGNError):
    """An enrollment request the bank cannot take (unknown class, wrong feature size...)."""


@dataclass(frozen=True)
class RefitPolicy:
    """What `refit()` re-decides after the bank's entries changed.

    gamma: 'keep' the bank's gamma, 'cv' re-choose it by stratified k-fold CV over the bank's
    gamma grid, 'auto' = 'cv' when every predictable class has >= `folds` examples and the
    bank has <= cv_max_entries entries, else 'keep'.
    calibration (open-set threshold): 'recalibrate' from held-out CV scores, 'keep' the stored
    one, 'auto' = recalibrate exactly when gamma was re-chosen by CV (the scores come free).
    min_examples: classes with fewer entries are kept in the bank but not predicted (see
    `active_view`) and do not take part in the fit.
    """

    gamma: GammaPolicy = 'auto'
    calibration: CalibrationPolicy = 'auto'
    min_examples: int = 1
    folds: int = 5
    cv_max_entries: int = AUTO_CV_MAX_ENTRIES
    duplicate_cosine: float = DUPLICATE_COSINE

    def __post_init__(self) -> None:
        if self.gamma not in ('keep', 'cv', 'auto'):
            raise ValueError(f'gamma policy must be keep, cv or auto, got {self.gamma!r}')
        if self.calibration not in ('keep', 'recalibrate', 'auto'):
            raise ValueError(f'calibration policy must be keep, recalibrate or auto, got '
                             f'{self.calibration!r}')
        if self.min_examples < 1 or self.folds < 2:
            raise ValueError('min_examples must be >= 1 and folds >= 2')


@dataclass(frozen=True)
class NearDuplicate:
    """New example `index` is within `cosine` of `other` (a bank entry or another new one)."""

    index: int
    other: str          # 'bank #i (class)' or 'new #j'
    cosine: float
    same_class: bool


@dataclass(frozen=True)
class EnrollResult:
    """The new bank and what happened (for logs, diagnostics and the CLI)."""

    file: BankFile
    action: Literal['add', 'remove']
    class_name: str
    count: int                       # examples added / entries removed
    new_class: bool = False
    duplicates: tuple[NearDuplicate, ...] = ()
    duplicate_count: int = 0
    refit: dict[str, Any] = field(default_factory=dict)

    @property
    def bank(self) -> FeatureBank:
        return self.file.bank

    @property
    def version(self) -> int:
        return bank_version(self.file.bank)

    def describe(self) -> str:
        verb = 'added' if self.action == 'add' else 'removed'
        what = 'example(s) to new class' if self.new_class else (
            'example(s) of' if self.action == 'add' else 'entries of class')
        text = (f'bank v{self.version}: {verb} {self.count} {what} {self.class_name!r}; '
                f'gamma {self.bank.gamma:g} ({self.refit.get("gamma_reason", "?")}), '
                f'threshold {self.refit.get("calibration_reason", "?")}')
        if self.duplicate_count:
            text += f'; {self.duplicate_count} near-duplicate example(s)'
        return text


# ------------------------------------------------------------------------------ queries


def bank_version(bank: FeatureBank) -> int:
    """The bank's version counter: 0 as built, +1 per enrollment or removal."""
    return int(bank.meta.get('bank_version', 0))


def class_counts(bank: FeatureBank) -> dict[str, int]:
    """Entries per class name, in class-id order."""
    counts = torch.bincount(bank.labels, minlength=bank.num_classes).tolist()
    return dict(zip(bank.class_names, (int(n) for n in counts), strict=True))


def predictable(bank: FeatureBank, min_examples: int) -> list[str]:
    """Names of the classes with at least min_examples entries."""
    return [c for c, n in class_counts(bank).items() if n >= min_examples]


def active_view(bank: FeatureBank, min_examples: int) -> FeatureBank:
    """The bank a classifier should use: entries of classes with >= min_examples only.

    Class names (and so class ids) are unchanged; a class below the minimum simply gets no
    votes. Returns `bank` itself when every class qualifies (the common case: no copy).
    """
    counts = torch.bincount(bank.labels, minlength=bank.num_classes)
    ok = counts >= min_examples
    if bool(ok.all()):
        return bank
    keep = ok[bank.labels]
    if not bool(keep.any()):
        raise EnrollError(f'no class has {min_examples} example(s) yet: nothing to predict')
    return replace(bank, features=bank.features[keep], labels=bank.labels[keep])


# ------------------------------------------------------------------------------ operations


@dataclass(frozen=True)
class BankFile:
    """A bank and the exact feature values its file holds (or will hold once saved).

    stored: (N, d) float16 or float32, the `features` array of the file. Invariant:
    bank.features == normalize(stored) row by row, computed as `FeatureBank.load` does, so
    save + load gives back the same bank bit for bit. (Re-casting the normalised features
    is not enough: rounding to float16 and re-normalising is not idempotent.)
    """

    bank: FeatureBank
    stored: np.ndarray

    @classmethod
    def load(cls, path: str | os.PathLike[str] | None = None,
             expected_config: Any = None) -> 'BankFile':
        """Read a bank file (None: the shipped default) keeping its stored feature values."""
        bank = FeatureBank.load(path, expected_config)
        with np.load(bank.path, allow_pickle=False) as z:
            stored = z['features']
        return cls(bank, stored)

    @classmethod
    def of(cls, bank: FeatureBank, dtype: str | None = None) -> 'BankFile':
        """Wrap a bank never saved: features re-derived from their rounded stored values."""
        dtype = dtype or bank.meta.get('stored_dtype', 'float32')
        stored = bank.features.cpu().numpy().astype(dtype)
        meta = dict(bank.meta, stored_dtype=dtype)
        return cls(replace(bank, features=_from_stored(stored), meta=meta), stored)

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Atomic write of exactly this bank (see `save_atomic`)."""
        return save_atomic(self, path)


def add_examples(bf: BankFile, features: torch.Tensor, class_name: str,
                 source: str = 'api', policy: RefitPolicy = RefitPolicy(),
                 when: datetime | None = None) -> EnrollResult:
    """Add encoder features of new examples under `class_name` (new or existing class).

    features: (M, D) float32 raw encoder output (D = the bank's encoder feature_dim), M >= 1.
    Returns a new bank (version + 1); `bf` is left untouched.
    """
    bank = bf.bank
    class_name = _check_name(class_name)
    if features.ndim != 2 or features.shape[0] == 0:
        raise EnrollError(f'expected (M, {bank.transform.in_dim}) features with M >= 1, got '
                          f'{tuple(features.shape)}')
    if features.shape[1] != bank.transform.in_dim:
        raise EnrollError(f'features have {features.shape[1]} dims, the bank encoder gives '
                          f'{bank.transform.in_dim}')
    if not bool(torch.isfinite(features).all()):
        raise EnrollError('features hold non-finite values')
    z_new = bank.transform(features.float().cpu())                  # (M, d) unit rows
    u_new = z_new if bank.head is None else bank.head.vote_space(z_new)
    stored_new = u_new.numpy().astype(bf.stored.dtype)
    new = _from_stored(stored_new)                                   # (M, d) unit rows
    names = list(bank.class_names)
    new_class = class_name not in names
    if new_class:
        names.append(class_name)
    cid = names.index(class_name)
    dups, n_dups = near_duplicates(new, bank, cid, policy.duplicate_cosine)
    feats = torch.cat([bank.features, new])
    labels = torch.cat([bank.labels, torch.full((len(new),), cid, dtype=torch.int64)])
    meta = _log(bank, 'add', class_name, len(new), source, when, near_duplicates=n_dups)
    out, moved = refit(replace(bank, features=feats, labels=labels, class_names=names,
                               meta=meta, path=None), policy)
    stored = np.concatenate([bf.stored, stored_new])
    return EnrollResult(_restore(out, stored, moved), 'add', class_name, len(new), new_class,
                        tuple(dups), n_dups, out.meta['refit'])


def remove_class(bf: BankFile, class_name: str, source: str = 'api',
                 policy: RefitPolicy = RefitPolicy(), when: datetime | None = None
                 ) -> EnrollResult:
    """Drop every entry of `class_name`; ids of the classes after it shift down by one."""
    bank = bf.bank
    if class_name not in bank.class_names:
        raise EnrollError(f'no class {class_name!r} in the bank (classes: '
                          f'{", ".join(bank.class_names)})')
    if bank.num_classes == 1:
        raise EnrollError(f'{class_name!r} is the only class: a bank cannot be empty')
    cid = bank.class_names.index(class_name)
    keep = bank.labels != cid
    labels = bank.labels[keep]
    labels = labels - (labels > cid).long()
    names = [n for n in bank.class_names if n != class_name]
    removed = int((~keep).sum())
    meta = _log(bank, 'remove', class_name, removed, source, when)
    out, moved = refit(replace(bank, features=bank.features[keep], labels=labels,
                               class_names=names, meta=meta, path=None), policy)
    return EnrollResult(_restore(out, bf.stored[keep.numpy()], moved), 'remove', class_name,
                        removed, False, (), 0, out.meta['refit'])


def refit(bank: FeatureBank, policy: RefitPolicy = RefitPolicy()) -> tuple[FeatureBank, bool]:
    """Re-decide what depends on the bank's entries -> (new bank, whether rows were re-whitened).

    The single hook where a bank's fitted parts are refreshed after its entries changed
    (meta['refit'] records what was done):
    - gamma and the head's knobs (whitening / LDA shrinkage, fusion weight, temperature) are
      kept, or re-chosen by stratified k-fold CV on the bank (policy.gamma);
    - the head (bank/head.py) is refitted in closed form on the bank's entries: with kept
      knobs, the LDA class means, priors and pooled covariance (the vote's whitening is kept,
      so stored rows do not move); after CV, the whole head, and every row is re-whitened;
    - the open-set thresholds are recalibrated on held-out folds or kept (policy.calibration).
    Classes below policy.min_examples take no part and can never win (see `active_view`).
    The feature transform is always kept (see the module docstring).
    """
    head = bank.head
    view = active_view(bank, policy.min_examples)
    meta = copy.deepcopy(bank.meta)
    labels_all = view.labels.numpy()
    counts = np.bincount(labels_all, minlength=bank.num_classes)
    present = np.flatnonzero(counts > 0)                  # class ids that take part
    compact = torch.from_numpy(np.searchsorted(present, labels_all))
    gamma, gamma_reason, sel = bank.gamma, 'kept', None
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
                     weights=tuple(grid.get('weights') or (0.0,)))
        gamma, gamma_reason = float(sel.gamma), (
            f'{sel.folds_used}-fold CV on the bank: {100 * sel.cv_accuracy:.1f} %')
        new_head = fit_head(z_view, compact, len(present), sel.gamma, sel.alpha, sel.lda_alpha,
                            sel.fusion_weight, sel.temperature)
        meta['head'] = {**meta.get('head', {}), **sel.head_meta()}
    elif want_cv:
        gamma_reason = 'kept (CV needs two classes)'
        new_head = head
    else:
        if policy.gamma == 'auto':
            gamma_reason = 'kept (auto: bank too large or a class too small for CV)'
        new_head = head
        if head is not None and head.lda_coef is not None:
            # Closed-form LDA refit with the CV-chosen shrinkage kept.
            z_view = vote_to_z(view.features, head)
            fit = CovarianceFit.fit(z_view, compact, len(present))
            coef, bias = fit.lda(float(meta.get('head', {}).get('lda_alpha') or 0.0))
            new_head = replace(head, lda_coef=coef, lda_bias=bias)
    if new_head is not None:
        new_head = _expand_lda(replace(new_head, gamma=gamma), present, bank.num_classes)
        if new_head.is_plain_vote and new_head.temperature == 1.0:
            new_head = None
    rewhiten = sel is not None and (
        (head is not None and head.whiten is not None)
        or (new_head is not None and new_head.whiten is not None))
    features = bank.features
    if rewhiten:
        z_all = vote_to_z(bank.features, head)
        features = z_all if new_head is None else new_head.vote_space(z_all)
    cal_reason = _recalibrate(meta, bank, view, compact, present, gamma, new_head, sel, policy,
                              folds, z_view)
    meta['refit'] = {'version': int(meta.get('bank_version', 0)), 'gamma': gamma,
                     'gamma_reason': gamma_reason,
                     'head': ('none (plain kernel vote)' if new_head is None else
                              'refitted in closed form' + (', knobs by CV' if sel else
                                                           ', knobs kept')),
                     'calibration_reason': cal_reason, 'min_examples': policy.min_examples,
                     'predicted_classes': int(len(present))}
    return replace(bank, features=features, gamma=gamma, meta=meta, head=new_head), rewhiten


def vote_to_z(u: torch.Tensor, head: Head | None) -> torch.Tensor:
    """Bank rows in the vote's space (N, d) -> the transformed rows z (N, d) they came from.

    u = normalize(z W) with W the head's (invertible, symmetric) whitening, z unit rows, so
    z = normalize(u W^-1) (exact up to the stored precision). Without whitening u is z.
    """
    if head is None or head.whiten is None:
        return u
    inv = torch.linalg.inv(head.whiten.double())
    return torch.nn.functional.normalize(u.double() @ inv, dim=1).float()


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
                 policy: RefitPolicy, folds: int, z_view: torch.Tensor | None) -> str:
    """Update meta's open-set calibration per policy; -> what was done."""
    calib = meta.get('unknown_calibration')
    recal = policy.calibration == 'recalibrate' or (policy.calibration == 'auto'
                                                    and sel is not None)
    if not recal or len(present) < 2:
        return 'kept' if calib else 'none'
    if sel is None:      # held-out scores with every knob pinned at its kept value
        hm = meta.get('head', {})
        z_view = vote_to_z(view.features, bank.head) if z_view is None else z_view
        alphas = tuple({a for a in (hm.get('alpha'), hm.get('lda_alpha')) if a is not None})
        w = float(head.fusion_weight) if head is not None else 0.0
        sel = select(z_view, np.asarray(compact), len(present), (gamma,), ('none',), (None,),
                     folds, alphas=alphas, weights=(w,),
                     whiten_options=(head is not None and head.whiten is not None,))
    rate = float((calib or {}).get('false_reject_rate', 0.05))
    # The measure the bank already thresholds (format-1 banks: the vote share).
    measure = calib.get('measure', 'probability') if calib else (
        'novelty' if head is not None else 'probability')
    if sel.heldout_novelty is not None and measure == 'novelty':
        meta['unknown_calibration'] = calibrate_novelty(sel.heldout_novelty, rate)
        meta['probability_calibration'] = calibrate_unknown(sel.heldout_scores, rate)
    else:
        meta['unknown_calibration'] = calibrate_unknown(sel.heldout_scores, rate)
    return f'recalibrated ({100 * rate:g} % false rejects on held-out folds)'


def near_duplicates(new: torch.Tensor, bank: FeatureBank, class_id: int,
                    threshold: float = DUPLICATE_COSINE) -> tuple[list[NearDuplicate], int]:
    """New examples within `threshold` cosine of a bank entry or of an earlier new example.

    new: (M, d) unit rows in the bank's space. Returns (up to 20 listed pairs, exact count of
    new examples that have a near-duplicate).
    """
    found: list[NearDuplicate] = []
    flagged = set()
    if len(bank):
        best, idx = (new @ bank.features.T).max(dim=1)
        for i in torch.nonzero(best >= threshold).flatten().tolist():
            j = int(idx[i])
            cls = int(bank.labels[j])
            name = bank.class_names[cls] if cls < bank.num_classes else '?'
            found.append(NearDuplicate(i, f'bank #{j} ({name})', float(best[i]), cls == class_id))
            flagged.add(i)
    inner = torch.triu(new @ new.T, diagonal=1)
    for i, j in torch.nonzero(inner >= threshold).tolist():
        if j not in flagged:
            found.append(NearDuplicate(j, f'new #{i}', float(inner[i, j]), True))
            flagged.add(j)
    return found[:_MAX_LISTED], len(flagged)


def save_atomic(bf: BankFile, path: str | os.PathLike[str]) -> Path:
    """Write the bank so a crash at any moment leaves either the old file or the new one.

    Serialised into a unique temporary file in the target directory, fsync'ed, renamed over
    `path`, then the directory fsync'ed (so the rename itself survives a power cut). The
    features written are `bf.stored` exactly, so loading the file gives `bf.bank` bit for bit.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f'.{path.name}.{os.getpid()}.{threading.get_ident():x}.tmp.npz')
    # Casting float32 copies of the stored values back to their dtype is exact.
    exact = replace(bf.bank, features=torch.from_numpy(bf.stored.astype(np.float32)))
    try:
        exact.save(tmp, dtype=str(bf.stored.dtype))
        with open(tmp, 'rb') as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
    return path


# ------------------------------------------------------------------------------ helpers


def _restore(bank: FeatureBank, stored: np.ndarray, moved: bool) -> BankFile:
    """The BankFile of a refitted bank: stored values re-derived only if the rows moved."""
    if not moved:          # rows already are normalize(stored), row by row
        return BankFile(bank, stored)
    stored = bank.features.numpy().astype(stored.dtype)
    return BankFile(replace(bank, features=_from_stored(stored)), stored)


def _from_stored(stored: np.ndarray) -> torch.Tensor:
    """(M, d) stored values -> unit rows, exactly as `FeatureBank.load` computes them."""
    return torch.nn.functional.normalize(torch.from_numpy(stored.astype(np.float32)), dim=1)


def _check_name(name: str) -> str:
    name = str(name).strip()
    if not name or '\n' in name:
        raise EnrollError(f'class name {name!r} must be non-empty and on one line')
    return name


def _folds(counts: np.ndarray, folds: int) -> int:
    """Fewer folds when the smallest class is small (>= 2 so every fold trains)."""
    return int(max(2, min(folds, int(counts.min()))))


def _log(bank: FeatureBank, action: str, class_name: str, count: int, source: str,
         when: datetime | None, **extra: Any) -> dict[str, Any]:
    meta = copy.deepcopy(bank.meta)
    version = int(meta.get('bank_version', 0)) + 1
    meta['bank_version'] = version
    entry = {'version': version, 'action': action, 'class': class_name, 'count': int(count),
             'time': (when or datetime.now(UTC)).isoformat(timespec='seconds'),
             'source': str(source), **extra}
    meta['enrollments'] = [*meta.get('enrollments', []), entry]
    return meta
