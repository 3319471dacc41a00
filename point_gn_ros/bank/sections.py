"""Two-section banks: complete objects and single-view scans, each with its own head.

One head fitted on complete objects and their scans together serves neither well: its
knobs, PCA and within-class covariance are dominated by the scans (4 per object), and
complete objects lose 2 points (benchmarks/log, "Single-view scans"). A two-section bank
keeps the complete objects as the main section (exactly the complete-object bank: own PCA
width, whitening, LDA, gamma and temperature, all chosen by CV on complete objects) and the
scans as a second section (own knobs, chosen by CV grouped by source object); a gate
(bank/gate.py) says how likely a query is a scan and mixes the two sections'
probabilities (bank/classifier.py). With the scans' source objects known, the bank also
gets the object test of taught classes (bank/objects.py), fitted on the scan section.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import torch

from point_gn_ros.bank.gate import GATE_DIMS, GATE_SHRINKAGE, Gate
from point_gn_ros.bank.objects import ObjectTest
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.datasets.base import Dataset


class RowsDataset(Dataset):
    """The rows `rows` (bool mask or indices) of a dataset, as a dataset."""

    def __init__(self, base: Dataset, rows: np.ndarray, tag: str) -> None:
        idx = np.flatnonzero(rows) if np.asarray(rows).dtype == bool else np.asarray(rows)
        super().__init__(base.path, f'{base.split}[{tag}]', np.asarray(base.labels)[idx],
                         base.class_names)
        self.format = base.format
        self.skipped = list(getattr(base, 'skipped', []))
        self._base, self._idx = base, idx.astype(np.int64)

    def _load(self, i: int) -> np.ndarray:
        return self._base[int(self._idx[i])][0]


def combine_sections(complete: FeatureBank, views: FeatureBank, feats: torch.Tensor,
                     is_scan: np.ndarray, gate_dims: int | None = GATE_DIMS,
                     gate_shrinkage: float = GATE_SHRINKAGE,
                     groups: np.ndarray | None = None) -> FeatureBank:
    """The two-section bank: `complete` as the main section, `views` as the scan section.

    feats: (N, D) raw encoder features of every entry of both; is_scan: (N,) bool. The gate
    is fitted on them. groups: (N,) source object of each entry, or None; given (and the
    scan section's LDA reads every dim), the object test is fitted on the scans. The unknown
    rule keeps each kind's held-out false-reject rate at most the target: the lower of the
    two sections' calibrated thresholds.
    """
    if complete.class_names != views.class_names or complete.config != views.config:
        raise ValueError('sections need the same class names and encoder configuration')
    gate = Gate.fit(feats, is_scan, gate_dims, gate_shrinkage)
    p = gate.scan_probability(feats).numpy()
    right = (p > 0.5) == np.asarray(is_scan, dtype=bool)
    meta: dict[str, Any] = dict(complete.meta)
    meta['gate'] = {'dims': gate_dims, 'shrinkage': gate_shrinkage, 'priors': 'equal',
                    'train_routing_complete': float(right[~is_scan].mean()),
                    'train_routing_scans': float(right[is_scan].mean())}
    cal_c, cal_v = complete.meta.get('unknown_calibration'), views.meta.get('unknown_calibration')
    if cal_c and cal_v and cal_c.get('measure', 'probability') == cal_v.get(
            'measure', 'probability') == 'probability':
        meta['unknown_calibration'] = dict(
            cal_c, threshold=min(float(cal_c['threshold']), float(cal_v['threshold'])),
            rule="lower of the two sections' thresholds")
    objects = None
    if groups is not None and views.head is not None and views.head.lda_wide:
        scan = torch.from_numpy(np.asarray(is_scan, dtype=bool))
        objects = ObjectTest.fit(views.transform.standardized(feats[scan]),
                                 np.asarray(groups)[scan.numpy()], views.labels.numpy(),
                                 views.class_names)
        meta['object_test'] = objects.describe()
    return replace(complete, meta=meta, views=views, gate=gate, objects=objects)
