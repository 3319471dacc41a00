"""Encoder configuration: every knob that changes the encoder's output."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
import math
from typing import Any
from collections.abc import Mapping

# Bump whenever the encoder's output changes for a given configuration, so that
# banks built by an older encoder are refused instead of silently mis-matched.
ENCODER_VERSION = 1
# More scales multiply the encoder's cost; two help (benchmarks/RESULTS.md).
MAX_EXTRA_SIGMAS = 3
# How clouds with fewer points than num_points are filled up (core/sampling.py).
UPSAMPLE_METHODS = ('repeat', 'midpoint')


@dataclass(frozen=True)
class EncoderConfig:
    """Point-GN encoder hyper-parameters (defaults: the paper's ModelNet40 set)."""

    num_points: int = 1024
    init_dim: int = 27
    stages: int = 4
    k: int = 120
    sigma: float = 0.4
    # Rotate each cloud about the vertical (z) axis into a canonical heading before
    # encoding: yaw-invariant classification for upright objects seen from any side.
    yaw_align: bool = False
    # Multi-scale features: the cloud is encoded again with each of these GPE sigmas (same
    # FPS centres and neighbours) and the features are concatenated, sigma's first.
    extra_sigmas: tuple[float, ...] = ()
    # How a cloud of fewer than num_points points is filled up (core/sampling.py): 'repeat'
    # (points repeated; the default, so a bank file without this field reads as built) or
    # 'midpoint' (new points between neighbours; +2-3 points on single-view scans by
    # grouped CV). Complete objects of num_points points or more are unaffected.
    upsample: str = 'repeat'

    def __post_init__(self) -> None:
        if self.num_points < 2 ** self.stages:
            raise ValueError(
                f'num_points={self.num_points} is too small for {self.stages} stages')
        if self.init_dim < 3 or self.init_dim % 3:
            raise ValueError(f'init_dim must be a positive multiple of 3, got {self.init_dim}')
        if self.stages < 1:
            raise ValueError(f'stages must be >= 1, got {self.stages}')
        if self.k < 1:
            raise ValueError(f'k must be >= 1, got {self.k}')
        if not (math.isfinite(self.sigma) and self.sigma > 0):
            raise ValueError(f'sigma must be a positive number, got {self.sigma}')
        # frozen: normalise a list (JSON) to a tuple of floats
        object.__setattr__(self, 'extra_sigmas', tuple(float(s) for s in self.extra_sigmas))
        if len(self.extra_sigmas) > MAX_EXTRA_SIGMAS or not all(
                math.isfinite(s) and s > 0 for s in self.extra_sigmas):
            raise ValueError(f'extra_sigmas must be at most {MAX_EXTRA_SIGMAS} positive '
                             f'numbers, got {list(self.extra_sigmas)}')
        if self.upsample not in UPSAMPLE_METHODS:
            raise ValueError(f'upsample must be one of {list(UPSAMPLE_METHODS)}, '
                             f'got {self.upsample!r}')

    @property
    def stage_dims(self) -> tuple[int, ...]:
        """Feature width after each stage (doubles every stage)."""
        return tuple(self.init_dim * 2 ** (i + 1) for i in range(self.stages))

    @property
    def stage_points(self) -> tuple[int, ...]:
        """Number of FPS centres at each stage (halves every stage)."""
        return tuple(self.num_points // 2 ** (i + 1) for i in range(self.stages))

    @property
    def sigmas(self) -> tuple[float, ...]:
        """Every GPE sigma the features are computed with, in feature order."""
        return (self.sigma, *self.extra_sigmas)

    @property
    def scale_dim(self) -> int:
        """Length of one sigma's global feature: max and mean of every stage."""
        return 2 * sum(self.stage_dims)

    @property
    def feature_dim(self) -> int:
        """Length of the global feature: scale_dim per sigma."""
        return self.scale_dim * len(self.sigmas)

    def require_single_scale(self) -> None:
        """Raise for a multi-scale configuration: a single-sigma encoder would fill half a row."""
        if self.extra_sigmas:
            raise ValueError('a multi-scale configuration needs one encoder per sigma: use '
                             'recognizer.make_encoder (core/multiscale.py)')

    def single(self, sigma: float) -> 'EncoderConfig':
        """The same configuration with one sigma and no extra scales."""
        return replace(self, sigma=sigma, extra_sigmas=())

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict; extra_sigmas and upsample only when not the default.

        So the banks (and feature caches) of configurations without them are unchanged.
        """
        out = asdict(self)
        if self.extra_sigmas:
            out['extra_sigmas'] = list(self.extra_sigmas)
        else:
            del out['extra_sigmas']
        if self.upsample == 'repeat':
            del out['upsample']
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> 'EncoderConfig':
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f'unknown encoder configuration keys: {sorted(unknown)}')
        return cls(**{k: data[k] for k in known if k in data})
