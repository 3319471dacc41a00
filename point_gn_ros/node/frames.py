"""Which way is up: rotating object clouds into the z-up convention the banks are built in.

Banks are built from z-up objects (ModelNet40: x forward, y left, z up, as REP 103's body
frames). Depth cameras publish in optical frames (REP 103: x right, y down, z forward); an
object seen there lies on its side for the encoder and is mislabelled with confident
scores. The node therefore turns every object into z-up before resampling, by a fixed
convention per frame name (`up_axis` 'auto': frames ending in `_optical_frame` have -y up)
or by an explicit `up_axis`.

`UpConvention` is the one place that decides; a tf2 lookup (rotation of the input frame
into a gravity-aligned frame at the message stamp) can replace it later with the same
call signature: frame_id -> rotation or None. Only rotations, no translation: the node
reports positions in the input frame, the rotation only feeds the classifier.
"""

from __future__ import annotations

import numpy as np

OPTICAL_SUFFIX = '_optical_frame'
UP_AXES = ('auto', 'z', '-z', 'y', '-y', 'x', '-x')

# R such that xyz_up = xyz @ R.T, a proper rotation (det +1) with R @ up = +z. '-y' is
# REP 103's optical -> body turn: x_body = z_opt, y_body = -x_opt, z_body = -y_opt.
_ROTATIONS: dict[str, np.ndarray] = {
    'z': np.eye(3),
    '-z': np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1]]),
    'y': np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]]),
    '-y': np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]]),
    'x': np.array([[0, 0, -1], [0, 1, 0], [1, 0, 0]]),
    '-x': np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]]),
}


def up_rotation(up_axis: str) -> np.ndarray | None:
    """(3, 3) float32 rotation taking `up_axis` of the input frame to +z; None for 'z'."""
    if up_axis not in _ROTATIONS:
        raise ValueError(f'up_axis {up_axis!r} must be one of {", ".join(UP_AXES)}')
    return None if up_axis == 'z' else _ROTATIONS[up_axis].astype(np.float32)


def to_z_up(xyz: np.ndarray, rotation: np.ndarray | None) -> np.ndarray:
    """xyz: (N, 3) float32 in the input frame -> (N, 3) float32 z-up (same array if None)."""
    if rotation is None:
        return xyz
    return xyz @ rotation.T


class UpConvention:
    """frame_id -> rotation into z-up (None = already z-up), by name convention.

    up_axis 'auto': '-y' for frames named `*_optical_frame` (REP 103), else 'z'; any other
    value of UP_AXES applies to every frame.
    """

    def __init__(self, up_axis: str = 'auto') -> None:
        if up_axis not in UP_AXES:
            raise ValueError(f'up_axis {up_axis!r} must be one of {", ".join(UP_AXES)}')
        self.up_axis = up_axis
        self._fixed = None if up_axis == 'auto' else up_rotation(up_axis)
        self._optical = up_rotation('-y')

    def __call__(self, frame_id: str) -> np.ndarray | None:
        if self.up_axis != 'auto':
            return self._fixed
        return self._optical if frame_id.endswith(OPTICAL_SUFFIX) else None
