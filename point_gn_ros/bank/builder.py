"""Dataset -> feature bank, with every knob chosen by cross-validation on that bank."""

from __future__ import annotations

from collections import Counter
from datetime import datetime, UTC
import hashlib
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from point_gn_ros.bank.discriminant import fit_gate, fit_head, fit_object_test, fit_ridge
from point_gn_ros.bank.model import GATE_DIMS, GATE_SHRINKAGE, FeatureTransform, Head, Standardize
from point_gn_ros.bank.store import (FeatureBank, MatrixDtype, rounded_head, rounded_transform,
                                     stored_rows)
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.datasets.base import Dataset
from point_gn_ros.bank.selection import (DEFAULT_ALPHAS, DEFAULT_GAMMAS, DEFAULT_LDA_ALPHAS,
                                         DEFAULT_WEIGHTS, Selection, calibrate_novelty,
                                         calibrate_unknown, select)
from point_gn_ros.recognizer import Encoder, encode_clouds, make_encoder


def encode_dataset(dataset, encoder: Encoder, batch_size: int = 64, progress: bool = True,
                   cache_dir: Path | None = None) -> torch.Tensor:
    """Encode every cloud of a dataset: -> (len(dataset), feature_dim) float32.

    cache_dir: reuse raw features keyed by dataset, split, encoder version and config (a
    multi-scale encoder's features are cached per scale, so adding a scale re-encodes
    only that one).
    """
    from point_gn_ros.core.multiscale import MultiScaleEncoder
    if isinstance(encoder, MultiScaleEncoder) and cache_dir is not None:
        return torch.cat([encode_dataset(dataset, enc, batch_size, progress, cache_dir)
                          for enc in encoder.scales], dim=1)
    cache = None
    if cache_dir is not None:
        cache = feature_cache_path(dataset, encoder.cfg, cache_dir)
        if cache.is_file():
            return torch.from_numpy(np.load(cache, allow_pickle=False))
    clouds = (dataset[i][0] for i in range(len(dataset)))
    feats = encode_clouds(clouds, encoder, batch_size=batch_size, total=len(dataset),
                          progress=f'encoding {dataset.split}' if progress else None)
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.save(cache, feats.numpy())
    return feats


def feature_cache_path(dataset, cfg: EncoderConfig, cache_dir: Path | str) -> Path:
    """Where encode_dataset caches a single-scale encoder's features of `dataset`."""
    from point_gn_ros.core.config import ENCODER_VERSION
    key = hashlib.sha1(repr((str(Path(dataset.path).resolve()), dataset.split, len(dataset),
                             ENCODER_VERSION, cfg.to_dict())).encode()).hexdigest()
    return Path(cache_dir) / f'feats_{key[:16]}.npy'


def fit_selected(feats: torch.Tensor, labels: np.ndarray, num_classes: int, sel: Selection,
                 stored_dtype: str = 'float32', matrix_dtype: MatrixDtype = 'float32'
                 ) -> tuple[FeatureTransform, Head, torch.Tensor]:
    """Fit the CV-chosen transform and head on all of feats (N, D).

    -> transform, head, bank rows in the vote's space (N, d) float32. With a kernel ridge
    term (sel.ridge_weight > 0) the rows come back as the file will store them in
    `stored_dtype` (int4 rounding would otherwise undo the ridge fit: bank/discriminant.py).
    matrix_dtype: the projection, whitening and wide-LDA precision are rounded as a file
    of that matrix dtype stores them (bank/store.py) before anything is computed with them.
    """
    tf = rounded_transform(FeatureTransform.fit(feats, sel.standardize, sel.dims), matrix_dtype)
    z = tf(feats)
    lab = torch.as_tensor(np.asarray(labels), dtype=torch.int64)
    head = rounded_head(fit_head(z, lab, num_classes, sel.gamma, sel.alpha, sel.lda_alpha,
                                 sel.fusion_weight, sel.temperature,
                                 x=tf.standardized(feats) if sel.lda_wide else None),
                        matrix_dtype)
    rows = head.vote_space(z)
    if sel.ridge_weight > 0:
        rows = stored_rows(rows, stored_dtype)
        head = replace(head, ridge_coef=fit_ridge(rows, lab, num_classes, sel.ridge_gamma,
                                                  sel.ridge_lambda),
                       ridge_gamma=sel.ridge_gamma, ridge_lambda=sel.ridge_lambda,
                       ridge_weight=sel.ridge_weight)
    return tf, head, rows


def build_bank(dataset, cfg: EncoderConfig = EncoderConfig(), device: str = 'cpu',
               gammas: tuple[float, ...] = DEFAULT_GAMMAS,
               standardize_options: tuple[Standardize, ...] = ('none', 'standardize'),
               dims_options: tuple[int | None, ...] = (None,), folds: int = 5,
               false_reject_rate: float = 0.05, progress: bool = True,
               cache_dir: Path | None = None, encoder: Encoder | None = None,
               feats: torch.Tensor | None = None,
               groups: np.ndarray | None = None,
               alphas: tuple[float, ...] = DEFAULT_ALPHAS,
               weights: tuple[float, ...] = DEFAULT_WEIGHTS,
               lda_alphas: tuple[float, ...] = DEFAULT_LDA_ALPHAS,
               cv_subset: np.ndarray | None = None, wide_lda: bool = False,
               ridge: bool = False, stored_dtype: str = 'float32',
               matrix_dtype: MatrixDtype = 'float32') -> FeatureBank:
    """Encode `dataset`, choose transform and head by k-fold CV on it, return the bank.

    groups: (N,) int or None; entries sharing a group (an object and its simulated views)
    stay in one CV fold. alphas=() gives the plain kernel vote (format-1 behaviour).
    cv_subset: (M,) int64 entry indices the CV runs on (default all; CV cost grows with the
    square of the bank): the knobs chosen there are then fitted on every entry.
    wide_lda: CV also weighs an LDA on every standardised encoder dim (bank/model.py).
    ridge: CV also weighs a kernel ridge term (bank/discriminant.py), fitted on the rows as a file
    of `stored_dtype` holds them (save the bank with that dtype).
    matrix_dtype: 'float16' stores the large fitted matrices as float16 (format 5,
    bank/store.py): about half the file of a wide-LDA or PCA bank.
    """
    encoder = encoder or make_encoder(cfg, device)
    if feats is None:
        feats = encode_dataset(dataset, encoder, progress=progress, cache_dir=cache_dir)
    labels = np.asarray(dataset.labels, dtype=np.int64)
    cv = np.arange(len(labels)) if cv_subset is None else np.asarray(cv_subset, dtype=np.int64)
    sel = select(feats[torch.from_numpy(cv)], labels[cv], len(dataset.class_names), gammas,
                 standardize_options, dims_options, folds,
                 groups=None if groups is None else np.asarray(groups)[cv], alphas=alphas,
                 weights=weights, lda_alphas=lda_alphas, wide_lda=wide_lda, ridge=ridge)
    tf, head, vote_feats = fit_selected(feats, labels, len(dataset.class_names), sel,
                                        stored_dtype, matrix_dtype)
    counts = Counter(labels.tolist())
    meta = {
        'provenance': {
            'dataset': str(dataset.path), 'format': dataset.format, 'split': dataset.split,
            'count': int(len(labels)),
            'per_class': {dataset.class_names[c]: int(n) for c, n in sorted(counts.items())},
            'created': datetime.now(UTC).isoformat(timespec='seconds'),
        },
        'selection': {'standardize': sel.standardize, 'dims': sel.dims, 'gamma': sel.gamma,
                      'cv_folds': folds, 'cv_accuracy': sel.cv_accuracy,
                      'cv_grouped': groups is not None, 'cv_entries': int(len(cv)),
                      'table': sel.table,
                      'grid': {'gammas': list(gammas),
                               'standardize': list(standardize_options),
                               'dims': list(dims_options), 'alphas': list(alphas),
                               'lda_alphas': list(lda_alphas), 'weights': list(weights),
                               'wide_lda': bool(wide_lda), 'ridge': bool(ridge)}},
        'head': sel.head_meta(),
    }
    if matrix_dtype != 'float32':
        meta['matrix_dtype'] = matrix_dtype
    if head.has_ridge:   # fitted on rows rounded as this dtype stores them (store.py checks)
        meta['head']['ridge']['stored_dtype'] = stored_dtype
    if sel.heldout_novelty is not None:
        # The default unknown rule thresholds the calibrated top-1 probability: on a pseudo
        # open set of the train split it separated unseen classes better than the novelty
        # (AUROC 0.850 vs 0.760, experiments/novelty_study.py). Novelty's own threshold is kept
        # for Classifier(novelty_threshold=...).
        meta['unknown_calibration'] = calibrate_unknown(sel.heldout_scores, false_reject_rate)
        meta['novelty_calibration'] = calibrate_novelty(sel.heldout_novelty, false_reject_rate)
    return FeatureBank(features=vote_feats, labels=torch.from_numpy(labels),
                       class_names=list(dataset.class_names), config=encoder.cfg, transform=tf,
                       gamma=sel.gamma, meta=meta, head=head)


# ---- two-section banks
# Two-section banks: complete objects and single-view scans, each with its own head.
#
# One head fitted on complete objects and their scans together serves neither well: its
# knobs, PCA and within-class covariance are dominated by the scans (4 per object), and
# complete objects lose about 2 points. A two-section bank
# keeps the complete objects as the main section (exactly the complete-object bank: own PCA
# width, whitening, LDA, gamma and temperature, all chosen by CV on complete objects) and the
# scans as a second section (own knobs, chosen by CV grouped by source object); a gate
# (bank/model.py `Gate`) says how likely a query is a scan and mixes the two sections'
# probabilities (bank/classifier.py). With the scans' source objects known, the bank also
# gets the object test of taught classes (bank/model.py), fitted on the scan section.

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
    gate = fit_gate(feats, is_scan, gate_dims, gate_shrinkage)
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
        objects = fit_object_test(views.transform.standardized(feats[scan]),
                                 np.asarray(groups)[scan.numpy()], views.labels.numpy(),
                                 views.class_names)
        meta['object_test'] = objects.describe()
    return replace(complete, meta=meta, views=views, gate=gate, objects=objects)
