"""A bank and the exact feature values its file holds: what enrollment builds and saves.

`BankFile` keeps the stored (rounded) values beside the bank's unit rows so that save + load
gives back the same bank bit for bit; `save_atomic` writes it so that a crash leaves either
the old file or the new one. The copy-on-write operations on it are in bank/enroll.py.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
import os
import re
import threading
from pathlib import Path
from typing import Any

import numpy as np
import torch

from point_gn_ros.bank.npz_read import read_npz_bounded
from point_gn_ros.bank.refit import ScatterStats, vote_to_z
from point_gn_ros.bank.store import FeatureBank, quantized, unpack_int4
from point_gn_ros.errors import BankError

# The temporary files of save_atomic (+ FeatureBank.save's own `.tmp` beside them).
_TEMP_NAME = re.compile(r'\.(?P<name>.+)\.(?P<pid>\d+)\.[0-9a-f]+\.tmp\.npz(\.tmp)?')
# Rows per block when a pass goes over a whole bank (scatter statistics, the stored-rows
# check): a large section's float temporaries stay small.
_BLOCK_ROWS = 8192

__all__ = ['BankFile', 'from_stored', 'refitted_file', 'remove_stale_temps', 'save_atomic',
           'stored_dtype']


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
