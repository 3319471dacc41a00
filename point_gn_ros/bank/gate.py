"""The gate of a two-section bank: how likely a query is a single-view scan.

A sectioned bank (bank/store.py, `FeatureBank.views`) holds complete objects and single-view
scans as two sections, each with its own transform and head. A whole CAD-like object and
one side of it look different to the encoder, and one head fitted on both serves neither
well (benchmarks/log, "Two-section bank"). The gate is a closed-form two-class LDA (complete
vs scan) on its own standardised, PCA-projected, L2-normalised features, with equal priors
(the mix of complete objects and scans a robot will send is not the bank's mix):

  p_scan (B,)  = softmax(gate_z @ coef^T + bias)[:, 1]
  probability  = (1 - p_scan) * complete section + p_scan * scan section
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from point_gn_ros.bank.head import CovarianceFit
from point_gn_ros.bank.transform import FeatureTransform

# Chosen by grouped 5-fold CV on ModelNet40 train (every 3rd object, complete + 4 HPR scans;
# `experiments/gated_study.py --gate-grid`): all 1,620 dims (no PCA), shrinkage 0.001, equal
# priors: 95.9 % of complete objects and 99.8 % of scans routed right (256 dims: 94.5 / 99.7;
# 64 dims with the bank's 1:4 priors: 90.2 / 99.5). Without PCA the gate is two vectors.
GATE_DIMS: int | None = None
GATE_SHRINKAGE = 0.001
GATE_ARRAYS = ('gate_tf_mean', 'gate_tf_scale', 'gate_tf_projection', 'gate_coef', 'gate_bias')


@dataclass
class Gate:
    """transform: raw encoder features -> (B, d) unit rows; coef (2, d); bias (2,)."""

    transform: FeatureTransform
    coef: torch.Tensor
    bias: torch.Tensor

    @classmethod
    def fit(cls, feats: torch.Tensor, is_scan: np.ndarray, dims: int | None = GATE_DIMS,
            shrinkage: float = GATE_SHRINKAGE) -> 'Gate':
        """feats: (N, D) raw encoder features; is_scan: (N,) bool (both kinds present)."""
        scan = torch.from_numpy(np.asarray(is_scan, dtype=np.int64))
        if int(scan.min()) == int(scan.max()):
            raise ValueError('the gate needs complete objects and scans')
        dims = None if dims is None or dims >= feats.shape[1] else dims
        tf = FeatureTransform.fit(feats, 'standardize', dims)
        fit = CovarianceFit.fit(tf(feats), scan, 2)
        fit.log_prior = torch.full((2,), float(np.log(0.5)), dtype=torch.float64)
        coef, bias = fit.lda(shrinkage)
        return cls(tf, coef, bias)

    def to(self, device: torch.device | str) -> 'Gate':
        return Gate(self.transform.to(device), self.coef.to(device), self.bias.to(device))

    def scan_probability(self, feats: torch.Tensor) -> torch.Tensor:
        """feats: (B, D) raw encoder features -> (B,) probability of being a partial scan."""
        z = self.transform(feats)
        return torch.softmax(z @ self.coef.T + self.bias, dim=1)[:, 1]

    def arrays(self) -> dict[str, np.ndarray]:
        """The bank-file arrays (float32) of this gate."""
        tf = self.transform
        out = {'gate_tf_mean': tf.mean, 'gate_tf_scale': tf.scale,
               'gate_tf_projection': tf.projection, 'gate_coef': self.coef,
               'gate_bias': self.bias}
        return {k: v.cpu().numpy().astype(np.float32) for k, v in out.items() if v is not None}

    @classmethod
    def from_arrays(cls, a: dict[str, np.ndarray], feature_dim: int) -> 'Gate':
        """Validate and build; raises ValueError naming the problem."""
        mean, scale = a.get('gate_tf_mean'), a.get('gate_tf_scale')
        proj, coef, bias = a.get('gate_tf_projection'), a.get('gate_coef'), a.get('gate_bias')
        if mean is None or scale is None or coef is None or bias is None:
            raise ValueError('gate arrays incomplete (gate_tf_mean, gate_tf_scale, gate_coef, '
                             'gate_bias)')
        d = feature_dim if proj is None else proj.shape[-1]
        shapes = {'gate_tf_mean': (mean, (feature_dim,)), 'gate_tf_scale': (scale, (feature_dim,)),
                  'gate_tf_projection': (proj, (feature_dim, d)), 'gate_coef': (coef, (2, d)),
                  'gate_bias': (bias, (2,))}
        for name, (arr, shape) in shapes.items():
            if arr is None:
                continue
            if arr.shape != shape or arr.dtype.kind != 'f' or not np.isfinite(arr).all():
                raise ValueError(f'{name} must be finite floats of shape {shape}, got '
                                 f'{arr.dtype} {arr.shape}')
        if not (scale > 0).all():
            raise ValueError('gate_tf_scale must be positive')

        def t(x: np.ndarray | None) -> torch.Tensor | None:
            return None if x is None else torch.from_numpy(x.astype(np.float32))
        return cls(FeatureTransform(t(mean), t(scale), t(proj)), t(coef), t(bias))
