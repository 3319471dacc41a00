"""A bank's large fitted matrices as float16 with a power-of-two scale (format 5).

The PCA projection (D, d), the vote's whitening (d, d) and a wide LDA's precision (D, D)
are most of a bank file's bytes beside its rows. With meta `matrix_dtype` 'float16' they
are stored as float16 values m / 2^e, e per matrix in meta `matrix_scale_log2` (a wide
LDA's precision reaches 2e5, past float16's 65504; the scale puts the largest entry in
[2^14, 2^15)). Multiplying by a power of two is exact, so a file holds exactly the values
the bank computed with, provided the fit rounded them first (`round_matrix`, called where
the matrices are fitted: builder.py, refit.py); `encode` refuses values that were not.
Entries 2^24 below a matrix's largest become float16 subnormals (absolute error
< 2^-10 ulp of the largest): nothing a product with unit rows can see.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import torch

if TYPE_CHECKING:
    from point_gn_ros.bank.head import Head
    from point_gn_ros.bank.transform import FeatureTransform

MatrixDtype = Literal['float32', 'float16']
# The file arrays stored this way (head_whiten_triu: format 4's triangle of head_whiten).
HALF_MATRICES = ('tf_projection', 'head_whiten', 'head_whiten_triu', 'head_lda_precision')
# float16's largest power of two below its maximum (65504) is 2^15.
_TOP = 14
MAX_SCALE_LOG2 = 60


def _exponent(a: np.ndarray) -> int:
    top = float(np.abs(a).max()) if a.size else 0.0
    return 0 if top == 0 else int(np.frexp(top)[1]) - 1 - _TOP


def round_matrix(t: torch.Tensor | None) -> torch.Tensor | None:
    """Any float tensor -> float32 with the values a float16 file holds (None: None)."""
    if t is None:
        return None
    a = t.detach().cpu().numpy().astype(np.float32)
    e = _exponent(a)
    back = np.ldexp(np.ldexp(a, -e).astype(np.float16).astype(np.float32), e)
    return torch.from_numpy(back).to(t.device)


def rounded_transform(tf: 'FeatureTransform', dtype: MatrixDtype) -> 'FeatureTransform':
    """The transform with its PCA projection as a `dtype` file stores it."""
    return tf if dtype == 'float32' else replace(tf, projection=round_matrix(tf.projection))


def rounded_head(head: 'Head | None', dtype: MatrixDtype) -> 'Head | None':
    """The head's whitening and wide-LDA precision as a `dtype` file stores them."""
    if head is None or dtype == 'float32':
        return head
    return replace(head, whiten=round_matrix(head.whiten),
                   lda_precision=round_matrix(head.lda_precision))


def encode(a: np.ndarray) -> tuple[np.ndarray, int]:
    """float32 array of `round_matrix` values -> (float16 array, scale exponent e).

    Raises ValueError when a value does not survive (a matrix fitted without rounding).
    """
    # Rounding may carry the largest entry up to 2^15 x 2^e: then e is one below _exponent.
    top = _exponent(a)
    for e in (top, top - 1):
        half = np.ldexp(a, -e).astype(np.float16)
        if np.array_equal(np.ldexp(half.astype(np.float32), e), a):
            return half, e
    raise ValueError('a matrix to be stored as float16 was not rounded when fitted '
                     '(bank/half.py round_matrix)')


def decode(a: np.ndarray, e: int) -> np.ndarray:
    """A stored float16 matrix and its exponent -> float32 values (exact)."""
    return np.ldexp(a.astype(np.float32), e)


def decode_arrays(bad: Callable[[str], Exception], a: dict[str, np.ndarray],
                  meta: dict[str, Any], half: bool) -> dict[str, np.ndarray]:
    """A section's file arrays with its float16 matrices as float32; `bad` makes a BankError.

    half: the file is format 5. Elsewhere a float16 matrix is refused (no scale to apply).
    """
    scales = meta.get('matrix_scale_log2', {}) if half else {}
    if not isinstance(scales, dict) or (half and meta.get('matrix_dtype') != 'float16'):
        raise bad('format 5 needs matrix_dtype float16 and a matrix_scale_log2 object')
    out = dict(a)
    for name in HALF_MATRICES:
        arr = a.get(name)
        if arr is None:
            continue
        e = scales.get(name)
        if half != (arr.dtype == np.float16) or (half and (
                not isinstance(e, int) or isinstance(e, bool) or abs(e) > MAX_SCALE_LOG2)):
            raise bad(f'{name} must be float16 with an integer scale exponent in format 5 '
                      f'and float32 before it, got {arr.dtype}, exponent {e!r}')
        if half:
            out[name] = decode(arr, e)
    return out
