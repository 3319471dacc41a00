"""Naive Point-GN encoder: the obviously-correct test oracle for every fast path.

One cloud at a time, plain torch, no fusion and no tricks. Fast paths must agree
with it within 1e-4 (relative to the feature's largest magnitude) and give
identical neighbourhoods, so every choice below (distance formula, tie-breaking,
FPS start) is part of the encoder's definition.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from point_gn_ros.core.config import EncoderConfig


def gpe_centres(dim: int, device: torch.device | str = 'cpu') -> torch.Tensor:
    """Gaussian centres of one axis block: (ceil(dim / 3),) float32 in (-1, 1)."""
    n = math.ceil(dim / 3)
    return torch.linspace(-1.0, 1.0, n + 2, dtype=torch.float32, device=device)[1:-1]


def gpe(xyz: torch.Tensor, dim: int, sigma: float) -> torch.Tensor:
    """Gaussian positional encoding.

    xyz: (..., 3) float32 -> (..., dim) float32. Per axis a block of
    exp(-0.5 ((c - v) / sigma)^2) over the centres c; blocks x, y, z concatenated.
    """
    c = gpe_centres(dim, xyz.device)
    blocks = [torch.exp(-0.5 * ((c - xyz[..., a:a + 1]) / sigma) ** 2) for a in range(3)]
    return torch.cat(blocks, dim=-1)[..., :dim]


def sq_dist(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Squared distances, summed x, y, z in that order: a (M, 3), b (N, 3) -> (M, N)."""
    d = a[:, None, :] - b[None, :, :]
    return d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]


def fps_start(xyz: torch.Tensor) -> int:
    """First FPS point: the one farthest from the centroid (lowest index on ties).

    Chosen by geometry so that the result does not depend on point order.
    """
    centroid = xyz.mean(dim=0, keepdim=True)
    return int(torch.argmax(sq_dist(xyz, centroid)[:, 0]))


def fps(xyz: torch.Tensor, m: int) -> torch.Tensor:
    """Farthest point sampling: xyz (N, 3) float32 -> (m,) int64 indices, m <= N.

    Ties go to the lowest index (torch.argmax returns the first maximum).
    """
    idx = torch.empty(m, dtype=torch.int64)
    cur = fps_start(xyz)
    min_d = torch.full((xyz.shape[0],), float('inf'), dtype=xyz.dtype, device=xyz.device)
    for i in range(m):
        idx[i] = cur
        min_d = torch.minimum(min_d, sq_dist(xyz, xyz[cur:cur + 1])[:, 0])
        cur = int(torch.argmax(min_d))
    return idx.to(xyz.device)


def knn(xyz: torch.Tensor, centres: torch.Tensor, k: int) -> torch.Tensor:
    """K nearest points of each centre: xyz (N, 3), centres (S, 3) -> (S, k) int64.

    Ordered by distance, ties by lowest index (stable sort).
    """
    d = sq_dist(centres, xyz)
    return torch.sort(d, dim=1, stable=True).indices[:, :k]


def _std(x: torch.Tensor) -> torch.Tensor:
    # Unbiased std over every element of one cloud's neighbourhoods; per cloud,
    # never pooled across a batch, so a cloud's feature ignores its batch-mates.
    return x.std()


def encode_cloud(xyz: torch.Tensor, cfg: EncoderConfig) -> torch.Tensor:
    """Encode one normalised cloud: xyz (num_points, 3) float32 -> (feature_dim,) float32."""
    feat = gpe(xyz, cfg.init_dim, cfg.sigma)
    out = []
    for s in cfg.stage_points:
        centre_idx = fps(xyz, s)
        centre_xyz, centre_feat = xyz[centre_idx], feat[centre_idx]
        nb = knn(xyz, centre_xyz, min(cfg.k, xyz.shape[0]))           # (S, K)
        dxyz = xyz[nb] - centre_xyz[:, None, :]                        # (S, K, 3)
        dxyz = dxyz / (_std(dxyz) + 1e-5)
        dfeat = feat[nb] - centre_feat[:, None, :]                     # (S, K, D)
        dfeat = dfeat / (_std(dfeat) + 1e-5)
        f = torch.cat([dfeat, centre_feat[:, None, :].expand_as(dfeat)], dim=-1)  # (S, K, 2D)
        pe = gpe(dxyz, f.shape[-1], cfg.sigma)
        w = (f + pe) * pe
        feat = F.gelu(w.max(dim=1).values + w.mean(dim=1))            # (S, 2D)
        xyz = centre_xyz
        out += [feat.max(dim=0).values, feat.mean(dim=0)]
    return torch.cat(out)


class NaiveEncoder:
    """Reference encoder over a batch, one cloud at a time.

    Input clouds must already be resampled to cfg.num_points and normalised
    (see point_gn_ros.core.sampling).
    """

    def __init__(self, cfg: EncoderConfig = EncoderConfig(), device: str = 'cpu') -> None:
        cfg.require_single_scale()
        self.cfg = cfg
        self.device = torch.device(device)

    @torch.no_grad()
    def encode(self, xyz: torch.Tensor) -> torch.Tensor:
        """xyz: (B, num_points, 3) float32 -> (B, feature_dim) float32."""
        xyz = xyz.to(self.device, torch.float32)
        return torch.stack([encode_cloud(c, self.cfg) for c in xyz])
