"""Object-level test of taught classes: is a query nearer the taught object than a built one.

A class taught from a few looks at ONE object (issue 12: "my toolbox") is a tight cluster;
the discriminant head sees only its class mean and the shared covariance, so scans of other
objects of a similar category drift into it (the "scan drop" of benchmarks/log). The bank's
build holds 8 single-view scans of every train object, so it knows how far scans of one
object scatter around their own mean, and where every built object's mean lies.

Object space: the r leading generalised eigenvectors W (r, D) of the between-object scatter
against the within-object scatter S_w of the scan section's standardised rows (transform
`standardized`), S_w shrunk by alpha towards its mean variance, so that W S_w W^T = I: a
squared distance to an object's mean of n scans is then about r + r / n for a scan of that
object. For a query q, z = W x(q), a taught class I (not in the build's provenance) with mean
m_I of its n_I examples:

  t_I = (|z - m_I|^2 - r / n_I) - min_j (|z - mu_j|^2 - r / n_j)     (j: built objects)

and its log-probability moves by -(lam t_I + theta), then the rows are renormalised. A scan of
the taught object has t_I well below 0 (boost); one of another object of a built class has
t_I > 0 (damped). Built classes' log-probabilities never move, so with no taught class the
probabilities are exactly the head's. r, alpha, lam and theta were chosen by nested CV on
the train split only (experiments/object_test_study.py, benchmarks/log).

The built objects' class names are kept: an object of a class no longer in the bank, or
removed and re-taught, is not a "built object" any more and is left out of the minimum.
"""

from __future__ import annotations

from dataclasses import dataclass
import json
from typing import Any, TYPE_CHECKING

import numpy as np
import torch

from point_gn_ros.bank.transform import FeatureTransform
from point_gn_ros.bank.validate import parse_meta

if TYPE_CHECKING:
    from point_gn_ros.bank.store import FeatureBank

# Chosen by experiments/object_test_study.py (train split, 12 rounds, rule fixed before scoring).
OBJECT_RANK = 32
OBJECT_ALPHA = 0.01
OBJECT_LAM = 0.2
OBJECT_THETA = -2.0
PREFIX = 'objects_'
ARRAYS = tuple(PREFIX + k for k in ('projection', 'means', 'labels', 'counts', 'meta'))
_ROWS = 8192      # rows a block while the scatter is summed (float64 blocks of ~100 MB)


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

    @classmethod
    def fit(cls, x: torch.Tensor, groups: np.ndarray, labels: np.ndarray,
            class_names: list[str], rank: int = OBJECT_RANK, alpha: float = OBJECT_ALPHA,
            lam: float = OBJECT_LAM, theta: float = OBJECT_THETA) -> 'ObjectTest':
        """x: (N, D) standardised scan rows; groups: (N,) source object; labels: (N,) class id.

        Every object needs >= 2 scans (its within scatter); an object's class is its first
        row's.
        """
        _, obj, counts = np.unique(np.asarray(groups), return_inverse=True, return_counts=True)
        if len(counts) < 2 or counts.min() < 2 or not 0 < rank <= x.shape[1]:
            raise ValueError(f'object test: needs >= 2 objects of >= 2 scans and 0 < rank <= '
                             f'{x.shape[1]}, got {len(counts)} objects, rank {rank}')
        k, d = len(counts), x.shape[1]
        idx = torch.from_numpy(obj.astype(np.int64))
        sums = torch.zeros(k, d, dtype=torch.float64)
        for rows in torch.arange(len(x)).split(_ROWS):
            sums.index_add_(0, idx[rows], x[rows].double())
        m = sums / torch.from_numpy(counts)[:, None].double()          # (K, D)
        sw = torch.zeros(d, d, dtype=torch.float64)
        for rows in torch.arange(len(x)).split(_ROWS):
            c = x[rows].double() - m[idx[rows]]
            sw += c.T @ c
        sw /= float(len(x) - k)
        mc = m - m.mean(0)
        sb = mc.T @ mc / k
        sw = (1 - alpha) * sw + alpha * torch.trace(sw) / d * torch.eye(d, dtype=sw.dtype)
        inv = torch.linalg.solve_triangular(torch.linalg.cholesky(sw),
                                            torch.eye(d, dtype=sw.dtype), upper=False)
        w = (torch.linalg.eigh(inv @ sb @ inv.T)[1][:, -rank:].T @ inv)    # (r, D)
        first = np.zeros(k, dtype=np.int64)
        first[obj[::-1]] = np.arange(len(obj))[::-1]                       # first row per object
        return cls(w.float(), (m @ w.T).float(),
                   torch.from_numpy(np.asarray(labels, dtype=np.int64)[first]),
                   torch.from_numpy(counts.astype(np.int64)), tuple(class_names),
                   float(lam), float(theta), float(alpha))

    def arrays(self) -> dict[str, np.ndarray]:
        """The file arrays (bank/store.py, format 6)."""
        meta = {'rank': self.rank, 'alpha': self.alpha, 'lam': self.lam, 'theta': self.theta,
                'class_names': list(self.class_names)}
        return {PREFIX + 'projection': self.projection.numpy().astype(np.float32),
                PREFIX + 'means': self.means.numpy().astype(np.float32),
                PREFIX + 'labels': self.labels.numpy().astype(np.int32),
                PREFIX + 'counts': self.counts.numpy().astype(np.int32),
                PREFIX + 'meta': np.frombuffer(json.dumps(meta, sort_keys=True).encode(),
                                               dtype=np.uint8)}

    @classmethod
    def from_arrays(cls, a: dict[str, np.ndarray], feature_dim: int) -> 'ObjectTest':
        """The test from a file's arrays; any inconsistency raises ValueError."""
        missing = [k for k in ARRAYS if k not in a]
        if missing:
            raise ValueError(f'object test: missing arrays {missing}')
        try:
            meta = parse_meta(np.asarray(a[PREFIX + 'meta']))     # size and depth capped
            names = tuple(str(n) for n in meta['class_names'])
            lam, theta, alpha = (float(meta[k]) for k in ('lam', 'theta', 'alpha'))
        except (ValueError, UnicodeDecodeError, KeyError, TypeError) as exc:
            raise ValueError(f'object test: bad metadata ({exc})') from None
        p, m = a[PREFIX + 'projection'], a[PREFIX + 'means']
        lab, cnt = a[PREFIX + 'labels'], a[PREFIX + 'counts']
        r = p.shape[0] if p.ndim == 2 else -1
        if (p.dtype != np.float32 or m.dtype != np.float32 or p.shape != (r, feature_dim)
                or r < 1 or m.ndim != 2 or m.shape[1] != r or len(m) < 2
                or lab.shape != (len(m),) or cnt.shape != (len(m),)
                or lab.dtype.kind not in 'iu' or cnt.dtype.kind not in 'iu'):
            raise ValueError(f'object test: arrays do not fit {feature_dim}-dim features: '
                             f'projection {p.dtype} {p.shape}, means {m.dtype} {m.shape}, '
                             f'labels {lab.shape}, counts {cnt.shape}')
        if not (np.isfinite(p).all() and np.isfinite(m).all() and np.isfinite([lam, theta])
                .all() and lab.min() >= 0 and lab.max() < len(names) and cnt.min() >= 1):
            raise ValueError('object test: non-finite values, labels out of range or counts < 1')
        return cls(torch.from_numpy(p), torch.from_numpy(m), torch.from_numpy(lab.astype(
            np.int64)), torch.from_numpy(cnt.astype(np.int64)), names, lam, theta, alpha)

    def describe(self) -> dict[str, Any]:
        return {'objects': len(self.means), 'rank': self.rank, 'alpha': self.alpha,
                'lam': self.lam, 'theta': self.theta}

    def shift_for(self, bank: 'FeatureBank') -> 'ObjectShift | None':
        """The shift of this bank version, or None when it has no taught class to move.

        Needs the scan section's wide LDA (its class means are the taught classes' means of
        standardised rows, kept by every enrollment).
        """
        views = bank.views
        if views is None or views.head is None or not views.head.lda_wide:
            return None
        built = set(bank.meta.get('provenance', {}).get('per_class', bank.class_names))
        from point_gn_ros.bank.refit import example_counts      # refit imports the store
        n = example_counts(views)
        taught = [c for c, name in enumerate(bank.class_names)
                  if name not in built and int(n[c]) > 0]
        if not taught:
            return None
        removed = {e.get('class') for e in bank.meta.get('enrollments', [])
                   if e.get('action') == 'remove'}
        ok = np.array([self.class_names[int(c)] in bank.class_names
                       and self.class_names[int(c)] not in removed for c in self.labels])
        if not ok.any():
            return None
        r = float(self.rank)
        keep = torch.from_numpy(ok)
        ids = torch.tensor(taught, dtype=torch.int64)
        w = self.projection.double()
        return ObjectShift(views.transform, w, self.means[keep].double(),
                           r / self.counts[keep].double(),
                           ids, views.head.lda_means[ids].double() @ w.T,
                           r / n[ids].double(), self.lam, self.theta)


@dataclass(frozen=True)
class ObjectShift:
    """One bank version's shift of its taught classes (`ObjectTest.shift_for`), float64.

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
