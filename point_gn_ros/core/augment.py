"""Enrollment augmentation: an example stored in every frame its canonical yaw can land in.

`canonical_yaw` (core/sampling.py) puts the principal x-y axis on +x and fixes the signs of x
and y independently by third moments. On a complete object that frame is stable; on a single
partial scan it is not: two scans of one object a few tens of degrees apart can land in frames
that differ by an axis swap (the two x-y spreads are close) and/or a sign flip of x or y (the
third moment of a half-seen object is small), i.e. by an element of the dihedral group D4 of
the square (4 rotations by 90 degrees, 4 mirrors). A query stays one encoding; an enrolled
example is encoded in each frame of a subgroup, so whichever frame the query lands in, one of
the stored variants is in it too.

Groups (k = variants per example, the identity first):
  none    1  the canonical frame only
  mirror  2  + x -> -x
  rot4    4  rotations by 0, 90, 180, 270 degrees
  d4      8  rotations and mirrors: every frame canonical_yaw can confuse
"""

from __future__ import annotations

from typing import Literal

import numpy as np

Augment = Literal['none', 'mirror', 'rot4', 'd4']

# 2x2 maps of (x, y), rows of the matrix M in xy' = xy @ M.T.
_E = ((1, 0), (0, 1))
_ROT = (_E, ((0, -1), (1, 0)), ((-1, 0), (0, -1)), ((0, 1), (-1, 0)))
_MIRRORS = (((-1, 0), (0, 1)), ((1, 0), (0, -1)), ((0, 1), (1, 0)), ((0, -1), (-1, 0)))
AUGMENTS: dict[str, tuple[tuple[tuple[int, int], tuple[int, int]], ...]] = {
    'none': (_E,),
    'mirror': (_E, _MIRRORS[0]),
    'rot4': _ROT,
    'd4': _ROT + _MIRRORS,
}


def check_augment(augment: str) -> str:
    """Validate an augmentation name -> it (ValueError names the choices)."""
    if augment not in AUGMENTS:
        raise ValueError(f'augment must be one of {", ".join(AUGMENTS)}, got {augment!r}')
    return augment


def variants_per_example(augment: str) -> int:
    """How many bank entries one example becomes under `augment`."""
    return len(AUGMENTS[check_augment(augment)])


def yaw_variants(xyz: np.ndarray, augment: str) -> np.ndarray:
    """Prepared clouds (B, N, 3) float32 -> (B * k, N, 3) float32, example-major.

    Row b * k + j is cloud b under the group's j-th map of (x, y) (j = 0: unchanged); z and
    the point order are kept. The maps are exact in float32 (sign changes and swaps only).
    """
    mats = AUGMENTS[check_augment(augment)]
    if xyz.ndim != 3 or xyz.shape[2] != 3:
        raise ValueError(f'expected clouds of shape (B, N, 3), got {xyz.shape}')
    if len(mats) == 1:
        return xyz
    m = np.asarray(mats, dtype=np.float32)                    # (k, 2, 2)
    out = np.repeat(xyz[:, None], len(mats), axis=1)          # (B, k, N, 3)
    out[..., :2] = np.einsum('bnc,kdc->bknd', xyz[..., :2], m)
    return np.ascontiguousarray(out.reshape(-1, *xyz.shape[1:]))
