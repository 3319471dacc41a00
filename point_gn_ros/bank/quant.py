"""Stored row values of a bank file: float16/32 casts, int8 and packed int4 rows (store.py)."""

from __future__ import annotations

import numpy as np
import torch

STORED_DTYPES = ('float16', 'float32', 'int8', 'int4')
_INTEGER_DTYPES = {'int8': 127, 'int4': 7}    # stored dtype -> largest stored magnitude


def to_stored(features: torch.Tensor, dtype: str) -> np.ndarray:
    """Unit rows (N, d) -> the values a file stores (N, d) in `dtype`.

    float16/float32: cast. int8 / int4: every row scaled so its largest coordinate is +-127 /
    +-7 (load re-normalises rows, so no scale is kept; int4 is packed, pack_int4); stored
    values cast to float32 and stored again are unchanged.
    """
    q = quantized(features, dtype)
    return pack_int4(q) if dtype == 'int4' else q


def quantized(features: torch.Tensor, dtype: str) -> np.ndarray:
    """to_stored's values before int4 packing: (N, d) in dtype (int8 values for int4)."""
    if dtype not in STORED_DTYPES:
        raise ValueError(f'dtype must be one of {", ".join(STORED_DTYPES)}, got {dtype}')
    x = features.detach().cpu().float().numpy()
    if dtype not in _INTEGER_DTYPES:
        return x.astype(dtype)
    top = _INTEGER_DTYPES[dtype]
    peak = np.abs(x).max(axis=1, keepdims=True)
    scale = np.divide(np.float32(top), peak, out=np.zeros_like(peak), where=peak > 0)
    return np.clip(np.rint(x * scale), -top, top).astype(np.int8)


def pack_int4(q: np.ndarray) -> np.ndarray:
    """(N, d) int8 in [-7, 7] -> (N, ceil(d / 2)) uint8: q + 8 per 4 bits, first value high."""
    u = (q.astype(np.int16) + 8).astype(np.uint8)
    if u.shape[1] % 2:
        u = np.concatenate([u, np.full((len(u), 1), 8, np.uint8)], axis=1)  # a zero
    return (u[:, 0::2] << 4) | u[:, 1::2]


def unpack_int4(packed: np.ndarray, dim: int) -> np.ndarray:
    """pack_int4's inverse: (N, ceil(dim / 2)) uint8 -> (N, dim) int8 in [-8, 7]."""
    out = np.empty((len(packed), 2 * packed.shape[1]), np.int8)
    out[:, 0::2] = (packed >> 4).astype(np.int8) - 8
    out[:, 1::2] = (packed & 15).astype(np.int8) - 8
    return out[:, :dim]

