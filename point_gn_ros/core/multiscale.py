"""Multi-scale features: one encoder per GPE sigma, features concatenated.

The Gaussian positional encoding's sigma sets the spatial scale the features respond to;
features of two sigmas together classify better under the discriminant head than either
alone. Each scale is a complete single-sigma encoder, so
the oracle of every scale is the naive encoder of that sigma.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
import time

import torch

from point_gn_ros.core.config import EncoderConfig


class MultiScaleEncoder:
    """cfg.sigmas encoders run on the same prepared clouds, features concatenated.

    cfg: the multi-scale configuration (cfg.extra_sigmas non-empty); make: builds the
    encoder of one single-sigma configuration. encode: (B, N, 3) -> (B, cfg.feature_dim),
    sigma's block first, then each extra sigma's in order.
    """

    def __init__(self, cfg: EncoderConfig, make: Callable[[EncoderConfig], object]) -> None:
        self.cfg = cfg
        self.scales: Sequence = [make(cfg.single(s)) for s in cfg.sigmas]

    def __repr__(self) -> str:
        return f'MultiScaleEncoder(sigmas={list(self.cfg.sigmas)}, {self.scales[0]!r})'

    def warmup(self) -> float:
        """Warm every scale's encoder up: seconds taken."""
        t0 = time.perf_counter()
        for enc in self.scales:
            enc.warmup()
        return time.perf_counter() - t0

    @torch.no_grad()
    def encode(self, xyz: torch.Tensor) -> torch.Tensor:
        return torch.cat([enc.encode(xyz) for enc in self.scales], dim=1)

    def close(self) -> None:
        for enc in self.scales:
            getattr(enc, 'close', lambda: None)()
