"""The bank's typed parts: feature transform, discriminant head, gate, object test.

Plain data with the arithmetic a query needs; their fitting lives in bank/discriminant.py,
their file form in bank/store.py, the vote that reads them in bank/vote.py.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch

# ---- the feature transform: standardise, project, L2-normalise (fitted on the bank only)

Standardize = Literal['none', 'centre', 'standardize']


@dataclass
class FeatureTransform:
    """x -> normalize(((x - mean) / scale) @ projection).

    mean, scale: (D,) float32; projection: (D, d) float32 or None. Fitted on bank
    features only, so queries never influence it.
    """

    mean: torch.Tensor
    scale: torch.Tensor
    projection: torch.Tensor | None = None

    @classmethod
    def identity(cls, dim: int) -> 'FeatureTransform':
        return cls(torch.zeros(dim), torch.ones(dim), None)

    @classmethod
    def fit(cls, feats: torch.Tensor, standardize: Standardize = 'standardize',
            dims: int | None = None) -> 'FeatureTransform':
        """Fit on bank features: feats (N, D) float32."""
        feats = feats.float()
        d = feats.shape[1]
        mean = feats.mean(0) if standardize != 'none' else torch.zeros(d)
        scale = torch.ones(d)
        if standardize == 'standardize':
            # Floor at a small share of the typical spread: near-constant
            # dimensions must not be blown up into noise.
            std = feats.std(0)
            scale = std.clamp_min(1e-3 * float(std.median()) + 1e-12)
        projection = None
        if dims is not None and dims < d:
            z = (feats - mean) / scale
            # PCA basis of the bank; sign fixed so the file is reproducible.
            _, _, v = torch.linalg.svd(z - z.mean(0), full_matrices=False)
            basis = v[:dims].T.contiguous()
            signs = torch.sign(basis[basis.abs().argmax(0), torch.arange(dims)])
            projection = basis * signs
        return cls(mean, scale, projection)

    @property
    def in_dim(self) -> int:
        return int(self.mean.shape[0])

    @property
    def out_dim(self) -> int:
        return self.in_dim if self.projection is None else int(self.projection.shape[1])

    def to(self, device: torch.device | str) -> 'FeatureTransform':
        proj = None if self.projection is None else self.projection.to(device)
        return FeatureTransform(self.mean.to(device), self.scale.to(device), proj)

    def _scaled(self, feats: torch.Tensor) -> torch.Tensor:
        return (feats.float() - self.mean) / self.scale

    def standardized(self, feats: torch.Tensor) -> torch.Tensor:
        """feats: (B, D) float32 -> (B, D) float32 unit rows, standardised, not projected.

        What a wide LDA reads (bank/model.py): every encoder dim, not only the PCA's.
        """
        return torch.nn.functional.normalize(self._scaled(feats), dim=1, eps=1e-12)

    def both(self, feats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """feats: (B, D) -> (self(feats), standardized(feats)) from one standardisation."""
        s = self._scaled(feats)
        x = torch.nn.functional.normalize(s, dim=1, eps=1e-12)
        if self.projection is None:
            return x, x
        return torch.nn.functional.normalize(s @ self.projection, dim=1, eps=1e-12), x

    def __call__(self, feats: torch.Tensor) -> torch.Tensor:
        """feats: (B, D) float32 -> (B, out_dim) float32, unit L2 norm."""
        z = self._scaled(feats)
        if self.projection is not None:
            z = z @ self.projection
        return torch.nn.functional.normalize(z, dim=1, eps=1e-12)


# ---- the discriminant head
# Closed-form discriminant head on bank features: whitened kernel vote fused with LDA.
#
# Fitted from the bank alone (no gradient training). On transformed bank features z
# (standardised, optionally PCA-projected, L2-normalised: `FeatureTransform`):
#
#   Sigma        pooled within-class covariance of z, (d, d)
#   Sigma_a      (1 - a) Sigma + a tr(Sigma)/d I             shrinkage a in (0, 1]
#   W            Sigma_a^(-1/2) (symmetric)                  whitening
#   u            normalize(z W)                              whitened, re-normalised
#   log_vote_c   log share of class c in sum_i exp(gamma (cos(u, u_i) - 1))
#   lda_c        z Sigma_a^-1 mu_c - mu_c Sigma_a^-1 mu_c / 2 + log prior_c
#   fused_c      log_vote_c + w log_softmax(lda)_c
#   probability  softmax(fused / T)                          T: temperature by CV log-loss
#   novelty      1 - max_i cos(u, u_i)                       in [0, 2]; 0 = a bank entry
#
# A kernel ridge term (bank/discriminant.py, `ridge_coef`) adds ridge_weight x sum_i k(u, u_i) A_ic
# to fused: per-entry coefficients A (N, C) fitted in closed form so the bank reproduces its
# own labels under a wide kernel k; it needs every entry's cosine (the exact search).
#
# A wide LDA (`lda_wide`) fits the LDA on the transform's standardised rows before the PCA
# projection (x = `FeatureTransform.standardized`, all D encoder dims) instead of on z: the PCA
# keeps the directions of most spread, not those that separate classes best. Its coefficients
# are (C, D); it keeps its precision Sigma_a^-1 (D, D) and class means (C, D) so an enrollment
# can add a class in closed form under the kept covariance (bank/refit.py).
#
# The plain kernel vote is the case W = None (vote on z), w = 0, T = 1: its
# probability is exactly the vote share. The bank stores its entries already
# whitened (u_i), so a query costs one (d, d) product more than the plain vote.

# exp() of a kernel logit this far below the best entry underflows float32: floor there.
_TINY = float(torch.finfo(torch.float32).tiny)
# Kernel logits are floored here (relative to the best entry) before exp(): below it
# exp() gives float32 denormals, which are many times slower to add, and the mass is
# negligible beside the best entry's 1.
LOGIT_FLOOR = -80.0


@dataclass
class Head:
    """A fitted head (see module docstring). Tensors float32 on one device.

    whiten: (d, d) or None; lda_coef: (C, d) or None ((C, D) when lda_wide); lda_bias:
    (C,) or None. lda_wide: the LDA reads the standardised rows x (B, D), not z;
    lda_precision (D, D) and lda_means (C, D): what an enrollment refits it from.
    """

    gamma: float
    whiten: torch.Tensor | None = None
    lda_coef: torch.Tensor | None = None
    lda_bias: torch.Tensor | None = None
    fusion_weight: float = 0.0
    temperature: float = 1.0
    lda_wide: bool = False
    lda_precision: torch.Tensor | None = None
    lda_means: torch.Tensor | None = None
    lda_trace: float = 0.0       # wide LDA: tr(Sigma_a^-1 Sigma) (lda_noise_trace)
    ridge_coef: torch.Tensor | None = None   # (N, C): one row per bank entry
    ridge_gamma: float = 0.0
    ridge_lambda: float = 0.0
    ridge_weight: float = 0.0

    @property
    def is_plain_vote(self) -> bool:
        return self.whiten is None and (self.lda_coef is None or self.fusion_weight == 0) \
            and not self.has_ridge

    @property
    def has_ridge(self) -> bool:
        return self.ridge_coef is not None and self.ridge_weight > 0

    def to(self, device: torch.device | str) -> 'Head':
        def mv(t: torch.Tensor | None) -> torch.Tensor | None:
            return None if t is None else t.to(device)
        return Head(self.gamma, mv(self.whiten), mv(self.lda_coef), mv(self.lda_bias),
                    self.fusion_weight, self.temperature, self.lda_wide,
                    mv(self.lda_precision), mv(self.lda_means), self.lda_trace,
                    # float64 once here: the ridge sum runs in float64 (bank/discriminant.py)
                    None if self.ridge_coef is None else self.ridge_coef.to(device, torch.float64),
                    self.ridge_gamma, self.ridge_lambda, self.ridge_weight)

    def vote_space(self, z: torch.Tensor) -> torch.Tensor:
        """z: (B, d) transformed unit rows -> (B, d) rows the kernel vote compares."""
        if self.whiten is None:
            return z
        return torch.nn.functional.normalize(z @ self.whiten, dim=1, eps=1e-12)

    def lda_log_probs(self, z: torch.Tensor) -> torch.Tensor | None:
        """z: (B, d) -> (B, C) LDA log-posteriors, or None without an LDA part."""
        if self.lda_coef is None or self.fusion_weight == 0:
            return None
        return torch.log_softmax(z @ self.lda_coef.T + self.lda_bias, dim=1)


# ---- the gate of a two-section bank
# The gate of a two-section bank: how likely a query is a single-view scan.
#
# A sectioned bank (bank/store.py, `FeatureBank.views`) holds complete objects and single-view
# scans as two sections, each with its own transform and head. A whole CAD-like object and
# one side of it look different to the encoder, and one head fitted on both serves neither
# well. The gate is a closed-form two-class LDA (complete
# vs scan) on its own standardised, PCA-projected, L2-normalised features, with equal priors
# (the mix of complete objects and scans a robot will send is not the bank's mix):
#
#   p_scan (B,)  = softmax(gate_z @ coef^T + bias)[:, 1]
#   probability  = (1 - p_scan) * complete section + p_scan * scan section

# Chosen by grouped 5-fold CV on ModelNet40 train (every 3rd object, complete + 4 HPR scans;
# `experiments/gated_study.py --gate-grid`): all 1,620 dims (no PCA), shrinkage 0.001, equal
# priors: 95.9 % of complete objects and 99.8 % of scans routed right (256 dims: 94.5 / 99.7;
# 64 dims with the bank's 1:4 priors: 90.2 / 99.5). Without PCA the gate is two vectors.
GATE_DIMS: int | None = None
GATE_SHRINKAGE = 0.001


@dataclass
class Gate:
    """transform: raw encoder features -> (B, d) unit rows; coef (2, d); bias (2,)."""

    transform: FeatureTransform
    coef: torch.Tensor
    bias: torch.Tensor

    def to(self, device: torch.device | str) -> 'Gate':
        return Gate(self.transform.to(device), self.coef.to(device), self.bias.to(device))

    def scan_probability(self, feats: torch.Tensor) -> torch.Tensor:
        """feats: (B, D) raw encoder features -> (B,) probability of being a partial scan."""
        z = self.transform(feats)
        return torch.softmax(z @ self.coef.T + self.bias, dim=1)[:, 1]


# ---- the object test of taught classes
# Object-level test of taught classes: is a query nearer the taught object than a built one.
#
# A class taught from a few looks at ONE object ("my toolbox") is a tight cluster;
# the discriminant head sees only its class mean and the shared covariance, so scans of other
# objects of a similar category drift into it. The bank's
# build holds 8 single-view scans of every train object, so it knows how far scans of one
# object scatter around their own mean, and where every built object's mean lies.
#
# Object space: the r leading generalised eigenvectors W (r, D) of the between-object scatter
# against the within-object scatter S_w of the scan section's standardised rows (transform
# `standardized`), S_w shrunk by alpha towards its mean variance, so that W S_w W^T = I: a
# squared distance to an object's mean of n scans is then about r + r / n for a scan of that
# object. For a query q, z = W x(q), a taught class I (not in the build's provenance) with mean
# m_I of its n_I examples:
#
#   t_I = (|z - m_I|^2 - r / n_I) - min_j (|z - mu_j|^2 - r / n_j)     (j: built objects)
#
# and its log-probability moves by -(lam t_I + theta), then the rows are renormalised. A scan of
# the taught object has t_I well below 0 (boost); one of another object of a built class has
# t_I > 0 (damped). Built classes' log-probabilities never move, so with no taught class the
# probabilities are exactly the head's. r, alpha, lam and theta were chosen by nested CV on
# the train split only (experiments/object_test_study.py).
#
# The built objects' class names are kept: an object of a class no longer in the bank, or
# removed and re-taught, is not a "built object" any more and is left out of the minimum.

# Chosen by experiments/object_test_study.py (train split, 12 rounds, rule fixed before scoring).
OBJECT_RANK = 32
OBJECT_ALPHA = 0.01
OBJECT_LAM = 0.2
OBJECT_THETA = -2.0


@dataclass(frozen=True)
class ObjectTest:
    """The built objects in object space (module docstring).

    projection (r, D) float32; means (K, r) float32; labels (K,) int64 into class_names;
    counts (K,) int64 scans per object; lam, theta: the shift's slope and offset.
    """

    projection: torch.Tensor
    means: torch.Tensor
    labels: torch.Tensor
    counts: torch.Tensor
    class_names: tuple[str, ...]
    lam: float = OBJECT_LAM
    theta: float = OBJECT_THETA
    alpha: float = OBJECT_ALPHA

    @property
    def rank(self) -> int:
        return int(self.projection.shape[0])

    def describe(self) -> dict[str, Any]:
        return {'objects': len(self.means), 'rank': self.rank, 'alpha': self.alpha,
                'lam': self.lam, 'theta': self.theta}

    def shift(self, class_names: list[str], built: set[str], removed: set[str],
              views_transform: FeatureTransform, views_head: Head | None,
              examples: torch.Tensor) -> 'ObjectShift | None':
        """The shift of one bank version, or None when it has no taught class to move.

        class_names: the bank's classes; built: the classes its build made (provenance);
        removed: classes an enrollment removed since; views_transform, views_head: the scan
        section's transform and head, whose wide LDA keeps the taught classes' means of
        standardised rows; examples: (C,) examples per class in the scan section.
        """
        if views_head is None or not views_head.lda_wide:
            return None
        n = examples
        taught = [c for c, name in enumerate(class_names)
                  if name not in built and int(n[c]) > 0]
        if not taught:
            return None
        ok = np.array([self.class_names[int(c)] in class_names
                       and self.class_names[int(c)] not in removed for c in self.labels])
        if not ok.any():
            return None
        r = float(self.rank)
        keep = torch.from_numpy(ok)
        ids = torch.tensor(taught, dtype=torch.int64)
        w = self.projection.double()
        return ObjectShift(views_transform, w, self.means[keep].double(),
                           r / self.counts[keep].double(),
                           ids, views_head.lda_means[ids].double() @ w.T,
                           r / n[ids].double(), self.lam, self.theta)


@dataclass(frozen=True)
class ObjectShift:
    """One bank version's shift of its taught classes (`ObjectTest.shift`), float64.

    projection (r, D); built (K, r) and built_noise (K,): the kept built objects' means and
    r / n; taught (T,) class ids, taught_means (T, r), taught_noise (T,).
    """

    transform: FeatureTransform
    projection: torch.Tensor
    built: torch.Tensor
    built_noise: torch.Tensor
    taught: torch.Tensor
    taught_means: torch.Tensor
    taught_noise: torch.Tensor
    lam: float
    theta: float

    def __post_init__(self) -> None:
        # |m|^2 - r / n per mean, once per bank version: a lone query then costs two products.
        for name, means, noise in (('_built_c', self.built, self.built_noise),
                                   ('_taught_c', self.taught_means, self.taught_noise)):
            object.__setattr__(self, name, (means ** 2).sum(1) - noise)

    def gaps(self, features: torch.Tensor) -> torch.Tensor:
        """features: (B, D) raw encoder output -> t (B, T) (module docstring)."""
        z = self.transform.standardized(features.cpu()).double() @ self.projection.T
        # |z - m|^2 - r / n = |z|^2 - 2 z.m + (|m|^2 - r / n); |z|^2 cancels in the difference
        d_built = (self._built_c - 2 * z @ self.built.T).min(1, keepdim=True).values
        return (self._taught_c - 2 * z @ self.taught_means.T) - d_built

    def __call__(self, prob: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """Probabilities (B, C) float32, rows summing to 1 -> shifted and renormalised (B, C)."""
        logp = prob.double().log()
        logp[:, self.taught] -= self.lam * self.gaps(features) + self.theta
        return torch.softmax(logp, dim=1).float()
