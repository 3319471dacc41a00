"""A bank that changes while it is used: versioned snapshots, serialised writers.

Readers (the node's worker) call `current()` once per micro-batch and use that snapshot for
the whole batch: an answer is always computed with one consistent bank version. Writers
(enrollment, removal, save) take a lock, build the next version copy-on-write
(bank/enroll.py) and publish it by swapping one reference, which readers never wait for.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from datetime import datetime
import logging
import os
from pathlib import Path
import threading
from typing import Generic, TypeVar

import numpy as np
import torch

from point_gn_ros.bank.enroll import (BankFile, EnrollResult, RefitPolicy, active_view,
                                      add_examples, bank_version, class_counts, remove_class,
                                      save_atomic)
from point_gn_ros.bank import ridge
from point_gn_ros.bank.rows import with_room
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.core.threads import lower_priority, name_os_thread, trim_heap

Model = TypeVar('Model')
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Snapshot(Generic[Model]):
    """One bank version: the whole bank, the view that is predicted, its model.

    file: the whole bank (what is saved); active: the view of the classes that can be
    predicted (bank/enroll.py `active_view`); model: built on that view (e.g. a Recognizer).
    """

    file: BankFile
    active: FeatureBank
    model: Model

    @property
    def bank(self) -> FeatureBank:
        return self.file.bank

    @property
    def version(self) -> int:
        return bank_version(self.file.bank)

    @property
    def class_names(self) -> list[str]:
        return self.file.bank.class_names

    def counts(self) -> dict[str, int]:
        return class_counts(self.file.bank)


class LiveBank(Generic[Model]):
    """The current bank version plus serialised add / remove / save.

    make_model(active_bank) -> Model builds what readers use (called under the writer lock,
    outside any reader's path). derive(active_bank, previous_model) -> Model, optional: builds
    the model of an add / remove from the previous version's (e.g. extending its search
    index, bank/search.py) where make_model would start from nothing. on_refit(snapshot),
    optional: told of a version the background ridge refit published (`_refit_loop`).
    """

    def __init__(self, file: BankFile, make_model: Callable[[FeatureBank], Model],
                 policy: RefitPolicy | None = None,
                 derive: Callable[[FeatureBank, Model], Model] | None = None,
                 on_refit: Callable[[Snapshot[Model]], None] | None = None) -> None:
        self.policy = policy or RefitPolicy()
        self.on_refit = on_refit     # called with each version a background refit publishes
        self._make_model, self._derive = make_model, derive
        self._lock = threading.Lock()
        # One pass over the bank now, so that every enrollment's LDA refit is cheap, and
        # its rows moved to where enrollments append without copying them (bank/rows.py).
        self._snap = self._snapshot(_with_room(file.with_stats()))
        self._refit_thread: threading.Thread | None = None
        self._refit_pending()            # a bank saved while its ridge term waited

    def current(self) -> Snapshot[Model]:
        """The latest published version (never blocks: a reference read)."""
        return self._snap

    def add(self, features: torch.Tensor, class_name: str, source: str,
            when: datetime | None = None, augment: str = 'none',
            sizes: np.ndarray | None = None) -> EnrollResult:
        """features: (M * k, D) float32 raw encoder output -> the result; publishes it.

        augment: how the examples were encoded (k frames each, see `add_examples`); sizes:
        (M, SIZE_DIM) the examples' metric log sizes (core/size.py) or None.
        """
        with self._lock:
            res = add_examples(self._snap.file, features, class_name, source, self.policy, when,
                               augment, sizes=sizes)
            self._snap = self._snapshot(res.file, self._snap)
            self._refit_pending()
        return res

    def remove(self, class_name: str, source: str, when: datetime | None = None
               ) -> EnrollResult:
        with self._lock:
            res = remove_class(self._snap.file, class_name, source, self.policy, when)
            self._snap = self._snapshot(res.file, self._snap)
            self._refit_pending()
        return res

    def wait_refit(self, timeout: float | None = None) -> bool:
        """Wait for a background ridge refit (bank/ridge.py); -> False if it still runs."""
        thread = self._refit_thread
        if thread is not None:
            thread.join(timeout)
            return not thread.is_alive()
        return True

    def _refit_pending(self) -> None:
        """Start the background full refit of a pending ridge term, if none runs (locked)."""
        if not _pending(self._snap.file) or (
                self._refit_thread is not None and self._refit_thread.is_alive()):
            return
        self._refit_thread = threading.Thread(target=self._refit_loop, name='pgn_ridge_refit',
                                              daemon=True)
        self._refit_thread.start()

    def _refit_loop(self) -> None:
        """Refit the latest version's pending ridge; publish it unless a writer came first.

        The (N, N) solve runs outside the lock (readers and writers go on); if the bank
        changed meanwhile, the newer version is refitted instead.
        """
        name_os_thread()
        lower_priority()          # a background refit: the threads that answer come first
        while True:
            snap = self._snap
            if not _pending(snap.file):
                return
            try:
                fitted = refit_ridge_sections(snap.file)
            except Exception as exc:  # noqa: BLE001 - the bank keeps answering without it
                log.error('bank version %d: ridge refit failed, the term stays off: %s',
                          snap.version, exc)
                return
            with self._lock:
                if self._snap is snap:
                    self._snap = published = self._snapshot(fitted, snap)
                    break
            trim_heap()           # the refit's buffers: memory back to the OS
        trim_heap()
        if self.on_refit is not None:
            try:
                self.on_refit(published)
            except Exception as exc:  # noqa: BLE001 - e.g. the node was cleaned up meanwhile
                log.warning('bank version %d (ridge refit) not handed on: %s',
                            published.version, exc)

    def rebuild(self) -> Snapshot[Model]:
        """Same bank, new model (e.g. after a live parameter changed how it is built)."""
        with self._lock:
            self._snap = self._snapshot(self._snap.file)
        return self._snap

    def save(self, path: str | os.PathLike[str], make_dirs: bool = True) -> tuple[Path, int]:
        """Atomically write the current version; -> (path, version written).

        Holds the writer lock so that no enrollment is lost between snapshot and write;
        readers are not affected. make_dirs=False: the folder must exist.
        """
        with self._lock:
            snap = self._snap
            return save_atomic(snap.file, path, make_dirs), snap.version

    def _snapshot(self, file: BankFile, previous: Snapshot[Model] | None = None
                  ) -> Snapshot[Model]:
        active = active_view(file.bank, self.policy.min_examples)
        if previous is not None and self._derive is not None:
            return Snapshot(file, active, self._derive(active, previous.model))
        return Snapshot(file, active, self._make_model(active))


def _with_room(file: BankFile) -> BankFile:
    """The same bank (values bit for bit) with each section's rows in an appendable buffer."""
    views = None if file.views is None else _with_room(file.views)
    bank = replace(file.bank, features=with_room(file.bank.features),
                   views=None if views is None else views.bank)
    return replace(file, bank=bank, views=views)


def _pending(file: BankFile) -> bool:
    return ridge.is_pending(file.bank.meta) or (
        file.views is not None and ridge.is_pending(file.views.bank.meta))


def refit_ridge_sections(file: BankFile) -> BankFile:
    """The same bank with each section's pending ridge term fitted (stored values kept).

    What the background refit publishes; scripts call it to measure that final state.
    """
    views = None if file.views is None else replace(
        file.views, bank=ridge.refit_pending(file.views.bank))
    main = ridge.refit_pending(replace(file.bank, views=None))
    bank = replace(main, views=None if views is None else views.bank)
    return replace(file, bank=bank, views=views)
