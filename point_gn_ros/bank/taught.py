"""Taught classes as prototypes, and metric size as evidence (core/size.py).

A class taught from a few sensor scans is answered best by its class mean: the head's
discriminant was fitted on thousands of CAD rows and leans to what it was built on. And a
robot's clouds are in metres: a 15 cm carton is not a wardrobe. This layer moves the head's
probabilities (B, C) after the head, in two ways:

  taught block  classes with taught examples (meta 'taught', written by every enrollment)
                take a share of the probability and divide it among themselves by
                softmax(KAPPA cos(z, m_c) + W plaus_c): m_c the mean of the class's taught
                rows z (the main section's transformed unit rows), cos the cosine to it.
                A metric query (sizes given): the share is p_T + g (1 - p_T), p_T the head's
                total on the block, g = logistic(LEAD_SLOPE (fit_T - fit_B + LEAD_MARGIN)),
                fit_T and fit_B its fit (below) to its nearest taught and nearest built class;
                the block is divided by g of the prototypes' division and 1 - g of the head's.
                Sensor scans of a taught object resemble its taught scans more than a CAD
                class's mean, and the head, fitted on CAD rows, would hand them to a built
                class (62.4 % of the lidar-proxy answers before the lead; docs/SIZE.md).
                A unit-sphere query (no sizes): the share stays p_T, and the prototypes'
                division is mixed with the head's by g = logistic(GATE_SLOPE (best cosine to
                a taught mean - GATE_COS)) (built-class queries keep the head's division;
                the ModelNet40 figures after teaching stay as they were);
  size          every class whose size is known gets W plaus_c on its log-probability:
                taught classes: -1/2 sum_d (s_d - mu_d)^2 / var_d over the measured log sizes
                of its taught examples (var shrunk with PRIOR_COUNT pseudo examples towards
                the taught classes' pooled variance, `pooled_variance`); built classes: the
                real-world size prior (data/size_prior.json),
                0 inside the relaxed range, -1/2 (distance / RANGE_TAU)^2 outside it.

Queries without metric size (sizes None: unit-sphere data, the node's metric_size off) skip
the size terms; a bank with no taught class and no size then leaves the head's output
exactly as it is (ModelNet40 figures unchanged).

Fit: max_c (cos(z, m_c) + W / KAPPA inside_c) over every class with a mean (built classes:
the mean of their bank rows, size from the prior), inside_c = min(plaus_c + region_c / 2, 0):
the size counts against a class only outside its size region (below), so a taught class's
Gaussian and a built class's range weigh alike. For the unknown rule (fit below the
threshold), a metric query in a bank whose taught classes have sizes is judged against the
taught classes only: a built class's CAD mean fits sensor scans of anything about as well
(AUROC 0.61 on the lidar proxy, against 0.92 for the taught fit). There the whole size
distance counts, plaus_c + region_c / 2 in place of inside_c (a size near the class's mean
counts for it): among Gaussians no clipping is needed, and the clipped form ties every size
inside the region. Fit AUROC with a class left out (`point_gn fewshot`, 5 draws): 0.658 on
the tabletop set and 0.932 on the lidar proxy, against 0.633 and 0.905 clipped, with the
same queries rejected at the default threshold. Knobs chosen by CV on the tabletop set and
the ModelNet40 train split (experiments/size_knob_study.py, experiments/lead_study.py,
docs/SIZE.md).

Size region (for the same unknown rule): misfit = the answer's size distance over its
class's region; above 1 the query's size lies outside the region. The distance is -2 plaus_c
(taught: the squared standardised log-size distance; built: the squared prior-range gap in
RANGE_TAU units); the region is distance <= REGION_CHI2 (the 95 % quantile of chi-square
with SIZE_DIM degrees of freedom), widened for the taught classes to the REGION_QUANTILE of
their examples' leave-one-out distances, pooled over the taught classes, where those need
more (scans that vary more in size than the prior says). Radius and pooling chosen by
experiments/open_set_study.py (docs/SIZE.md).
"""

from __future__ import annotations

from dataclasses import dataclass
import json
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import torch

from point_gn_ros.core.size import SIZE_DIM

KAPPA = 10.0           # shape: logit per unit cosine to a taught class mean
W_SIZE = 0.5           # size: weight of the plausibility on the log-probability
GATE_COS = 0.75        # the prototypes re-divide the taught block for queries whose best
GATE_SLOPE = 10.0      # cosine to a taught mean passes GATE_COS (logistic gate of this slope)
LEAD_SLOPE = 10.0      # a metric query's taught-block share: logistic of this slope in the
LEAD_MARGIN = 0.2      # fit lead of its nearest taught class over its nearest built one, plus this
PRIOR_VAR = 0.02       # taught classes' log-size variance prior (sd ~14 %) ...
PRIOR_COUNT = 3.0      # ... worth this many examples
RANGE_LOW, RANGE_HIGH = 0.5, 1.25   # prior ranges relaxed: a partial view shows less
RANGE_TAU = float(np.log(1.5))      # log-size distance outside a range per unit penalty
# The node's default unknown rule: fit below this is unknown (docs/SIZE.md: chosen on the
# tabletop set's leave-one-class-out folds, checked on blobs, scenes and garbage).
DEFAULT_FIT_THRESHOLD = 0.0
FIT_OFF = -10.0        # a fit threshold at or below this: no fit rule
MAX_PLAUS = 50.0       # plausibility floor (-MAX_PLAUS): one absurd size does not swamp all
KEY = 'taught'
REGION_CHI2 = 12.59    # chi-square (SIZE_DIM = 6 dof) 95 % quantile: the size region's radius^2
REGION_QUANTILE = 0.95  # of the taught examples' leave-one-out distances (the widening)
KEPT_SIZES = 20        # taught examples' sizes kept per class (the newest) for the widening
_PRIOR_FILE = Path(__file__).resolve().parents[1] / 'data' / 'size_prior.json'
_PRIOR_DIMS = ('height', 'length', 'width')


@lru_cache(maxsize=1)
def size_prior() -> dict[str, np.ndarray]:
    """Class name -> (3, 2) log ranges [height, length, width] x [low, high] (relaxed)."""
    raw = json.loads(_PRIOR_FILE.read_text())['classes']
    out = {}
    for name, r in raw.items():
        lo = np.log([r[d][0] * RANGE_LOW for d in _PRIOR_DIMS])
        hi = np.log([r[d][1] * RANGE_HIGH for d in _PRIOR_DIMS])
        out[name] = np.stack([lo, hi], axis=1)
    return out


def fit_rule(threshold: float) -> float | None:
    """A node / CLI fit threshold -> the classifier's (None: off, at or below FIT_OFF)."""
    return None if threshold <= FIT_OFF else float(threshold)


def plausible_scale(xyz: np.ndarray, class_name: str) -> float:
    """Factor that gives a unit-sphere object of `class_name` a typical real size.

    xyz: (N, 3) z up. The geometric mean of (middle of the prior's height range / height)
    and (middle of its length range / horizontal extent); 1.0 for a class without a prior.
    """
    raw = json.loads(_PRIOR_FILE.read_text())['classes'].get(class_name)
    p = np.asarray(xyz, dtype=np.float64)
    if raw is None or len(p) < 2:
        return 1.0
    h = max(float(np.ptp(p[:, 2])), 1e-6)
    ln = max(float(np.ptp(p[:, 0])), float(np.ptp(p[:, 1])), 1e-6)
    want_h, want_l = np.sqrt(np.prod(raw['height'])), np.sqrt(np.prod(raw['length']))
    return float(np.sqrt(want_h / h * want_l / ln))


# ------------------------------------------------------------------ bank metadata (JSON)


def add_taught(meta: dict[str, Any], class_name: str, z: torch.Tensor,
               sizes: np.ndarray | None) -> dict[str, Any]:
    """Meta with `class_name`'s taught record updated by new examples (a new dict).

    z: (M, d) the examples' transformed unit rows (canonical frames); sizes: (M, SIZE_DIM)
    log sizes (core/size.py) or None when the examples carry no metric size.
    Record: n (examples), mean (d,) of z, and with sizes: sn, smean (SIZE_DIM,), sm2 (sum of
    squared deviations), merged by Chan's update, and sizes: the newest KEPT_SIZES examples'
    log sizes (for the size region's widening).
    """
    taught = dict(meta.get(KEY, {}))
    rec = dict(taught.get(class_name, {}))
    zs = z.double().numpy()
    n0, m = int(rec.get('n', 0)), len(zs)
    mean0 = np.asarray(rec.get('mean', np.zeros(zs.shape[1])), dtype=np.float64)
    if mean0.shape != (zs.shape[1],):     # rows of another transform: start again
        n0, mean0 = 0, np.zeros(zs.shape[1])
    rec['n'] = n0 + m
    rec['mean'] = _rounded((n0 * mean0 + zs.sum(0)) / (n0 + m))
    if sizes is not None and len(sizes):
        s = np.asarray(sizes, dtype=np.float64).reshape(-1, SIZE_DIM)
        sn0 = int(rec.get('sn', 0))
        smean0 = np.asarray(rec.get('smean', np.zeros(SIZE_DIM)), dtype=np.float64)
        sm20 = np.asarray(rec.get('sm2', np.zeros(SIZE_DIM)), dtype=np.float64)
        k, mu = len(s), s.mean(0)
        delta = mu - smean0
        tot = sn0 + k
        rec['sn'] = tot
        rec['smean'] = _rounded(smean0 + delta * k / tot)
        rec['sm2'] = _rounded(sm20 + ((s - mu) ** 2).sum(0) + delta ** 2 * sn0 * k / tot)
        kept = [list(r) for r in rec.get('sizes', [])] + [_rounded(r, 4) for r in s]
        rec['sizes'] = kept[-KEPT_SIZES:]
    taught[class_name] = rec
    return {**meta, KEY: taught}


def drop_taught(meta: dict[str, Any], class_name: str) -> dict[str, Any]:
    """Meta without `class_name`'s taught record (a new dict)."""
    if class_name not in meta.get(KEY, {}):
        return meta
    return {**meta, KEY: {c: r for c, r in meta[KEY].items() if c != class_name}}


def _rounded(v: np.ndarray, digits: int = 6) -> list[float]:
    return [round(float(x), digits) for x in v]


# ------------------------------------------------------------------ the layer


@dataclass(frozen=True)
class TaughtLayer:
    """One bank version's prototypes and size models (module docstring).

    taught (T,) class ids with a mean; means (T, d) unit; built_ids (K,) and built_means
    (K, d): the other classes' bank-row means; size_mu, size_var (C, SIZE_DIM) for classes
    with measured sizes (nan elsewhere); ranges (C, 3, 2) log prior ranges (nan: none);
    region (C,) the size region's squared radius per class (module docstring).
    """

    taught: np.ndarray
    means: np.ndarray
    built_ids: np.ndarray
    built_means: np.ndarray
    size_mu: np.ndarray
    size_var: np.ndarray
    ranges: np.ndarray
    region: np.ndarray
    kappa: float = KAPPA
    w_size: float = W_SIZE
    gate_cos: float = GATE_COS
    lead_slope: float = LEAD_SLOPE
    lead_margin: float = LEAD_MARGIN

    @classmethod
    def build(cls, meta: dict[str, Any], class_names: list[str], z_rows: torch.Tensor,
              labels: torch.Tensor) -> 'TaughtLayer':
        """From the main section's metadata and its bank rows z (N, d), labels (N,)."""
        c = len(class_names)
        d = z_rows.shape[1]
        rec = {k: v for k, v in meta.get(KEY, {}).items()
               if k in class_names and isinstance(v, dict)}
        taught, means, loo = [], [], []
        mu, var = np.full((c, SIZE_DIM), np.nan), np.full((c, SIZE_DIM), np.nan)
        for name, r in rec.items():
            i = class_names.index(name)
            m = np.asarray(r.get('mean', []), dtype=np.float64)
            if m.shape == (d,) and np.isfinite(m).all() and np.linalg.norm(m) > 0:
                taught.append(i)
                means.append(m / np.linalg.norm(m))
        sized = {class_names.index(k): r for k, r in rec.items() if int(r.get('sn', 0)) > 0}
        target = pooled_variance([(int(r['sn']), np.asarray(r['sm2'], dtype=np.float64))
                                  for r in sized.values()])
        for i, r in sized.items():
            mu[i] = np.asarray(r['smean'], dtype=np.float64)
            var[i] = (np.asarray(r['sm2'], dtype=np.float64) + PRIOR_COUNT * target) \
                / (int(r['sn']) - 1 + PRIOR_COUNT)
            loo.extend(loo_distances(np.asarray(r.get('sizes', []), dtype=np.float64), target))
        taught_ids = np.asarray(taught, dtype=np.int64)
        built = np.setdiff1d(np.arange(c), taught_ids)
        lab = labels.numpy()
        zr = z_rows.double().numpy()
        bm = np.zeros((len(built), d))
        for k, i in enumerate(built):
            rows = zr[lab == i]
            if len(rows):
                v = rows.mean(0)
                bm[k] = v / max(np.linalg.norm(v), 1e-12)
        prior = size_prior()
        ranges = np.full((c, 3, 2), np.nan)
        for i, name in enumerate(class_names):
            if name in prior:
                ranges[i] = prior[name]
        # taught classes with sizes: the chi-square radius, widened to what their examples need
        wide = max(REGION_CHI2, float(np.quantile(loo, REGION_QUANTILE))) if loo \
            else REGION_CHI2
        region = np.where(np.isfinite(mu[:, 0]), wide, REGION_CHI2)
        return cls(taught_ids, np.asarray(means).reshape(-1, d), built.astype(np.int64), bm,
                   mu, var, ranges, region)

    @property
    def active(self) -> bool:
        """Whether the layer can move anything without sizes (taught classes exist)."""
        return len(self.taught) > 0

    @property
    def sized_taught(self) -> bool:
        """Whether a taught class has measured sizes."""
        return bool(len(self.taught)) and bool(np.isfinite(self.size_mu[self.taught, 0]).any())

    def plausibility(self, sizes: np.ndarray) -> np.ndarray:
        """sizes: (B, SIZE_DIM) log sizes -> (B, C) plausibility <= 0 (0: no size known)."""
        sizes = np.asarray(sizes, dtype=np.float64)
        out = np.zeros((len(sizes), len(self.size_mu)))
        known = np.isfinite(self.size_mu[:, 0])
        if known.any():
            d2 = (sizes[:, None, :] - self.size_mu[None, known]) ** 2 / self.size_var[None, known]
            out[:, known] = -0.5 * d2.sum(-1)
        ranged = np.isfinite(self.ranges[:, 0, 0]) & ~known
        if ranged.any():
            x = sizes[:, None, :3]
            r = self.ranges[None, ranged]
            gap = np.maximum(r[..., 0] - x, 0.0) + np.maximum(x - r[..., 1], 0.0)
            out[:, ranged] = -0.5 * ((gap / RANGE_TAU) ** 2).sum(-1)
        return np.maximum(out, -MAX_PLAUS)

    def apply(self, prob: torch.Tensor, z: torch.Tensor, sizes: np.ndarray | None
              ) -> tuple[torch.Tensor, np.ndarray, np.ndarray | None]:
        """Prob (B, C) rows summing to 1, z (B, d) unit rows, sizes (B, SIZE_DIM) or None.

        -> moved probabilities (B, C) float32, fit (B,) float64, misfit (B,) float64: the
        answer's size distance over its class's region (> 1: outside; None without sizes;
        module docstring).
        """
        logp = prob.double().clamp_min(1e-300).log().numpy()
        zq = z.double().numpy()
        plaus = None if sizes is None else self.plausibility(sizes)
        cos = self._cosines(zq)
        fits = self._fits(cos, plaus)
        built = self.built_ids
        if plaus is not None:
            logp[:, built] += self.w_size * plaus[:, built]
        if len(self.taught):
            cos_t = cos[:, self.taught]                                 # (B, T)
            s = self.kappa * cos_t
            if plaus is not None:
                s = s + self.w_size * plaus[:, self.taught]
            log_t = _logsumexp(logp[:, self.taught])
            log_b = _logsumexp(logp[:, built]) if len(built) else np.full(len(zq), -np.inf)
            p_t = np.exp(log_t - np.logaddexp(log_t, log_b))
            if plaus is None:
                # a unit-sphere query: the head's share of the taught block, re-divided by the
                # prototypes as its best cosine to a taught mean passes gate_cos (a built-class
                # query keeps the head's division)
                gate = 1.0 / (1.0 + np.exp(-GATE_SLOPE * (cos_t.max(1) - self.gate_cos)))
                mass = p_t
            else:
                # a metric query: the block's share raised towards 1, and re-divided by the
                # prototypes, as the query is more like its nearest taught class than its
                # nearest built one (shape and size, `fit`)
                lead = fits[:, self.taught].max(1) - _best(fits[:, built])
                gate = 1.0 / (1.0 + np.exp(-np.clip(self.lead_slope * (lead + self.lead_margin),
                                                     -50.0, 50.0)))
                mass = gate + (1.0 - gate) * p_t
            share = gate[:, None] * np.exp(s - _logsumexp(s)[:, None]) \
                + (1.0 - gate[:, None]) * np.exp(logp[:, self.taught] - log_t[:, None])
            logp[:, self.taught] = np.log(np.maximum(mass, 1e-300))[:, None] \
                + np.log(np.maximum(share, 1e-300))
            if len(built):
                logp[:, built] += (np.log(np.maximum(1.0 - mass, 1e-300)) - log_b)[:, None]
        out = torch.softmax(torch.from_numpy(logp), dim=1).float()
        misfit = None
        if plaus is not None:
            top = out.argmax(1).numpy()
            misfit = -2.0 * plaus[np.arange(len(top)), top] / self.region[top]
        # a metric query in a bank with sized taught classes is judged against the taught
        # classes (the built classes' CAD means fit sensor scans of anything about as well),
        # by the whole size distance where the size is known: all are Gaussians, none needs
        # the region's equal footing with a range
        if plaus is not None and self.sized_taught:
            t = self.taught
            whole = np.where(np.isfinite(self.size_mu[t, 0]), plaus[:, t] + 0.5 * self.region[t],
                             0.0)
            judged = cos[:, t] + self.w_size / self.kappa * whole
        else:
            judged = fits
        return out, _best(judged, empty=0.0), misfit

    def fit(self, zq: np.ndarray, plaus: np.ndarray | None) -> np.ndarray:
        """(B, d) unit rows, plausibility (B, C) or None -> (B,) best fit over every class."""
        return _best(self.fits(zq, plaus), empty=0.0)

    def fits(self, zq: np.ndarray, plaus: np.ndarray | None) -> np.ndarray:
        """(B, d) unit rows, plausibility (B, C) or None -> (B, C) fit per class.

        Shape and size (module docstring); -inf for a class without a mean.
        """
        return self._fits(self._cosines(zq), plaus)

    def _cosines(self, zq: np.ndarray) -> np.ndarray:
        """(B, d) unit rows -> (B, C) cosine to each class's mean (-inf: no mean)."""
        cos = np.full((len(zq), len(self.size_mu)), -np.inf)
        if len(self.taught):
            cos[:, self.taught] = zq @ self.means.T
        if len(self.built_ids):
            cos[:, self.built_ids] = zq @ self.built_means.T
        return cos

    def _fits(self, cos: np.ndarray, plaus: np.ndarray | None) -> np.ndarray:
        if plaus is None:
            return cos
        # inside a class's size region the size says nothing against it
        inside = np.minimum(plaus + 0.5 * self.region[None, :], 0.0)
        return cos + self.w_size / self.kappa * inside


def pooled_variance(classes: list[tuple[int, np.ndarray]]) -> np.ndarray:
    """The taught classes' pooled within-class log-size variance, (SIZE_DIM,).

    classes: (examples, sum of squared deviations (SIZE_DIM,)) per class with sizes. Shrunk
    towards PRIOR_VAR with PRIOR_COUNT pseudo examples; PRIOR_VAR for none. Each class's
    variance is shrunk towards it: 5 examples say little about their own spread, the other
    taught classes, seen by the same sensor, say more than a fixed prior.
    """
    m2 = sum((s for _, s in classes), np.zeros(SIZE_DIM))
    dof = sum(n - 1 for n, _ in classes)
    return (m2 + PRIOR_COUNT * PRIOR_VAR) / (dof + PRIOR_COUNT)


def loo_distances(sizes: np.ndarray, target: np.ndarray | float = PRIOR_VAR) -> list[float]:
    """Leave-one-out distances of one class's taught examples.

    sizes: (n, SIZE_DIM) log sizes; target: the variance the class's is shrunk towards
    (`pooled_variance`) -> each one's distance (-2 plausibility) to the class's size model
    fitted without it (none for fewer than 2 examples).
    """
    n = len(sizes)
    if n < 2 or sizes.ndim != 2 or sizes.shape[1] != SIZE_DIM:
        return []
    out = []
    for i in range(n):
        rest = np.delete(sizes, i, axis=0)
        mu = rest.mean(0)
        var = (((rest - mu) ** 2).sum(0) + PRIOR_COUNT * target) / (n - 2 + PRIOR_COUNT)
        out.append(float(min(((sizes[i] - mu) ** 2 / var).sum(), 2 * MAX_PLAUS)))
    return out


def _best(fits: np.ndarray, empty: float = -np.inf) -> np.ndarray:
    """(B, K) -> (B,) row maxima; `empty` for K = 0."""
    return fits.max(1) if fits.shape[1] else np.full(len(fits), empty)


def _logsumexp(a: np.ndarray) -> np.ndarray:
    m = a.max(1)
    m = np.where(np.isfinite(m), m, 0.0)
    return m + np.log(np.exp(a - m[:, None]).sum(1))
