"""The discriminant head's arrays in a bank file: validated and built (store.py calls it)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from point_gn_ros.bank.head import Head


def head_from_arrays(bad: Callable[[str], Exception], a: dict[str, np.ndarray],
                     meta: dict[str, Any], gamma: float, dim: int, num_classes: int,
                     entries: int, ridge_version: int) -> Head:
    """Validate and build the stored head (formats 2-4); `bad` makes a BankError.

    a: the section's arrays; dim: the vote space's width; entries: the section's rows.
    """
    hm = meta.get('head')
    if not isinstance(hm, dict):
        raise bad('metadata holds no head settings')
    try:
        weight, temp = float(hm['fusion_weight']), float(hm['temperature'])
    except (KeyError, TypeError, ValueError) as exc:
        raise bad(f'incomplete head metadata ({exc})') from None
    if not (np.isfinite(weight) and weight >= 0 and np.isfinite(temp) and temp > 0):
        raise bad(f'head fusion weight {weight} / temperature {temp} out of range')
    wide = bool(hm.get('lda_wide', False))
    in_dim = len(a['tf_mean'])
    tri = a.get('head_whiten_triu')
    if tri is not None:
        if 'head_whiten' in a or tri.shape != (dim * (dim + 1) // 2,) or tri.dtype.kind != 'f':
            raise bad(f'head_whiten_triu must be ({dim * (dim + 1) // 2},) floats and '
                      f'come without head_whiten, got {tri.dtype} {tri.shape}')
        full = np.zeros((dim, dim), np.float32)
        full[np.triu_indices(dim)] = tri
        a = {**a, 'head_whiten': np.triu(full, 1).T + full}
    shapes = {'head_whiten': (dim, dim),
              'head_lda_coef': (num_classes, in_dim if wide else dim),
              'head_lda_bias': (num_classes,), 'head_ridge_coef': (entries, num_classes)}
    if wide:
        shapes.update(head_lda_precision=(in_dim * (in_dim + 1) // 2,),
                      head_lda_means=(num_classes, in_dim))
    got = {}
    for name, shape in shapes.items():
        arr = a.get(name)
        if arr is None:
            continue
        if arr.shape != shape or arr.dtype.kind != 'f' or not np.isfinite(arr).all():
            raise bad(f'{name} must be finite floats of shape {shape}, got {arr.dtype} '
                      f'{arr.shape}')
        got[name] = torch.from_numpy(arr.astype(np.float32))
    if ('head_lda_coef' in got) != ('head_lda_bias' in got):
        raise bad('head_lda_coef and head_lda_bias come together')
    if weight > 0 and 'head_lda_coef' not in got:
        raise bad('head fusion weight > 0 but no LDA arrays')
    precision = None
    if wide:
        if not {'head_lda_coef', 'head_lda_precision', 'head_lda_means'} <= set(got):
            raise bad('a wide-LDA head needs head_lda_coef, _bias, _precision and _means')
        precision = torch.zeros(in_dim, in_dim)
        rows, cols = np.triu_indices(in_dim)
        precision[rows, cols] = got['head_lda_precision']
        precision[cols, rows] = got['head_lda_precision']
    trace = float(hm.get('lda_trace') or 0.0)
    if wide and not (np.isfinite(trace) and 0 <= trace <= 1e6):
        raise bad(f'head lda_trace {trace} out of range')
    ridge = hm.get('ridge') if isinstance(hm.get('ridge'), dict) else {}
    try:
        r_gamma, r_lambda, r_weight = (float(ridge.get(k, 0.0)) for k in
                                       ('gamma', 'lambda', 'weight'))
    except (TypeError, ValueError) as exc:
        raise bad(f'head ridge settings unreadable ({exc})') from None
    if ('head_ridge_coef' in got) != (r_weight > 0):
        raise bad('head_ridge_coef and a ridge weight > 0 come together')
    if r_weight > 0 and not all(np.isfinite(v) and v > 0 for v in (r_gamma, r_lambda,
                                                                    r_weight)):
        raise bad(f'head ridge gamma {r_gamma} / lambda {r_lambda} / weight {r_weight} out '
                  'of range')
    if r_weight > 0 and meta.get('format_version', 0) < ridge_version:
        raise bad(f'a kernel ridge head in a format {meta.get("format_version")} bank')
    return Head(gamma, got.get('head_whiten'), got.get('head_lda_coef'),
                got.get('head_lda_bias'), weight, temp, wide, precision,
                got.get('head_lda_means'), trace, got.get('head_ridge_coef'), r_gamma,
                r_lambda, r_weight)
