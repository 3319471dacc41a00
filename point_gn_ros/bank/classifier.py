"""Bank classifier: the bank's head (bank/head.py) over cosine similarities to the bank.

The paper's kernel vote sums exp(-gamma (1 - cos)) per class. With gamma in the
thousands those sums underflow in float32, so they are evaluated relative to the
best entry (log domain). The head fuses the vote (optionally on whitened features)
with LDA log-posteriors and calibrates the result with a temperature:

  probability (B, C)  calibrated class probabilities, rows sum to 1
  scores      (B,)    probability of the top class
  novelty     (B,)    1 - best cosine to any bank entry in the vote's space, [0, 2]

A two-section bank (complete objects + single-view scans, `FeatureBank.views`) evaluates
both sections and mixes them with the gate's p = probability that the query is a scan
(bank/gate.py): probability = (1 - p) complete + p scans, novelty likewise.

A plain-vote bank (format 1, or one CV chose the vote for) has probability = each
class's share of the kernel votes, as before.

A two-section bank with an object test (bank/objects.py) then moves the probabilities of
its taught classes (those enrollment created) by how much nearer the query is to the taught
object than to any built one, and renormalises; with no taught class nothing moves.

A lone query (a batch of one, on the CPU with the compiled kernels) takes bank/lone.py's
path: the same formulas in a few C calls instead of ~40 torch ops, which after a sensor's
idle gap each started cold. Batches take the torch path up to the exact scan's cosines; an
exact section then finishes each row in that compiled code too (`compiled_finish`).

Search (`search=`): 'exact' compares every query with every bank entry (torch);
'indexed' uses bank/search.py's two-stage search (4-bit coarse scan, exact rescoring of
the best candidates, each query alone), built once per Classifier; 'auto' (default)
picks 'indexed' for banks of at least `INDEX_MIN_ENTRIES` entries on the CPU, where a
lone query would otherwise read the whole bank.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from point_gn_ros.bank.head import ExactSearch, VoteSearch
from point_gn_ros.bank.helper import helper_thread
from point_gn_ros.bank.lone import LoneGate, LoneSection
from point_gn_ros.bank.refit import vote_to_z
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.bank.taught import TaughtLayer

UNKNOWN = -1
SEARCHES = ('auto', 'exact', 'indexed')
# 'auto' indexes banks this large. Below it the exact scan stays affordable (shipped bank,
# 9,843 x 640: 2.8-3.5 ms a lone query exact, 1.2-2.0 indexed; about equal per query in
# batches of 16), its labels stay bit-for-bit those of the published figures, and no index
# is built per enrollment (benchmarks/log "Large banks").
INDEX_MIN_ENTRIES = 20_000
# Upper bound on queries x bank entries held at once (float32 similarity block).
_MAX_BLOCK = 1 << 24
# A section whose gate weight is below this is not evaluated for that row: its share of each
# probability would be under 1e-6 (the gate is confident for ~85 % of queries, so most
# queries search one section, not two).
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

    def __len__(self) -> int:
        return int(self.labels.shape[0])


def votes_from_similarity(sims: torch.Tensor, bank_labels: torch.Tensor, num_classes: int,
                          gamma: float) -> torch.Tensor:
    """Kernel-vote shares from cosine similarities.

    sims: (B, N) cosine to each bank entry; bank_labels: (N,) int64 -> (B, C) float32,
    rows sum to 1.
    """
    logits = (sims - 1.0) * gamma                                # (B, N), <= 0
    logits = logits - logits.max(dim=1, keepdim=True).values     # best entry -> exp(0)
    votes = torch.zeros(sims.shape[0], num_classes, dtype=logits.dtype, device=logits.device)
    votes.index_add_(1, bank_labels, logits.exp_())
    return votes / votes.sum(dim=1, keepdim=True)


def class_scores(query: torch.Tensor, bank_feats: torch.Tensor, bank_labels: torch.Tensor,
                 num_classes: int, gamma: float) -> torch.Tensor:
    """Kernel-vote shares.

    query: (B, d) unit rows; bank_feats: (N, d) unit rows; bank_labels: (N,) int64
    -> (B, C) float32, rows sum to 1. Queries are processed in blocks so a large
    bank never needs a huge similarity matrix.
    """
    step = max(1, _MAX_BLOCK // max(1, bank_feats.shape[0]))
    out = [votes_from_similarity(q @ bank_feats.T, bank_labels, num_classes, gamma)
           for q in query.split(step)]
    return torch.cat(out) if out else torch.zeros(0, num_classes)


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
    derived from it where that is exact (bank/search.py `IndexedSearch.derive`).
    """
    if kind == 'indexed':
        from point_gn_ros.bank.search import IndexedSearch
        if isinstance(previous, IndexedSearch):
            return IndexedSearch.derive(previous, bank_u, bank_labels, num_classes)
        return IndexedSearch(bank_u, bank_labels, num_classes)
    if kind != 'exact':
        raise ValueError(f'search kind {kind!r} must be exact or indexed')
    return ExactSearch(bank_u, bank_labels, num_classes)


class Classifier:
    """Classifies encoder features against a loaded bank with the bank's head.

    Unknown rule (label -1), exactly:
      unknown_threshold None or 0   off
      unknown_threshold > 0         top-1 calibrated probability < unknown_threshold
      unknown_threshold < 0         the bank's calibration (`unknown_calibration`): top-1
                                    calibrated probability < its threshold (format 1: top-1
                                    vote share), or novelty > it if its measure is novelty
      novelty_threshold > 0         novelty > novelty_threshold (also combinable)
    """

    def __init__(self, bank: FeatureBank, device: str = 'cpu',
                 unknown_threshold: float | None = None, gamma: float | None = None,
                 novelty_threshold: float | None = None, search: str = 'auto',
                 index_min_entries: int = INDEX_MIN_ENTRIES,
                 previous: 'Classifier | None' = None, object_test: bool = True,
                 fit_threshold: float | None = None,
                 volume_threshold: float | None = None) -> None:
        """Classifier of one bank version (the search is built here, once).

        gamma: override the bank's (comparisons only); search: 'auto', 'exact' or
        'indexed' (module docstring); index_min_entries: the size from which 'auto' indexes;
        previous: the classifier of the version this one follows (an enrollment): its
        indexes are extended instead of rebuilt where that gives the same (`make_search`);
        object_test: apply the bank's object test to its taught classes (bank/objects.py);
        fit_threshold: a query whose shape-and-size fit (bank/taught.py) is below it, or
        whose size lies outside its answer's size region, is unknown (None: no such rule);
        volume_threshold: a query whose share of volumetric
        neighbourhoods (core/surface.py) is above it is unknown (None: no such rule).
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
        # A kernel ridge term reads every entry's cosine: the exact search (bank/ridge.py).
        self.search_kind = 'exact' if self.head.has_ridge else resolve_search(
            search, len(bank.labels), self.device, index_min_entries)
        self.search = make_search(self.search_kind, self.features, self.labels,
                                  bank.num_classes,
                                  None if previous is None else previous.search)
        # A sectioned bank: the scan section has its own classifier, mixed by the gate.
        self.views = None if bank.views is None else Classifier(
            bank.views, device, gamma=None, search=search, index_min_entries=index_min_entries,
            previous=None if previous is None else previous.views)
        self.gate = None if bank.gate is None else bank.gate.to(self.device)
        self.novelty_threshold = novelty_threshold or None
        if unknown_threshold is not None and unknown_threshold < 0:
            calib = bank.meta.get('unknown_calibration')
            if not calib:
                raise ValueError(f'{bank.path}: bank holds no calibrated unknown threshold')
            if calib.get('measure', 'probability') == 'novelty':
                self.novelty_threshold = float(calib['threshold'])
                unknown_threshold = None
            else:
                unknown_threshold = float(calib['threshold'])
        self.unknown_threshold = unknown_threshold or None
        self.fit_threshold = fit_threshold
        self.volume_threshold = volume_threshold
        self._taught: TaughtLayer | None = None
        # The object test's shift of taught classes (bank/objects.py); None: nothing moves.
        self.object_shift = None if bank.objects is None or not object_test \
            else bank.objects.shift_for(bank)
        # A lone query's compiled path (bank/lone.py), where every part of this bank has one.
        self.lone = LoneSection.build(self)
        # A batch's rows finished by it after the exact scan (False: the torch head, which
        # the tests hold it to).
        self.compiled_finish = True
        self.lone_gate = None
        if self.lone is not None and self.views is not None and self.gate is not None:
            self.lone_gate = LoneGate(self.lone.lib, self.gate) if self.views.lone else None
            self.lone = self.lone if self.lone_gate is not None else None

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
        if len(features) == 1 and self.lone is not None:
            return self._evaluate_lone(features)
        if self.views is None or self.gate is None:
            return (*self._section(features), None)
        p_scan = self.gate.scan_probability(features)
        # Each row is the gate's mix of the sections; a section weighing < GATE_SKIP for a
        # row is skipped for it and its weight given to the other one.
        use_c, use_v = p_scan < 1 - GATE_SKIP, p_scan > GATE_SKIP
        # Every row in one section (most lone queries): its result as it is, which is what
        # the mix below gives then (weight 1, the other section's 0), without the masking.
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
        if self.lone_gate is None:
            prob, novelty = self.lone.evaluate(x)
            return torch.from_numpy(prob)[None], torch.tensor([novelty]), None
        p = self.lone_gate(x)
        if p <= GATE_SKIP:
            prob, novelty = self.lone.evaluate(x)
        elif p >= 1 - GATE_SKIP:
            prob, novelty = self.views.lone.evaluate(x)
        else:   # both sections: the scan section on the helper thread (no GIL held there)
            helper = helper_thread()
            scans = helper.submit(self.views.lone.evaluate, x) if helper else None
            prob_c, nov_c = self.lone.evaluate(x)
            prob_v, nov_v = scans.result() if scans else self.views.lone.evaluate(x)
            prob = np.float32(1 - p) * prob_c + np.float32(p) * prob_v
            novelty = (1 - p) * nov_c + p * nov_v
        return (torch.from_numpy(prob)[None], torch.tensor([novelty], dtype=torch.float32),
                torch.tensor([p], dtype=torch.float32))

    def _section(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The section's own head: (B, D) raw features -> probability (B, C), novelty (B,)."""
        lone = self.lone
        if (self.compiled_finish and lone is not None and lone.index is None
                and isinstance(self.search, ExactSearch) and len(features) > 1):
            z, x = self.transform.both(features) if self.head.lda_wide \
                else (self.transform(features), None)
            sims = self.search.similarities(self.head.vote_space(z))
            prob, novelty = lone.finish_rows(sims.numpy(), (x if self.head.lda_wide
                                                            else z).numpy())
            return torch.from_numpy(prob), torch.from_numpy(novelty)
        if not self.head.lda_wide:
            return self.head.evaluate_with(self.transform(features), self.search)
        z, x = self.transform.both(features)         # one standardisation for vote and LDA
        return self.head.evaluate_with(z, self.search, x=x)

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
                 volumes: np.ndarray | None = None) -> Classification:
        """features: (B, D) float32 raw encoder output -> Classification.

        sizes: (B, SIZE_DIM) metric log sizes of the queries (core/size.py), or None for
        inputs without metric meaning. The taught-class prototypes and the size terms
        (bank/taught.py) run when the bank has taught classes, sizes are given, or the
        fit threshold is set; otherwise the head's probabilities are the answer.
        volumes: (B,) shares of volumetric neighbourhoods (core/surface.py) for the volume
        rule, or None.
        """
        prob, novelty, partial = self._evaluate(features)
        prob, novelty = prob.cpu(), novelty.cpu()
        fit = misfit = None
        if len(features) and (sizes is not None or self.fit_threshold is not None
                              or self.bank.meta.get('taught')):
            z = self.transform(features.to(self.device)).cpu()
            prob, fit, misfit = self.taught.apply(prob, z, sizes)
        k = max(1, min(top_k, prob.shape[1]))
        top_s, top_i = prob.topk(k, dim=1)
        labels = top_i[:, 0].clone()
        if self.unknown_threshold is not None:
            labels[top_s[:, 0] < self.unknown_threshold] = UNKNOWN
        if self.novelty_threshold is not None:
            labels[novelty > self.novelty_threshold] = UNKNOWN
        if self.fit_threshold is not None and fit is not None:
            labels[torch.from_numpy(fit < self.fit_threshold)] = UNKNOWN
            if misfit is not None:
                labels[torch.from_numpy(misfit > 1.0)] = UNKNOWN
        if self.volume_threshold is not None and volumes is not None:
            labels[torch.from_numpy(np.asarray(volumes) > self.volume_threshold)] = UNKNOWN
        return Classification(labels=labels.numpy().astype(np.int64),
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
                              else np.asarray(volumes, dtype=np.float32))
