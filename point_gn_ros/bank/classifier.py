"""Bank classifier: one bank version's answer to encoder features.

A query's path, chosen once per Classifier (`Classifier.path`, reported by `point_gn bank
info` and the node's /diagnostics): lone (a batch of one) or batch, times exact or indexed
search, all ending in the compiled head (bank/vote.py `CompiledHead`, pgn_head.c); where the
compiled head does not apply (no kernels, another device, or compiled=False) the torch
reference head (`reference_head`) with the exact search.

  probability (B, C)  calibrated class probabilities, rows sum to 1
  scores      (B,)    probability of the top class
  novelty     (B,)    1 - best cosine to any bank entry in the vote's space, [0, 2]

A two-section bank (complete objects + single-view scans, `FeatureBank.views`) evaluates
both sections and mixes them with the gate's p = probability that the query is a scan
(bank/model.py `Gate`): probability = (1 - p) complete + p scans, novelty likewise; a
section whose weight is below GATE_SKIP for a row is not evaluated for it.

A two-section bank with an object test (bank/model.py `ObjectTest`) then moves the
probabilities of its taught classes by how much nearer the query is to the taught object
than to any built one, and renormalises; with no taught class nothing moves. The taught
classes' prototypes and sizes (bank/taught.py) come last.

Search (`search=`): 'exact' compares every query with every bank entry; 'indexed' uses
bank/index.py's two-stage search (built once per Classifier, each query alone); 'auto'
(default) picks 'indexed' for CPU banks of at least `INDEX_MIN_ENTRIES` entries. A kernel
ridge head reads every entry's cosine: its section is always searched exactly.

The unknown rules (label -1) are the Classifier's alone (`unknown_rules`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from point_gn_ros.bank.discriminant import vote_to_z
from point_gn_ros.bank.index import IndexedSearch
from point_gn_ros.bank.model import ObjectShift
from point_gn_ros.bank.refit import example_counts
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.bank.taught import TaughtLayer
from point_gn_ros.bank.vote import (CompiledGate, CompiledHead, ExactSearch, VoteSearch,
                                    helper_thread, reference_head)
from point_gn_ros.core import kernels

UNKNOWN = -1
SEARCHES = ('auto', 'exact', 'indexed')
# 'auto' indexes banks this large; below it the exact scan costs about what the index does
# and no index is built per enrollment.
INDEX_MIN_ENTRIES = 20_000
# A section whose gate weight is below this is not evaluated for that row: its share of each
# probability would be under 1e-6.
GATE_SKIP = 1e-6


def _evaluate_no_grad(clf: 'Classifier', features: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    with torch.no_grad():        # grad mode is per thread
        return clf.evaluate(features)


@dataclass
class Classification:
    """Per-query results, plain numpy.

    labels (B,) int64, -1 = unknown; scores (B,) float32 (calibrated probability of
    the best class, also when it is rejected as unknown); topk_ids (B, k) int64;
    topk_scores (B, k) float32 (their probabilities); probability (B, C) float32
    (rows sum to 1); novelty (B,) float32 (1 - best cosine to the bank in the vote's
    space: 0 = identical to a bank entry, larger = less like anything in the bank).
    """

    labels: np.ndarray
    scores: np.ndarray
    topk_ids: np.ndarray
    topk_scores: np.ndarray
    probability: np.ndarray | None = None
    novelty: np.ndarray | None = None
    partial: np.ndarray | None = None    # (B,) gate's p(single-view scan); two-section banks
    fit: np.ndarray | None = None        # (B,) shape-and-size fit to the nearest class
                                         # (bank/taught.py); None when the layer did not run
    size_misfit: np.ndarray | None = None  # (B,) the answer's size distance over its class's
                                           # size region (> 1: outside); None without sizes
    volumetric: np.ndarray | None = None  # (B,) share of volumetric neighbourhoods
                                          # (core/surface.py); None without the volume rule
    separated: np.ndarray | None = None   # (B,) share of area apart from the cloud's
                                          # largest part (core/surface.py); None without the
                                          # scene rule
    rejected_by: np.ndarray | None = None  # (B,) object: the unknown rules that made each
                                           # row unknown, '+'-joined ('scene', 'fit+size');
                                           # '' where none did

    def __len__(self) -> int:
        return int(self.labels.shape[0])


def resolve_search(search: str, entries: int, device: torch.device | str = 'cpu',
                   index_min_entries: int = INDEX_MIN_ENTRIES) -> str:
    """'auto' -> 'indexed' for CPU banks of >= index_min_entries entries, else 'exact'."""
    if search not in SEARCHES:
        raise ValueError(f'search={search!r} must be one of {", ".join(SEARCHES)}')
    if search != 'auto':
        return search
    big = entries >= index_min_entries
    return 'indexed' if big and torch.device(device).type == 'cpu' else 'exact'


def make_search(kind: str, bank_u: torch.Tensor, bank_labels: torch.Tensor,
                num_classes: int, previous: VoteSearch | None = None) -> VoteSearch:
    """The vote search `kind` ('exact' or 'indexed') over rows bank_u (N, d), labels (N,).

    previous: the search of the bank version before (an enrollment's); an index is then
    derived from it where that is exact (bank/index.py `IndexedSearch.derive`).
    """
    if kind == 'indexed':
        if isinstance(previous, IndexedSearch):
            return IndexedSearch.derive(previous, bank_u, bank_labels, num_classes)
        return IndexedSearch(bank_u, bank_labels, num_classes)
    if kind != 'exact':
        raise ValueError(f'search kind {kind!r} must be exact or indexed')
    return ExactSearch(bank_u, bank_labels, num_classes)


@dataclass(frozen=True)
class UnknownRules:
    """When a query is unknown (label -1); each rule None is off.

    probability: top-1 calibrated probability below it; novelty: novelty above it;
    fit: shape-and-size fit (bank/taught.py) below it, or the size outside the answer's size
    region (size misfit > 1); volume: share of volumetric neighbourhoods (core/surface.py)
    above it; scene: share of area apart from the cloud's largest part (core/surface.py)
    above it.
    """

    probability: float | None = None
    novelty: float | None = None
    fit: float | None = None
    volume: float | None = None
    scene: float | None = None


def unknown_rules(bank: FeatureBank, unknown_threshold: float | None = None,
                  novelty_threshold: float | None = None, fit_threshold: float | None = None,
                  volume_threshold: float | None = None,
                  scene_threshold: float | None = None) -> UnknownRules:
    """The unknown rules of a bank under the given thresholds.

    unknown_threshold None or 0: off; > 0: top-1 calibrated probability below it; < 0: the
    bank's calibration (`unknown_calibration`): top-1 probability below its threshold, or
    novelty above it when its measure is novelty (a novelty threshold given as well: the
    smaller of the two). novelty_threshold > 0: novelty above it (also combinable).
    Raises ValueError when unknown_threshold < 0 and the bank holds no calibration.
    """
    novelty = novelty_threshold or None
    probability = unknown_threshold or None
    if probability is not None and probability < 0:
        calib = bank.meta.get('unknown_calibration')
        if not calib:
            raise ValueError(f'unknown_threshold={unknown_threshold:g} asks for the calibrated '
                             f'threshold, but {bank.path} holds no calibration')
        probability = None
        if calib.get('measure', 'probability') == 'novelty':
            novelty = float(calib['threshold']) if novelty is None \
                else min(novelty, float(calib['threshold']))
        else:
            probability = float(calib['threshold'])
    return UnknownRules(probability, novelty, fit_threshold, volume_threshold, scene_threshold)


class Classifier:
    """Classifies encoder features against a loaded bank with the bank's head.

    The unknown rules (label -1) are `rules` (`unknown_rules`).
    """

    def __init__(self, bank: FeatureBank, device: str = 'cpu',
                 unknown_threshold: float | None = None, gamma: float | None = None,
                 novelty_threshold: float | None = None, search: str = 'auto',
                 index_min_entries: int = INDEX_MIN_ENTRIES,
                 previous: 'Classifier | None' = None, object_test: bool = True,
                 fit_threshold: float | None = None,
                 volume_threshold: float | None = None, scene_threshold: float | None = None,
                 compiled: bool = True) -> None:
        """Classifier of one bank version (its path and search are chosen here, once).

        gamma: override the bank's (comparisons only); search: 'auto', 'exact' or
        'indexed' (module docstring); index_min_entries: the size from which 'auto' indexes;
        previous: the classifier of the version this one follows (an enrollment): its
        indexes are extended instead of rebuilt where that gives the same (`make_search`);
        object_test: apply the bank's object test to its taught classes; the thresholds:
        `unknown_rules` (the fit rule also makes a query whose size lies outside its answer's
        size region unknown); compiled: False runs the torch reference head (the tests'
        reference).
        """
        self.bank = bank
        self.device = torch.device(device)
        self.head = bank.classifier_head.to(self.device)
        if gamma is not None:
            self.head.gamma = float(gamma)
        self.gamma = self.head.gamma
        self.transform = bank.transform.to(self.device)
        self.features = bank.features.to(self.device)
        self.labels = bank.labels.to(self.device)
        self._choose_path(search, index_min_entries, previous, compiled)
        # A sectioned bank: the scan section has its own classifier, mixed by the gate.
        self.views = None if bank.views is None else Classifier(
            bank.views, device, gamma=None, search=search, index_min_entries=index_min_entries,
            previous=None if previous is None else previous.views, compiled=compiled)
        self.gate = None if bank.gate is None else bank.gate.to(self.device)
        self.rules = unknown_rules(bank, unknown_threshold, novelty_threshold, fit_threshold,
                                   volume_threshold, scene_threshold)
        self._taught: TaughtLayer | None = None
        # The object test's shift of taught classes; None: nothing moves.
        self.object_shift = None if bank.objects is None or not object_test \
            else _object_shift(bank)
        # A lone query runs the compiled path where every part of the bank has one.
        self.lone = self.compiled_head is not None and (
            self.views is None or (self.views.compiled_head is not None and self.gate is not None))
        lib = kernels.load() if self.lone and self.views is not None else None
        self.compiled_gate = None if lib is None else CompiledGate(lib, self.gate)

    def _choose_path(self, search: str, index_min_entries: int,
                     previous: 'Classifier | None', compiled: bool) -> None:
        """The one place a section's path is chosen: its search and its head."""
        bank = self.bank
        kind = 'exact' if self.head.has_ridge else resolve_search(
            search, len(bank.labels), self.device, index_min_entries)
        prev = None if previous is None else previous.search
        self.search: VoteSearch = make_search(kind, self.features, self.labels,
                                              bank.num_classes, prev)
        self.compiled_head = CompiledHead.build(self.transform, self.head, bank.num_classes,
                                                self.search) \
            if compiled and self.device.type == 'cpu' and len(bank.labels) else None
        if self.compiled_head is None and kind == 'indexed':
            # the reference head reads every entry
            kind = 'exact'
            self.search = make_search(kind, self.features, self.labels, bank.num_classes)
        self.search_kind = kind

    @property
    def path(self) -> dict[str, str]:
        """How a query is answered.

        {'head': 'compiled' | 'reference', 'lone': 'compiled' | 'as a batch', 'search': the
        search kind per section}.
        """
        out = {'head': 'compiled' if self.compiled_head is not None else 'reference',
               'lone': 'compiled' if self.lone else 'as a batch',
               'search': self.search_kind}
        if self.views is not None:
            out['search'] = f'{self.search_kind} (complete), {self.views.search_kind} (scans)'
            if self.views.compiled_head is None and self.compiled_head is not None:
                out['head'] = 'compiled (complete), reference (scans)'
        return out

    @property
    def unknown_threshold(self) -> float | None:
        return self.rules.probability

    @property
    def novelty_threshold(self) -> float | None:
        return self.rules.novelty

    @property
    def fit_threshold(self) -> float | None:
        return self.rules.fit

    @property
    def volume_threshold(self) -> float | None:
        return self.rules.volume

    @property
    def scene_threshold(self) -> float | None:
        return self.rules.scene

    def set_unknown_threshold(self, unknown_threshold: float | None) -> None:
        """Re-resolve the probability / calibrated rule (`unknown_rules`), others kept.

        Raises ValueError as `unknown_rules` does; the rules are unchanged then.
        """
        self.rules = replace(unknown_rules(self.bank, unknown_threshold),
                             fit=self.rules.fit, volume=self.rules.volume,
                             scene=self.rules.scene)

    @torch.no_grad()
    def evaluate(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """features: (B, D) raw encoder output -> probability (B, C), novelty (B,)."""
        return self._evaluate(features)[:2]

    def _evaluate(self, features: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """-> probability (B, C), novelty (B,), gate's p(scan) (B,) or None."""
        features = features.to(self.device)
        prob, novelty, p_scan = self._mixed(features)
        if self.object_shift is not None and len(features):
            prob = self.object_shift(prob.cpu(), features).to(self.device)
        return prob, novelty, p_scan

    def _mixed(self, features: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The sections' gate-mixed head: probability (B, C), novelty (B,), p(scan) or None."""
        if len(features) == 1 and self.lone:
            return self._evaluate_lone(features)
        if self.views is None or self.gate is None:
            return (*self._section(features), None)
        p_scan = self.gate.scan_probability(features)
        # Each row is the gate's mix of the sections; a section weighing < GATE_SKIP for a
        # row is skipped for it and its weight given to the other one.
        use_c, use_v = p_scan < 1 - GATE_SKIP, p_scan > GATE_SKIP
        # Every row in one section: its result as it is, which is what the mix below gives
        # then (weight 1, the other section's 0), without the masking.
        if not use_v.any():
            return (*self._section(features), p_scan)
        if not use_c.any():
            return (*self.views.evaluate(features), p_scan)
        g = torch.where(use_v, torch.where(use_c, p_scan, 1.0), 0.0)
        # Both sections: the scan section on the helper thread while this one evaluates the
        # complete section (their scans release the GIL); the same results either way.
        helper = helper_thread() if self.device.type == 'cpu' else None
        scans = helper.submit(_evaluate_no_grad, self.views, features[use_v]) if helper \
            else None
        parts = [self._section(features[use_c]),
                 scans.result() if scans else self.views.evaluate(features[use_v])]
        prob = torch.zeros(len(features), len(self.bank.class_names), device=self.device)
        novelty = torch.zeros(len(features), device=self.device)
        for rows, weight, (p, n) in zip((use_c, use_v), (1 - g, g), parts, strict=True):
            prob[rows] += weight[rows, None] * p
            novelty[rows] += weight[rows] * n
        return prob, novelty, p_scan

    def _evaluate_lone(self, features: torch.Tensor
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """`_evaluate` of one query (1, D) by the compiled path: the same formulas."""
        x = np.ascontiguousarray(features[0].detach().numpy(), dtype=np.float32)
        if self.compiled_gate is None:
            prob, novelty = self.compiled_head.evaluate(x)
            return torch.from_numpy(prob)[None], torch.tensor([novelty]), None
        p = self.compiled_gate(x)
        complete, scans = self.compiled_head, self.views.compiled_head
        if p <= GATE_SKIP:
            prob, novelty = complete.evaluate(x)
        elif p >= 1 - GATE_SKIP:
            prob, novelty = scans.evaluate(x)
        else:   # both sections: the scan section on the helper thread (no GIL held there)
            helper = helper_thread()
            pending = helper.submit(scans.evaluate, x) if helper else None
            prob_c, nov_c = complete.evaluate(x)
            prob_v, nov_v = pending.result() if pending else scans.evaluate(x)
            prob = np.float32(1 - p) * prob_c + np.float32(p) * prob_v
            novelty = (1 - p) * nov_c + p * nov_v
        return (torch.from_numpy(prob)[None], torch.tensor([novelty], dtype=torch.float32),
                torch.tensor([p], dtype=torch.float32))

    def _section(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The section's own head: (B, D) raw features -> probability (B, C), novelty (B,)."""
        if self.head.lda_wide:
            z, x = self.transform.both(features)     # one standardisation for vote and LDA
        else:
            z, x = self.transform(features), None
        if self.compiled_head is None or not len(features):
            return reference_head(self.head, z, self.search, x=x)
        prob, novelty = self.compiled_head.finish_rows(self.head.vote_space(z),
                                                       x if self.head.lda_wide else z)
        return torch.from_numpy(prob), torch.from_numpy(novelty)

    @torch.no_grad()
    def scores(self, features: torch.Tensor) -> torch.Tensor:
        """features: (B, D) raw encoder output -> (B, C) calibrated class probabilities."""
        return self.evaluate(features)[0]

    @property
    def taught(self) -> TaughtLayer:
        """The bank's prototypes and size models (bank/taught.py), built on first use."""
        if self._taught is None:
            self._taught = TaughtLayer.build(
                self.bank.meta, self.bank.class_names,
                vote_to_z(self.bank.features, self.bank.head), self.bank.labels)
        return self._taught

    @torch.no_grad()
    def classify(self, features: torch.Tensor, top_k: int = 5,
                 sizes: np.ndarray | None = None,
                 volumes: np.ndarray | None = None,
                 separated: np.ndarray | None = None) -> Classification:
        """features: (B, D) float32 raw encoder output -> Classification.

        sizes: (B, SIZE_DIM) metric log sizes of the queries (core/size.py), or None for
        inputs without metric meaning. The taught-class prototypes and the size terms
        (bank/taught.py) run when the bank has taught classes, sizes are given, or the
        fit threshold is set; otherwise the head's probabilities are the answer.
        volumes: (B,) shares of volumetric neighbourhoods (core/surface.py) for the volume
        rule, or None; separated: (B,) shares of area apart from each cloud's largest part
        (core/surface.py) for the scene rule, or None.
        """
        prob, novelty, partial = self._evaluate(features)
        prob, novelty = prob.cpu(), novelty.cpu()
        fit = misfit = None
        if len(features) and (sizes is not None or self.rules.fit is not None
                              or self.bank.meta.get('taught')):
            z = self.transform(features.to(self.device)).cpu()
            prob, fit, misfit = self.taught.apply(prob, z, sizes)
        k = max(1, min(top_k, prob.shape[1]))
        top_s, top_i = prob.topk(k, dim=1)
        labels = top_i[:, 0].numpy().astype(np.int64)
        rules = self.rules
        # each rule that is on and measured: (B,) bool, the rows it makes unknown
        by = {'probability': None if rules.probability is None
              else (top_s[:, 0] < rules.probability).numpy(),
              'novelty': None if rules.novelty is None
              else (novelty > rules.novelty).numpy(),
              'fit': None if rules.fit is None or fit is None else fit < rules.fit,
              'size': None if rules.fit is None or misfit is None else misfit > 1.0,
              'volume': None if rules.volume is None or volumes is None
              else np.asarray(volumes) > rules.volume,
              'scene': None if rules.scene is None or separated is None
              else np.asarray(separated) > rules.scene}
        by = {name: mask for name, mask in by.items() if mask is not None}
        rejected_by = np.array(['+'.join(n for n, m in by.items() if m[i])
                                for i in range(len(labels))], dtype=object)
        labels[rejected_by != ''] = UNKNOWN
        return Classification(labels=labels,
                              scores=top_s[:, 0].numpy().astype(np.float32),
                              topk_ids=top_i.numpy().astype(np.int64),
                              topk_scores=top_s.numpy().astype(np.float32),
                              probability=prob.numpy().astype(np.float32),
                              novelty=novelty.numpy().astype(np.float32),
                              partial=None if partial is None
                              else partial.cpu().numpy().astype(np.float32),
                              fit=None if fit is None else fit.astype(np.float32),
                              size_misfit=None if misfit is None
                              else misfit.astype(np.float32),
                              volumetric=None if volumes is None
                              else np.asarray(volumes, dtype=np.float32),
                              separated=None if separated is None
                              else np.asarray(separated, dtype=np.float32),
                              rejected_by=rejected_by)


def _object_shift(bank: FeatureBank) -> ObjectShift | None:
    """The object test's shift of this bank version's taught classes, or None."""
    views = bank.views
    if views is None or bank.objects is None:
        return None
    built = bank.built_classes
    removed = {e.class_name for e in bank.enrollments if e.action == 'remove'}
    return bank.objects.shift(bank.class_names, built, removed, views.transform, views.head,
                              example_counts(views))
