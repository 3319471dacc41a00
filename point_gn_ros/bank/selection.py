"""Choosing the head, feature transform and open-set threshold by cross-validation on the bank.

Nothing here ever sees a test split: every figure is a held-out fold of the bank.
One transform fit and one similarity product per fold and vote space, reused for
every gamma; the whitening for every shrinkage comes from one eigen-decomposition
per fold.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
import itertools

import numpy as np
import torch

from point_gn_ros.bank.discriminant import (RIDGE_MAX_ENTRIES, CovarianceFit, best_temperature,
                                            ridge_cv_scores)
from point_gn_ros.bank.model import FeatureTransform, Standardize
from point_gn_ros.bank.vote import log_vote_shares

DEFAULT_GAMMAS = tuple(5.0 * 2.0 ** k for k in range(11))          # 5 .. 5120
DEFAULT_ALPHAS = (0.05, 0.1, 0.2, 0.4)                # whitening of the vote (a matmul each)
DEFAULT_LDA_ALPHAS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.4)  # LDA covariance (nearly free in CV)
DEFAULT_WEIGHTS = (0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 1.0, 2.0)
# Kernel ridge term (bank/discriminant.py), tried only when asked (`select(ridge=True)`): kernel
# widths, regularisers and weights in the fused score (ridge scores span ~1, log vote shares
# tens of nats). Yaw-aligned ModelNet40 train, 5 folds: 89.9 % with it, 88.7 % without.
RIDGE_GAMMAS = (0.25, 0.5, 1.0, 2.0)
RIDGE_LAMBDAS = (0.001, 0.003, 0.01, 0.03)
RIDGE_WEIGHTS = (10.0, 30.0, 100.0, 300.0, 1000.0)
# Below this many entries CV runs single-threaded (_threads_for).
_SMALL_BANK = 2000
# Gamma of the plain vote when the bank is too small to cross-validate anything.
FALLBACK_GAMMA = 100.0


def stratified_folds(labels: np.ndarray, k: int = 5, seed: int = 0,
                     groups: np.ndarray | None = None) -> list[np.ndarray]:
    """Split indices into k folds with every class spread evenly: list of (n_i,) int64.

    groups: (N,) int or None. Entries sharing a group id (a source object and its
    simulated views) always land in the same fold, so no fold is scored against a
    near-copy of itself; a group takes the label of its first entry for stratification.
    """
    labels = np.asarray(labels)
    if groups is None:
        rng = np.random.default_rng(seed)
        folds: list[list[int]] = [[] for _ in range(k)]
        offset = 0
        for c in np.unique(labels):
            idx = rng.permutation(np.flatnonzero(labels == c))
            for j, i in enumerate(idx):
                folds[(j + offset) % k].append(int(i))
            offset += len(idx)
        return [np.sort(np.asarray(f, dtype=np.int64)) for f in folds]
    groups = np.asarray(groups)
    if groups.shape != labels.shape:
        raise ValueError(f'groups {groups.shape} must match labels {labels.shape}')
    uniq, first, inverse = np.unique(groups, return_index=True, return_inverse=True)
    members = [np.flatnonzero(inverse == g) for g in range(len(uniq))]
    group_label = labels[first]
    rng = np.random.default_rng(seed)
    fold_of_group = np.empty(len(uniq), dtype=np.int64)
    total = np.zeros(k, dtype=np.int64)
    for c in np.unique(group_label):
        gs = rng.permutation(np.flatnonzero(group_label == c))
        per_class = np.zeros(k, dtype=np.int64)
        # Largest groups first, each to the fold holding fewest of this class (then fewest
        # overall): near-even class counts per fold even with uneven group sizes.
        for g in sorted(gs, key=lambda g: -len(members[g])):
            f = int(np.lexsort((total, per_class))[0])
            fold_of_group[g] = f
            per_class[f] += len(members[g])
            total[f] += len(members[g])
    return [np.sort(np.concatenate([members[g] for g in np.flatnonzero(fold_of_group == f)]
                                   + [np.zeros(0, dtype=np.int64)])).astype(np.int64)
            for f in range(k)]


@dataclass
class Selection:
    """Best knobs, the CV table they were picked from and the held-out figures.

    The plain vote is alpha None, whiten_vote False, fusion_weight 0, temperature 1.
    """

    gamma: float
    standardize: Standardize
    dims: int | None
    cv_accuracy: float
    table: list[dict] = field(default_factory=list)
    heldout_scores: np.ndarray | None = None    # (N,) held-out calibrated top-1 probability
    heldout_correct: np.ndarray | None = None   # (N,) bool
    heldout_novelty: np.ndarray | None = None   # (N,) held-out novelty (1 - best cosine)
    alpha: float | None = None                  # shrinkage of the vote's whitening
    whiten_vote: bool = False
    lda_alpha: float | None = None              # shrinkage of the LDA covariance
    lda_wide: bool = False                      # LDA on the standardised rows, not z
    fusion_weight: float = 0.0
    temperature: float = 1.0
    cv_log_loss: float | None = None
    vote_cv_accuracy: float | None = None       # plain vote, best gamma, same CV folds
    folds_used: int = 0
    fallback: str | None = None                 # why CV was reduced or skipped
    ridge_gamma: float = 0.0                    # kernel ridge term: weight 0 = none
    ridge_lambda: float = 0.0
    ridge_weight: float = 0.0
    ridge_table: list[dict] = field(default_factory=list)
    temperature_without_ridge: float | None = None   # T of the same head without the term

    def head_meta(self) -> dict:
        """JSON-ready head settings and CV figures (what `bank info` prints)."""
        ridge = {} if not self.ridge_table else {'ridge': {
            'gamma': self.ridge_gamma, 'lambda': self.ridge_lambda, 'weight': self.ridge_weight,
            'temperature': self.temperature if self.ridge_weight > 0 else None,
            'temperature_without': self.temperature_without_ridge, 'table': self.ridge_table}}
        return {**ridge, 'alpha': self.alpha, 'whiten_vote': self.whiten_vote,
                'lda_alpha': self.lda_alpha, 'lda_wide': self.lda_wide,
                'fusion_weight': self.fusion_weight,
                'temperature': self.temperature, 'cv_log_loss': self.cv_log_loss,
                'vote_cv_accuracy': self.vote_cv_accuracy, 'folds_used': self.folds_used,
                'fallback': self.fallback}


def _min_class_groups(labels: np.ndarray, groups: np.ndarray | None) -> int:
    """Fewest independent objects (groups, else entries) of any class present."""
    if len(labels) == 0:
        return 0
    if groups is None:
        counts = np.bincount(labels)
    else:
        counts = np.bincount(np.unique(np.stack([labels, np.asarray(groups)]), axis=1)[0])
    return int(counts[counts > 0].min())        # classes with no entries at all: ignored


@dataclass
class _FoldScores:
    """Out-of-fold scores of one (standardize, dims) over the whole bank."""

    votes: dict[float | None, torch.Tensor]     # vote space (None: plain) -> (G, N, C) log shares
    best_cos: dict[float | None, torch.Tensor]  # vote space -> (N,) best cosine to the fold bank
    lda: dict[tuple[float, bool], torch.Tensor]  # (alpha, wide) -> (N, C) LDA log-probs


def _fold_scores(feats: torch.Tensor, lab: torch.Tensor, num_classes: int,
                 parts: list[np.ndarray], standardize: Standardize, dims: int | None,
                 gammas: tuple[float, ...], alphas: tuple[float, ...],
                 lda_alphas: tuple[float, ...], whiten_options: tuple[bool, ...],
                 wide: dict[float, torch.Tensor] | None = None) -> _FoldScores:
    """wide: `_wide_lda_scores` of the same folds and standardisation, or None."""
    n, g = len(lab), len(gammas)
    spaces: list[float | None] = [None] if False in whiten_options else []
    if True in whiten_options:
        spaces += list(alphas)
    out = _FoldScores({a: torch.zeros(g, n, num_classes) for a in spaces},
                      {a: torch.zeros(n) for a in spaces},
                      {(a, False): torch.zeros(n, num_classes) for a in lda_alphas})
    if wide is not None:
        out.lda.update({(a, True): scores for a, scores in wide.items()})
    everything = np.arange(n)

    def vote(space: float | None, sims: torch.Tensor, val: np.ndarray, train: np.ndarray) -> None:
        vi = torch.from_numpy(val)
        out.best_cos[space][vi] = sims.max(dim=1).values
        for gi, gamma in enumerate(gammas):
            out.votes[space][gi, vi] = log_vote_shares(sims, lab[train], num_classes, gamma)

    for val in parts:
        train = np.setdiff1d(everything, val)
        tf = FeatureTransform.fit(feats[train], standardize, dims)
        z_tr, z_val = tf(feats[train]), tf(feats[val])
        if None in spaces:
            vote(None, z_val @ z_tr.T, val, train)   # once per fold, reused for every gamma
        if not alphas and not lda_alphas:
            continue
        fit = CovarianceFit.fit(z_tr, lab[train], num_classes)
        c_tr, c_val = fit.coords(z_tr), fit.coords(z_val)     # once per fold
        for a in lda_alphas:
            logits = fit.lda_logits(c_val, a)
            out.lda[a, False][torch.from_numpy(val)] = torch.log_softmax(logits, dim=1).float()
        for a in alphas:
            if a in spaces:
                u_tr = torch.nn.functional.normalize(fit.whitened(c_tr, a), dim=1)
                u_val = torch.nn.functional.normalize(fit.whitened(c_val, a), dim=1)
                vote(a, u_val @ u_tr.T, val, train)
    return out


def _wide_lda_scores(feats: torch.Tensor, lab: torch.Tensor, num_classes: int,
                     parts: list[np.ndarray], standardize: Standardize,
                     lda_alphas: tuple[float, ...]) -> dict[float, torch.Tensor]:
    """Out-of-fold log-probabilities (N, C) per shrinkage of the LDA on every standardised dim.

    It does not depend on the PCA width, so CV computes it once per standardisation.
    """
    out = {a: torch.zeros(len(lab), num_classes) for a in lda_alphas}
    for val in parts:
        train = np.setdiff1d(np.arange(len(lab)), val)
        tf = FeatureTransform.fit(feats[train], standardize, None)
        fit = CovarianceFit.fit(tf.standardized(feats[train]), lab[train], num_classes)
        coords = fit.coords(tf.standardized(feats[val]))
        for a in lda_alphas:
            out[a][torch.from_numpy(val)] = torch.log_softmax(fit.lda_logits(coords, a),
                                                              dim=1).float()
    return out


@contextmanager
def _threads_for(n: int) -> Iterator[None]:
    """One torch thread for small banks: thousands of tiny ops lose to thread hand-offs."""
    before = torch.get_num_threads()
    if n < _SMALL_BANK:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def select(feats: torch.Tensor, labels: np.ndarray, num_classes: int,
           gammas: tuple[float, ...] = DEFAULT_GAMMAS,
           standardize_options: tuple[Standardize, ...] = ('none', 'standardize'),
           dims_options: tuple[int | None, ...] = (None,), folds: int = 5,
           seed: int = 0, groups: np.ndarray | None = None,
           alphas: tuple[float, ...] = DEFAULT_ALPHAS,
           weights: tuple[float, ...] = DEFAULT_WEIGHTS,
           whiten_options: tuple[bool, ...] = (False, True),
           lda_alphas: tuple[float, ...] = DEFAULT_LDA_ALPHAS,
           wide_lda: bool = False, ridge: bool = False) -> Selection:
    """Grid search by stratified k-fold CV on the bank.

    feats: (N, D) float32 raw encoder features; labels: (N,) int; groups: (N,) int or
    None (entries of one group never split across folds). Chooses standardisation,
    PCA width, whether the vote runs on whitened features (and their shrinkage),
    gamma, the LDA shrinkage and fusion weight by held-out accuracy (ties: the earlier,
    simpler one: plain vote, smaller weight), then the temperature by held-out
    log-loss. alphas: whitening shrinkages; lda_alphas: LDA shrinkages. alphas=() or
    weights=(0,) gives the plain kernel vote. With fewer than
    `folds` objects in some class the folds shrink to that count; with one, no CV is
    possible and the plain vote with FALLBACK_GAMMA is returned (`fallback` says why).
    wide_lda: also try each LDA on the standardised rows before the PCA (bank/model.py);
    ties keep the LDA on z. ridge: then also try a kernel ridge term (bank/discriminant.py) in the
    chosen vote space, kept only if it raises the held-out accuracy.
    """
    if ridge and len(labels) > RIDGE_MAX_ENTRIES:
        raise ValueError(f'a kernel ridge head fits banks of at most {RIDGE_MAX_ENTRIES} '
                         f'entries (its (N, N) solve), this one has {len(labels)}')
    with _threads_for(len(labels)):
        return _select(feats, labels, num_classes, gammas, standardize_options, dims_options,
                       folds, seed, groups, alphas, weights, whiten_options, lda_alphas,
                       wide_lda, ridge)


def _select(feats: torch.Tensor, labels: np.ndarray, num_classes: int,
            gammas: tuple[float, ...], standardize_options: tuple[Standardize, ...],
            dims_options: tuple[int | None, ...], folds: int, seed: int,
            groups: np.ndarray | None, alphas: tuple[float, ...], weights: tuple[float, ...],
            whiten_options: tuple[bool, ...], lda_alphas: tuple[float, ...],
            wide_lda: bool = False, ridge: bool = False) -> Selection:
    labels = np.asarray(labels, dtype=np.int64)
    lab = torch.from_numpy(labels)
    m = _min_class_groups(labels, groups)
    if m < 2:
        return Selection(gamma=FALLBACK_GAMMA, standardize=standardize_options[0], dims=None,
                         cv_accuracy=float('nan'), folds_used=0,
                         fallback=f'a class has {m} independent example(s): no held-out data '
                                  f'for CV; plain kernel vote, gamma {FALLBACK_GAMMA:g}')
    k = min(folds, m)
    fallback = None if k == folds else (f'a class has only {m} independent examples: '
                                        f'{k}-fold CV instead of {folds}')
    if not alphas or not any(w > 0 for w in weights):
        alphas, lda_alphas, weights = (), (), (0.0,)
    if not alphas:
        whiten_options = (False,)
    if not any(w > 0 for w in weights):
        lda_alphas = ()
    weights = tuple(sorted({0.0, *weights}))
    parts = stratified_folds(labels, k, seed, groups)
    table: list[dict] = []
    best: tuple | None = None            # (acc, fused, settings, best_cos)
    vote_best = -1.0
    wide_by_std: dict[str, dict[float, torch.Tensor]] = {}
    for std, dims in itertools.product(standardize_options, dims_options):
        if dims is not None and dims >= min(len(p) for p in parts) * (k - 1):
            continue                     # PCA wider than a fold's bank: not fittable
        wide = None
        if wide_lda and lda_alphas and dims is not None and dims < feats.shape[1]:
            if std not in wide_by_std:   # without a projection it would be the same LDA
                wide_by_std[std] = _wide_lda_scores(feats, lab, num_classes, parts, std,
                                                    lda_alphas)
            wide = wide_by_std[std]
        fs = _fold_scores(feats, lab, num_classes, parts, std, dims, gammas, alphas,
                          lda_alphas, whiten_options, wide)
        for space, votes in fs.votes.items():
            for gi, gamma in enumerate(gammas):
                v = votes[gi]
                acc0 = float((v.argmax(1) == lab).double().mean())
                if space is None:
                    vote_best = max(vote_best, acc0)
                row = {'standardize': std, 'dims': dims, 'whiten_alpha': space, 'gamma': gamma,
                       'vote_accuracy': acc0, 'lda_alpha': None, 'lda_wide': False,
                       'weight': 0.0, 'cv_accuracy': acc0}
                cands = [(acc0, None, 0.0)]
                for key, w in itertools.product(fs.lda, weights[1:]):
                    acc = float(((v + w * fs.lda[key]).argmax(1) == lab).double().mean())
                    cands.append((acc, key, w))
                for acc, key, w in cands:
                    if acc > row['cv_accuracy'] + 1e-12:
                        row.update(cv_accuracy=acc, lda_alpha=key[0], lda_wide=key[1],
                                   weight=w)
                table.append(row)
                if best is None or row['cv_accuracy'] > best[0] + 1e-12:
                    key, w = (row['lda_alpha'], row['lda_wide']), row['weight']
                    fused = v + w * fs.lda[key] if w > 0 else v.clone()
                    best = (row['cv_accuracy'], fused, dict(row), fs.best_cos[space].clone())
    if best is None:
        raise ValueError('no (standardize, dims) option fits this bank')
    acc, fused, row, best_cos = best
    ridge_row: dict = {'gamma': 0.0, 'lambda': 0.0, 'weight': 0.0}
    ridge_table: list[dict] = []
    t_without = None
    if ridge:
        t_without = best_temperature(fused, labels)[0]   # an enrollment's fallback (refit.py)
        acc, fused, ridge_row, ridge_table = _with_ridge(feats, lab, num_classes, parts, row,
                                                         acc, fused)
    t, loss = best_temperature(fused, labels)
    prob = torch.softmax(fused.double() / t, dim=1)
    top, pred = prob.max(dim=1)
    return Selection(gamma=row['gamma'], standardize=row['standardize'], dims=row['dims'],
                     cv_accuracy=acc, table=table, heldout_scores=top.float().numpy(),
                     heldout_correct=(pred == lab).numpy(),
                     heldout_novelty=(1.0 - best_cos).clamp_min(0).numpy(),
                     alpha=row['whiten_alpha'], whiten_vote=row['whiten_alpha'] is not None,
                     lda_alpha=row['lda_alpha'], lda_wide=row['lda_wide'],
                     fusion_weight=row['weight'], temperature=t,
                     cv_log_loss=loss, vote_cv_accuracy=vote_best if vote_best >= 0 else None,
                     folds_used=k, fallback=fallback, ridge_gamma=ridge_row['gamma'],
                     ridge_lambda=ridge_row['lambda'], ridge_weight=ridge_row['weight'],
                     ridge_table=ridge_table, temperature_without_ridge=t_without)


def _with_ridge(feats: torch.Tensor, lab: torch.Tensor, num_classes: int,
                parts: list[np.ndarray], row: dict, acc: float, fused: torch.Tensor
                ) -> tuple[float, torch.Tensor, dict, list[dict]]:
    """The chosen row's fused scores (N, C) with the best kernel ridge term, if any helps.

    Out-of-fold ridge scores in the row's vote space for every (gamma, lambda) of the grid.
    -> (accuracy, fused, {'gamma', 'lambda', 'weight'} (weight 0: none), CV table).
    """
    scores = {key: torch.zeros(len(lab), num_classes)
              for key in itertools.product(RIDGE_GAMMAS, RIDGE_LAMBDAS)}
    for val in parts:
        train = np.setdiff1d(np.arange(len(lab)), val)
        tf = FeatureTransform.fit(feats[train], row['standardize'], row['dims'])
        u_tr, u_val = tf(feats[train]), tf(feats[val])
        if row['whiten_alpha'] is not None:
            fit = CovarianceFit.fit(u_tr, lab[train], num_classes)
            u_tr, u_val = (torch.nn.functional.normalize(
                fit.whitened(fit.coords(u), row['whiten_alpha']), dim=1) for u in (u_tr, u_val))
        for key, s in ridge_cv_scores(u_tr, u_val, lab[train], num_classes, RIDGE_GAMMAS,
                                          RIDGE_LAMBDAS).items():
            scores[key][torch.from_numpy(val)] = s
    best: tuple = (acc, fused, {'gamma': 0.0, 'lambda': 0.0, 'weight': 0.0})
    table = []
    for (g, lam), w in itertools.product(scores, RIDGE_WEIGHTS):
        f = fused + w * scores[g, lam]
        a = float((f.argmax(1) == lab).double().mean())
        table.append({'gamma': g, 'lambda': lam, 'weight': w, 'cv_accuracy': a})
        if a > best[0] + 1e-12:
            best = (a, f, {'gamma': g, 'lambda': lam, 'weight': w})
    return best[0], best[1], best[2], table


def calibrate_unknown(heldout_scores: np.ndarray, false_reject_rate: float = 0.05) -> dict:
    """Threshold on the top-1 probability rejecting `false_reject_rate` of held-out bank objects.

    Every bank object is a known class, so the share of them falling below the
    threshold is exactly the false-reject rate expected on in-distribution input.
    """
    thr = float(np.quantile(heldout_scores, false_reject_rate))
    return {'measure': 'probability', 'threshold': thr,
            'false_reject_rate': float(false_reject_rate),
            'method': f'{false_reject_rate:.0%} quantile of held-out (k-fold) top-1 scores'}


def calibrate_novelty(heldout_novelty: np.ndarray, false_reject_rate: float = 0.05) -> dict:
    """Threshold on novelty rejecting `false_reject_rate` of held-out bank objects.

    Objects whose novelty exceeds it are unknown; held-out novelty is measured against
    the rest of the bank (k-fold), so it errs on the side of rejecting fewer.
    """
    thr = float(np.quantile(heldout_novelty, 1.0 - false_reject_rate))
    return {'measure': 'novelty', 'threshold': thr,
            'false_reject_rate': float(false_reject_rate),
            'method': f'{1 - false_reject_rate:.0%} quantile of held-out (k-fold) novelty'}
