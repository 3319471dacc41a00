"""Make clean dataset objects look a little more like segmented sensor data.

Dataset clouds sit centred in the unit sphere, complete and noise-free. ``Realism.apply``
optionally takes a simulated single-view scan (core/views.py, its default protocol: hidden
point removal, sensor noise; with the sensor frame, the scanned side faces the sensor), cuts a
partial view, drops points, places the object in a sensor frame (metres, yawed, a few metres
away) and adds Gaussian noise, in that order.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from point_gn_ros.bag.errors import BagError
from point_gn_ros.core.sampling import rotate_z
from point_gn_ros.core.views import simulate_view

# Placement ranges for --sensor-frame: object size (largest extent, m) and position (m).
SIZE_RANGE_M = (0.3, 2.0)
X_RANGE_M = (2.0, 8.0)
Y_RANGE_M = (-3.0, 3.0)
Z_RANGE_M = (0.0, 1.0)
# Never cut an object below this many points: the node rejects tiny objects (min_points 16).
MIN_KEEP = 32


@dataclass(frozen=True)
class Realism:
    """What to do to each object; the defaults change nothing."""

    sensor_frame: bool = False
    noise: float = 0.0      # Gaussian sigma, metres (dataset units without sensor_frame)
    dropout: float = 0.0    # probability of removing each point
    partial: float = 1.0    # share of points kept by a random plane cut
    max_yaw_deg: float = 180.0   # sensor_frame: yaw drawn from [-max, max] degrees
    single_view: bool = False    # a simulated single-view scan (core/views.py) first

    def __post_init__(self) -> None:
        if not (self.noise >= 0.0 and np.isfinite(self.noise)):
            raise BagError(f'--noise must be a finite sigma >= 0 (got {self.noise})')
        if not 0.0 <= self.dropout < 1.0:
            raise BagError(f'--dropout must be in [0, 1) (got {self.dropout})')
        if not 0.0 < self.partial <= 1.0:
            raise BagError(f'--partial must be in (0, 1] (got {self.partial})')
        if not 0.0 <= self.max_yaw_deg <= 180.0:
            raise BagError(f'--max-yaw must be in [0, 180] degrees (got {self.max_yaw_deg})')

    @property
    def active(self) -> bool:
        return (self.sensor_frame or self.single_view or self.noise > 0 or self.dropout > 0
                or self.partial < 1)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    def apply(self, xyz: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Xyz (N, 3) float32 -> (M, 3) float32, M <= N (M >= min(N, MIN_KEEP))."""
        out = np.asarray(xyz, dtype=np.float32)
        place = None
        if self.single_view:
            azimuth = None
            if self.sensor_frame:
                # Placement first, so the scanned side is the one facing the sensor (origin).
                place = Placement.draw(out, rng, self.max_yaw_deg)
                azimuth = float(np.arctan2(-place.offset[1], -place.offset[0]) - place.yaw)
            out = simulate_view(out, rng, azimuth=azimuth).points
        if self.partial < 1.0:
            out = partial_view(out, self.partial, rng)
        if self.dropout > 0.0:
            keep = rng.random(len(out)) >= self.dropout
            if keep.sum() < min(len(out), MIN_KEEP):
                keep[rng.permutation(len(out))[:MIN_KEEP]] = True
            out = out[keep]
        if self.sensor_frame:
            place = place or Placement.draw(out, rng, self.max_yaw_deg)
            out = place.apply(out)
        if self.noise > 0.0:
            out = out + rng.normal(0.0, self.noise, out.shape).astype(np.float32)
        return np.ascontiguousarray(out, dtype=np.float32)


def partial_view(xyz: np.ndarray, share: float, rng: np.random.Generator) -> np.ndarray:
    """Keep the `share` of points on one side of a plane with a random normal."""
    normal = rng.normal(size=3)
    normal /= np.linalg.norm(normal) + 1e-12
    depth = (xyz - xyz.mean(axis=0)) @ normal
    keep = max(min(len(xyz), MIN_KEEP), int(round(share * len(xyz))))
    return xyz[np.argsort(depth, kind='stable')[:keep]]


@dataclass(frozen=True)
class Placement:
    """Where an object goes in the sensor frame: scale, yaw (rad), then offset (m)."""

    centre: np.ndarray      # (3,) bounding-box centre of the object, dataset units
    scale: float
    yaw: float
    offset: np.ndarray      # (3,) metres, +x ahead of the sensor

    @classmethod
    def draw(cls, xyz: np.ndarray, rng: np.random.Generator,
             max_yaw_deg: float = 180.0) -> 'Placement':
        """A real size (m), a yaw about z and a position in front of the sensor, for xyz (N, 3).

        Dataset objects are upright (z up), so only yaw is realistic; Point-GN features are not
        rotation invariant, so yaw is what costs accuracy (compare a bag with max_yaw_deg=0).
        """
        centre = (xyz.max(axis=0) + xyz.min(axis=0)) / 2
        extent = float(np.ptp(xyz, axis=0).max()) or 1.0
        scale = rng.uniform(*SIZE_RANGE_M) / extent
        yaw = float(np.deg2rad(max_yaw_deg) * rng.uniform(-1.0, 1.0))
        offset = np.array([rng.uniform(*X_RANGE_M), rng.uniform(*Y_RANGE_M),
                           rng.uniform(*Z_RANGE_M)])
        return cls(centre, scale, yaw, offset)

    def apply(self, xyz: np.ndarray) -> np.ndarray:
        """Points (M, 3) in the object's frame -> (M, 3) float32 in the sensor frame."""
        return (rotate_z((xyz - self.centre) * self.scale, self.yaw) + self.offset).astype(
            np.float32)

