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

from point_gn_ros.bank.enroll import (BankFile, EnrollResult, add_examples, bank_version,
                                      class_counts, remove_class, save_atomic)
from point_gn_ros.bank.refit import RefitPolicy, active_view
from point_gn_ros.bank.store import FeatureBank, with_room

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
    index, bank/index.py) where make_model would start from nothing. Every version it
    publishes is complete: its fitted parts (a kernel ridge term included) are refitted
    before the swap, so what readers see is what a save writes and a load gives back.
    """

    def __init__(self, file: BankFile, make_model: Callable[[FeatureBank], Model],
                 policy: RefitPolicy | None = None,
                 derive: Callable[[FeatureBank, Model], Model] | None = None) -> None:
        self.policy = policy or RefitPolicy()
        self._make_model, self._derive = make_model, derive
        self._lock = threading.Lock()
        # One pass over the bank now, so that every enrollment's LDA refit is cheap, and
        # its rows moved to where enrollments append without copying them (bank/store.py).
        self._snap = self._snapshot(_with_room(file.with_stats()))

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
        return res

    def remove(self, class_name: str, source: str, when: datetime | None = None
               ) -> EnrollResult:
        with self._lock:
            res = remove_class(self._snap.file, class_name, source, self.policy, when)
            self._snap = self._snapshot(res.file, self._snap)
        return res

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
