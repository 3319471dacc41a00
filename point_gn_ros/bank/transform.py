"""Feature post-processing learnt from the bank only: standardise, project, L2-normalise."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch

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

        What a wide LDA reads (bank/head.py): every encoder dim, not only the PCA's.
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
