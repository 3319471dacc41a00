"""Online enrollment: add examples to a bank, remove a class, refit what depends on the bank.

Every operation is copy-on-write: it returns a NEW FeatureBank and never mutates the one it was
given, so a reader holding the old bank (the node's worker, mid micro-batch) keeps computing
with one consistent version. `LiveBank` (bank/live.py) serialises writers and swaps versions.
The operations take and give a `BankFile` (below): the bank with the exact values
its file holds, saved atomically.

The bank stores its rows in the vote's space (bank/store.py), so new examples go through the
bank's own transform (and head whitening); what depends on the entries is refreshed by
`refit()` (bank/refit.py), the single place that knows which knobs depend on them.

State added: the FeatureBank fields `enrollments` (the log, `Enrollment` entries, the last
MAX_HISTORY (500) only), `enrollments_compacted` (older entries dropped from it) and
`augmented_entries` ({class: entries beyond one per example}, augmented adds only: the
examples of a class = its entries minus this, see `example_counts`); in the file they are
metadata keys of the same names. Metadata added (JSON, in the bank file):
  bank_version   int, +1 per add/remove (0 = as built)
  refit          how gamma / calibration were last decided {version, gamma, calibration, ...}
  taught         {class: {n, mean, [sn, smean, sm2]}}: each enrolled class's prototype and
                 measured size (bank/taught.py)
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from datetime import datetime, UTC
import os
from pathlib import Path
import re
import threading
from typing import Any, Literal

import numpy as np
import torch

from point_gn_ros.bank.discriminant import (ScatterStats, vote_to_z, wide_means_add,
                                            wide_means_remove)
from point_gn_ros.bank.refit import (DUPLICATE_COSINE, RefitPolicy, copy_meta, example_counts,
                                     refit)
from point_gn_ros.bank.store import (Enrollment, FeatureBank, append_rows, class_name_problem,
                                     quantized, read_npz_bounded, unpack_int4)
from point_gn_ros.bank.taught import add_taught, drop_taught
from point_gn_ros.core.augment import variants_per_example
from point_gn_ros.core.size import SIZE_DIM
from point_gn_ros.errors import BankError, PointGNError

# ---- a bank and the exact values its file holds
# A bank and the exact feature values its file holds: what enrollment builds and saves.
#
# `BankFile` keeps the stored (rounded) values beside the bank's unit rows so that save + load
# gives back the same bank bit for bit; `save_atomic` writes it so that a crash leaves either
# the old file or the new one. The copy-on-write operations on it are in bank/enroll.py.

# The temporary files of save_atomic (+ FeatureBank.save's own `.tmp` beside them).
_TEMP_NAME = re.compile(r'\.(?P<name>.+)\.(?P<pid>\d+)\.[0-9a-f]+\.tmp\.npz(\.tmp)?')
# Rows per block when a pass goes over a whole bank (scatter statistics, the stored-rows
# check): a large section's float temporaries stay small.
_BLOCK_ROWS = 8192



@dataclass(frozen=True)
class BankFile:
    """A bank and the exact feature values its file holds (or will hold once saved).

    stored: (N, d) float16, float32 or int8, the `features` array of the file (unpacked
    to int8 values for an int4 file: bank.meta['stored_dtype'] says which). Invariant:
    bank.features == normalize(stored) row by row, computed as `FeatureBank.load` does, so
    save + load gives back the same bank bit for bit. (Re-casting the normalised features
    is not enough: rounding to float16 and re-normalising is not idempotent.)
    """

    bank: FeatureBank
    stored: np.ndarray
    # Scatter statistics of the rows for a cheap LDA refit (not saved; see `with_stats`).
    stats: ScatterStats | None = field(default=None, compare=False, repr=False)
    # A two-section bank's scan section (bank.views), with its own stored values.
    views: 'BankFile | None' = None

    @classmethod
    def load(cls, path: str | os.PathLike[str] | None = None,
             expected_config: Any = None) -> 'BankFile':
        """Read a bank file (None: the shipped default) keeping its stored feature values."""
        return cls._with_file_values(FeatureBank.load(path, expected_config))

    @classmethod
    def of_loaded(cls, bank: FeatureBank) -> 'BankFile':
        """A bank loaded earlier, with its file's stored values when they still give its rows.

        Else (the file changed or went away since) the values are re-derived (`of`).
        """
        if bank.path is not None:
            try:
                bf = cls._with_file_values(bank)
                if _matches(bf.stored, bank.features) and (
                        bf.views is None or _matches(bf.views.stored, bank.views.features)):
                    return bf
            except (OSError, KeyError, ValueError, BankError):
                pass
        return cls.of(bank)

    @classmethod
    def _with_file_values(cls, bank: FeatureBank) -> 'BankFile':
        z = read_npz_bounded(bank.path)
        stored = _unpacked(bank, z['features'])
        views = None if bank.views is None else cls(
            bank.views, _unpacked(bank.views, z['views_features']))
        return cls(bank, stored, views=views)

    @classmethod
    def of(cls, bank: FeatureBank, dtype: str | None = None) -> 'BankFile':
        """Wrap a bank never saved: features re-derived from their rounded stored values."""
        dtype = dtype or bank.meta.get('stored_dtype', 'float32')
        stored = quantized(bank.features, dtype)
        meta = dict(bank.meta, stored_dtype=dtype)
        views = None if bank.views is None else cls.of(bank.views, dtype)
        out = replace(bank, features=from_stored(stored), meta=meta,
                      views=None if views is None else views.bank)
        return cls(out, stored, views=views)

    def with_stats(self) -> 'BankFile':
        """The same, with ScatterStats when the bank's head has an LDA part (one pass).

        A wide LDA refits from its stored means and precision instead: no statistics.
        """
        head = self.bank.head
        views = None if self.views is None else self.views.with_stats()
        if self.stats is not None or head is None or head.lda_coef is None or head.lda_wide:
            return self if views is self.views else replace(self, views=views)
        # In blocks of rows: a 79k-row scan section in float64 would need ~0.5 GB at once.
        u, labels, stats = self.bank.features, self.bank.labels, None
        for i in range(0, len(u), _BLOCK_ROWS):
            part = ScatterStats.of(vote_to_z(u[i:i + _BLOCK_ROWS], head),
                                   labels[i:i + _BLOCK_ROWS], self.bank.num_classes)
            stats = part if stats is None else stats.merge(part)
        return replace(self, stats=stats, views=views)

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Atomic write of exactly this bank (see `save_atomic`)."""
        return save_atomic(self, path)


def save_atomic(bf: BankFile, path: str | os.PathLike[str], make_dirs: bool = True) -> Path:
    """Write the bank so a crash at any moment leaves either the old file or the new one.

    Serialised into a unique temporary file in the target directory, fsync'ed, renamed over
    `path`, then the directory fsync'ed (so the rename itself survives a power cut). The
    features written are `bf.stored` exactly, so loading the file gives `bf.bank` bit for bit.
    Any failure removes the temporary files; those a killed process left for `path` are
    removed first (`remove_stale_temps`). make_dirs=False: the folder must exist.
    """
    path = Path(path)
    if make_dirs:
        path.parent.mkdir(parents=True, exist_ok=True)
    elif not path.parent.is_dir():
        raise FileNotFoundError(f'folder {path.parent} does not exist')
    remove_stale_temps(path)
    tmp = path.with_name(f'.{path.name}.{os.getpid()}.{threading.get_ident():x}.tmp.npz')
    # Casting float32 copies of the stored values back to their dtype is exact.
    exact = replace(bf.bank, features=torch.from_numpy(bf.stored.astype(np.float32)))
    if bf.views is not None:
        exact = replace(exact, views=replace(
            bf.views.bank, features=torch.from_numpy(bf.views.stored.astype(np.float32))))
    try:
        exact.save(tmp, dtype=stored_dtype(bf.bank, bf.stored))
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


def remove_stale_temps(path: str | os.PathLike[str]) -> list[Path]:
    """Remove the temporary files of `save_atomic(..., path)` whose process is gone.

    `.<name>.<pid>.<thread>.tmp.npz` (and the `.tmp` that `FeatureBank.save` writes beside
    it) are left only by a process killed mid-save (kill -9, power cut); a live process's
    (another saver's) are kept. path: the bank file, or a folder (every bank in it).
    -> the files removed.
    """
    path = Path(path)
    folder, name = (path, None) if path.is_dir() else (path.parent, path.name)
    removed = []
    try:
        candidates = list(folder.glob('.*.tmp.npz*'))
    except OSError:
        return removed
    for tmp in candidates:
        m = _TEMP_NAME.fullmatch(tmp.name)
        if m is None or (name is not None and m['name'] != name):
            continue
        pid = int(m['pid'])
        if pid != os.getpid() and _alive(pid):
            continue
        try:
            tmp.unlink()
            removed.append(tmp)
        except OSError:
            pass
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:           # another user's process: alive
        return True
    return True


def refitted_file(bank: FeatureBank, stored: np.ndarray, moved: bool,
                  stats: ScatterStats | None) -> BankFile:
    """The BankFile of a refitted bank: stored values re-derived only if the rows moved.

    The scatter statistics live in z space, which re-whitening does not change.
    """
    if not moved:          # rows already are normalize(stored), row by row
        return BankFile(bank, stored, stats)
    stored = quantized(bank.features, stored_dtype(bank, stored))
    return BankFile(replace(bank, features=from_stored(stored)), stored, stats)


def stored_dtype(bank: FeatureBank, stored: np.ndarray) -> str:
    """The file dtype of stored values: int4 files keep theirs unpacked as int8."""
    return 'int4' if bank.meta.get('stored_dtype') == 'int4' else str(stored.dtype)


def from_stored(stored: np.ndarray) -> torch.Tensor:
    """(M, d) stored values -> unit rows, exactly as `FeatureBank.load` computes them."""
    return torch.nn.functional.normalize(torch.from_numpy(stored.astype(np.float32)), dim=1)


def _unpacked(bank: FeatureBank, stored: np.ndarray) -> np.ndarray:
    """A file's `features` array as BankFile keeps it (int4: unpacked to int8 values)."""
    return unpack_int4(stored, bank.features.shape[1]) if stored_dtype(bank, stored) == 'int4' \
        else stored


def _matches(stored: np.ndarray, features: torch.Tensor) -> bool:
    """Whether rows are exactly the normalised stored values (by blocks: no second copy)."""
    return stored.shape == tuple(features.shape) and all(
        torch.equal(from_stored(stored[i:i + _BLOCK_ROWS]), features[i:i + _BLOCK_ROWS])
        for i in range(0, len(stored), _BLOCK_ROWS))


# ---- enrollment

# At most this many near-duplicate pairs are listed (the count is always exact).
_MAX_LISTED = 20
# The metadata keeps the last MAX_HISTORY entries of `enrollments` (each at most ~800 bytes
# with a 256-character class name and a MAX_SOURCE_CHARS source): ~0.4 MB at most, within
# the 1 MB metadata limit of a loadable bank (bank/store.py) beside the class names.
MAX_HISTORY = 500
MAX_SOURCE_CHARS = 200

class EnrollError(PointGNError):
    """An enrollment request the bank cannot take (unknown class, wrong feature size...)."""



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
    feats = append_rows(bank.features, new)       # bank/store.py: no copy of the bank rows
    labels = torch.cat([bank.labels, torch.full((len(new),), cid, dtype=torch.int64)])
    extra = {} if k == 1 else {'examples': len(new) // k, 'augment': augment}
    meta, history = _log(bank, 'add', class_name, len(new), source, when,
                         near_duplicates=n_dups, **extra)
    if sizes is not None and np.shape(sizes) != (len(new) // k, SIZE_DIM):
        raise EnrollError(f'sizes must be ({len(new) // k}, {SIZE_DIM}), got {np.shape(sizes)}')
    meta = add_taught(meta, class_name, z_new[::k], sizes)
    if k > 1:
        aug = dict(bank.augmented_entries)
        aug[class_name] = int(aug.get(class_name, 0)) + len(new) - len(new) // k
        history['augmented_entries'] = aug
    # z of the new rows as a full refit would recover them from the stored values.
    stats = None if bf.stats is None else bf.stats.add(vote_to_z(new, bank.head), cid)
    head = bank.head
    if head is not None and head.lda_wide:     # its class means take in the new rows
        head = wide_means_add(head, bank.transform.standardized(features.float().cpu()), cid,
                              int((bank.labels == cid).sum()))
    out, moved = refit(replace(bank, features=feats, labels=labels, class_names=names,
                               meta=meta, path=None, head=head, **history), policy, stats)
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
    meta, history = _log(bank, 'remove', class_name, removed, source, when)
    meta = drop_taught(meta, class_name)
    history['augmented_entries'] = {c: n for c, n in bank.augmented_entries.items()
                                    if c != class_name}
    stats = None if bf.stats is None else bf.stats.remove(
        vote_to_z(bank.features[~keep], bank.head), cid)
    out, moved = refit(replace(bank, features=bank.features[keep], labels=labels,
                               class_names=names, meta=meta, path=None,
                               head=wide_means_remove(bank.head, cid), **history), policy,
                       stats)
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
         when: datetime | None, near_duplicates: int = 0, examples: int | None = None,
         augment: str | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """-> the next version's metadata, and its history fields (FeatureBank.enrollments...)."""
    meta = copy_meta(bank.meta)
    version = int(meta.get('bank_version', 0)) + 1
    meta['bank_version'] = version
    entry = Enrollment(version, action, class_name, int(count),
                       (when or datetime.now(UTC)).isoformat(timespec='seconds'),
                       _clipped(str(source), MAX_SOURCE_CHARS), int(near_duplicates),
                       examples, augment)
    history = (*bank.enrollments, entry)
    compacted = bank.enrollments_compacted
    if len(history) > MAX_HISTORY:         # compacted: the oldest entries are counted
        compacted += len(history) - MAX_HISTORY
        history = history[-MAX_HISTORY:]
    return meta, {'enrollments': history, 'enrollments_compacted': compacted,
                  'augmented_entries': dict(bank.augmented_entries)}
