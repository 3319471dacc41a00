"""Online enrollment: add examples to a bank, remove a class, refit what depends on the bank.

Every operation is copy-on-write: it returns a NEW FeatureBank and never mutates the one it was
given, so a reader holding the old bank (the node's worker, mid micro-batch) keeps computing
with one consistent version. `LiveBank` (bank/live.py) serialises writers and swaps versions.
The operations take and give a `BankFile` (bank/bank_file.py): the bank with the exact values
its file holds, saved atomically.

The bank stores its rows in the vote's space (bank/store.py), so new examples go through the
bank's own transform (and head whitening); what depends on the entries is refreshed by
`refit()` (bank/refit.py), the single place that knows which knobs depend on them.

Metadata added (JSON, in the bank file):
  bank_version   int, +1 per add/remove (0 = as built)
  enrollments    list of {version, action, class, count, time, source, near_duplicates}
                 (+ examples, augment when an add stored each example in k frames); the
                 last MAX_HISTORY (500) only
  enrollments_compacted  how many older entries were dropped from `enrollments`
  augmented_entries  {class: entries beyond one per example} (augmented adds only; the
                 examples of a class = its entries minus this, see `example_counts`)
  refit          how gamma / calibration were last decided {version, gamma, calibration, ...}
  taught         {class: {n, mean, [sn, smean, sm2]}}: each enrolled class's prototype and
                 measured size (bank/taught.py)
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from datetime import datetime, UTC
from typing import Any, Literal

import numpy as np
import torch

from point_gn_ros.bank.bank_file import (BankFile, from_stored, refitted_file, save_atomic,
                                         stored_dtype)
from point_gn_ros.bank.lda import wide_means_add, wide_means_remove
from point_gn_ros.bank.refit import (DUPLICATE_COSINE, RefitError, RefitPolicy, active_view,
                                     copy_meta, example_counts, refit, vote_to_z)
from point_gn_ros.bank.rows import append_rows
from point_gn_ros.bank.store import FeatureBank, quantized
from point_gn_ros.bank.taught import add_taught, drop_taught
from point_gn_ros.bank.validate import class_name_problem
from point_gn_ros.core.augment import variants_per_example
from point_gn_ros.core.size import SIZE_DIM
from point_gn_ros.errors import PointGNError

# At most this many near-duplicate pairs are listed (the count is always exact).
_MAX_LISTED = 20
# The metadata keeps the last MAX_HISTORY entries of `enrollments` (each at most ~800 bytes
# with a 256-character class name and a MAX_SOURCE_CHARS source): ~0.4 MB at most, within
# the 1 MB metadata limit of a loadable bank (bank/validate.py) beside the class names.
MAX_HISTORY = 500
MAX_SOURCE_CHARS = 200

class EnrollError(PointGNError):
    """An enrollment request the bank cannot take (unknown class, wrong feature size...)."""


__all__ = ['BankFile', 'EnrollError', 'EnrollResult', 'MAX_HISTORY', 'NearDuplicate',
           'RefitError', 'RefitPolicy', 'active_view', 'add_examples', 'bank_version',
           'class_counts', 'example_counts', 'near_duplicates', 'predictable', 'refit',
           'remove_class', 'save_atomic']


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
    count: int                       # entries added / removed
    new_class: bool = False
    duplicates: tuple[NearDuplicate, ...] = ()
    duplicate_count: int = 0
    refit: dict[str, Any] = field(default_factory=dict)
    augment: str = 'none'            # add: the frames each example was stored in
    examples: int = 0                # add: examples (count // variants); remove: 0

    @property
    def bank(self) -> FeatureBank:
        return self.file.bank

    @property
    def version(self) -> int:
        return bank_version(self.file.bank)

    def describe(self) -> str:
        verb = 'added' if self.action == 'add' else 'removed'
        n, frames = self.count, ''
        if self.action == 'add' and self.count != self.examples:
            n, frames = self.examples, f' ({self.count} entries, {self.augment})'
        what = f'example(s){frames} to new class' if self.new_class else (
            f'example(s){frames} of' if self.action == 'add' else 'entries of class')
        text = (f'bank v{self.version}: {verb} {n} {what} {self.class_name!r}; '
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
    """Names of the classes with at least min_examples examples (`example_counts`)."""
    counts = example_counts(bank).tolist()
    return [c for c, n in zip(bank.class_names, counts, strict=True) if n >= min_examples]


# ------------------------------------------------------------------------------ operations


def add_examples(bf: BankFile, features: torch.Tensor, class_name: str,
                 source: str = 'api', policy: RefitPolicy | None = None,
                 when: datetime | None = None, augment: str = 'none',
                 sizes: np.ndarray | None = None) -> EnrollResult:
    """Add encoder features of new examples under `class_name` (new or existing class).

    features: (M * k, D) float32 raw encoder output (D = the bank's encoder feature_dim),
    M >= 1 examples, each encoded in the k frames of `augment` (core/augment.py; k = 1 for
    'none'), example-major as `encode_clouds(..., augment=augment)` returns them. Every row
    becomes an entry; the class counts M examples (min_examples), near-duplicates are checked
    on the canonical frames. sizes: (M, SIZE_DIM) the examples' metric log sizes (core/size.py)
    or None (no metric meaning); kept with the class's prototype (bank/taught.py meta
    'taught'). Returns a new bank (version + 1); `bf` is left untouched. A
    two-section bank takes the examples into both sections (each through its own transform
    and head), so the class is predicted whichever section the gate favours.
    """
    if bf.views is not None:
        return _both_sections(add_examples, bf, features, class_name, source, policy,
                              when=when, augment=augment, sizes=sizes)
    bank, policy = bf.bank, policy or RefitPolicy()
    class_name = _check_name(class_name)
    try:
        k = variants_per_example(augment)
    except ValueError as e:
        raise EnrollError(str(e)) from None
    if features.ndim != 2 or features.shape[0] == 0 or features.shape[0] % k:
        raise EnrollError(f'expected (M * {k}, {bank.transform.in_dim}) features with M >= 1 '
                          f'(augment {augment!r}), got {tuple(features.shape)}')
    if features.shape[1] != bank.transform.in_dim:
        raise EnrollError(f'features have {features.shape[1]} dims, the bank encoder gives '
                          f'{bank.transform.in_dim}')
    if not bool(torch.isfinite(features).all()):
        raise EnrollError('features hold non-finite values')
    z_new = bank.transform(features.float().cpu())                  # (M, d) unit rows
    u_new = z_new if bank.head is None else bank.head.vote_space(z_new)
    stored_new = quantized(u_new, stored_dtype(bank, bf.stored))
    new = from_stored(stored_new)                                    # (M, d) unit rows
    names = list(bank.class_names)
    new_class = class_name not in names
    if new_class:
        names.append(class_name)
    cid = names.index(class_name)
    # Canonical frames only: the k frames of one example are alike by construction.
    dups, n_dups = near_duplicates(new[::k], bank, cid, policy.duplicate_cosine)
    feats = append_rows(bank.features, new)       # bank/rows.py: no copy of the bank rows
    labels = torch.cat([bank.labels, torch.full((len(new),), cid, dtype=torch.int64)])
    extra = {} if k == 1 else {'examples': len(new) // k, 'augment': augment}
    meta = _log(bank, 'add', class_name, len(new), source, when, near_duplicates=n_dups,
                **extra)
    if sizes is not None and np.shape(sizes) != (len(new) // k, SIZE_DIM):
        raise EnrollError(f'sizes must be ({len(new) // k}, {SIZE_DIM}), got {np.shape(sizes)}')
    meta = add_taught(meta, class_name, z_new[::k], sizes)
    if k > 1:
        aug = dict(meta.get('augmented_entries', {}))
        aug[class_name] = int(aug.get(class_name, 0)) + len(new) - len(new) // k
        meta['augmented_entries'] = aug
    # z of the new rows as a full refit would recover them from the stored values.
    stats = None if bf.stats is None else bf.stats.add(vote_to_z(new, bank.head), cid)
    head = bank.head
    if head is not None and head.lda_wide:     # its class means take in the new rows
        head = wide_means_add(head, bank.transform.standardized(features.float().cpu()), cid,
                              int((bank.labels == cid).sum()))
    out, moved = refit(replace(bank, features=feats, labels=labels, class_names=names,
                               meta=meta, path=None, head=head), policy, stats)
    stored = np.concatenate([bf.stored, stored_new])
    return EnrollResult(refitted_file(out, stored, moved, stats), 'add', class_name,
                        len(new), new_class, tuple(dups), n_dups, out.meta['refit'], augment,
                        len(new) // k)


def remove_class(bf: BankFile, class_name: str, source: str = 'api',
                 policy: RefitPolicy | None = None, when: datetime | None = None
                 ) -> EnrollResult:
    """Drop every entry of `class_name`; ids of the classes after it shift down by one.

    A two-section bank loses the class in both sections.
    """
    if bf.views is not None:
        return _both_sections(remove_class, bf, class_name, source, policy, when=when)
    bank, policy = bf.bank, policy or RefitPolicy()
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
    meta = drop_taught(_log(bank, 'remove', class_name, removed, source, when), class_name)
    if class_name in meta.get('augmented_entries', {}):
        meta['augmented_entries'] = {c: n for c, n in meta['augmented_entries'].items()
                                     if c != class_name}
    stats = None if bf.stats is None else bf.stats.remove(
        vote_to_z(bank.features[~keep], bank.head), cid)
    out, moved = refit(replace(bank, features=bank.features[keep], labels=labels,
                               class_names=names, meta=meta, path=None,
                               head=wide_means_remove(bank.head, cid)), policy, stats)
    return EnrollResult(refitted_file(out, bf.stored[keep.numpy()], moved, stats),
                        'remove', class_name, removed, False, (), 0, out.meta['refit'])


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


# ------------------------------------------------------------------------------ helpers


def _both_sections(op, bf: BankFile, *args: Any, when: datetime | None = None,  # noqa: ANN001
                   **kwargs: Any) -> EnrollResult:
    """Run an enrollment operation on each section of a two-section bank, one timestamp.

    -> the main section's result with the scan section's bank attached (the gate is kept:
    it tells complete objects from scans, whatever their class).
    """
    when = when or datetime.now(UTC)
    assert bf.views is not None
    main = op(BankFile(replace(bf.bank, views=None, gate=None), bf.stored, bf.stats),
              *args, when=when, **kwargs)
    views = op(bf.views, *args, when=when, **kwargs)
    bank = replace(main.bank, views=views.bank, gate=bf.bank.gate)
    return replace(main, file=replace(main.file, bank=bank, views=views.file))


def _check_name(name: str) -> str:
    name = str(name).strip()
    problem = class_name_problem(name)      # the rule the bank is loaded with
    if problem:
        raise EnrollError(problem)
    return name


def _clipped(text: str, limit: int) -> str:
    """`text`, its middle elided when longer than `limit` (its start and end say the most)."""
    if len(text) <= limit:
        return text
    head = (limit - 5) // 2
    return f'{text[:head]} ... {text[-(limit - 5 - head):]}'


def _log(bank: FeatureBank, action: str, class_name: str, count: int, source: str,
         when: datetime | None, **extra: Any) -> dict[str, Any]:
    meta = copy_meta(bank.meta)
    version = int(meta.get('bank_version', 0)) + 1
    meta['bank_version'] = version
    entry = {'version': version, 'action': action, 'class': class_name, 'count': int(count),
             'time': (when or datetime.now(UTC)).isoformat(timespec='seconds'),
             'source': _clipped(str(source), MAX_SOURCE_CHARS), **extra}
    history = [*meta.get('enrollments', []), entry]
    if len(history) > MAX_HISTORY:         # compacted: the oldest entries are counted
        meta['enrollments_compacted'] = (int(meta.get('enrollments_compacted', 0))
                                         + len(history) - MAX_HISTORY)
        history = history[-MAX_HISTORY:]
    meta['enrollments'] = history
    return meta
