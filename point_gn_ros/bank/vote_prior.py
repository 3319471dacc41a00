"""Class-size prior of the kernel vote for enrolled classes (issue 12, instance vs category).

The kernel vote sums exp(-gamma (1 - cos)) over EVERY entry of a class, so a class's entry count
acts as a prior: a new instance taught from 5 scans ("my bathtub") loses to its own category's
hundreds of scans, whose many moderately close entries outweigh the 5 close ones. An enrolled
class's count says how many looks were collected, not how often it is seen.

Opt-in, per bank section, recorded in its meta (set at enrollment, `RefitPolicy.vote_prior`):

  meta['vote_prior'] = {'beta': b, 'classes': [names]}

  vote'_c = vote_c * (n_ref / n_c)^b     for the listed classes c (n_c: their entries)
  vote'_c = vote_c                       for every other class
  n_ref   = mean entries per unlisted class of the section

b = 1 counts a listed class as if it had an average class's entries (its mean kernel times
n_ref); b = 0 is the plain vote. Classes not listed keep their votes exactly, so among the
built classes nothing changes. A bank without the key gets no bias (bit-identical answers).
Applied as a per-class bias on the log vote (bank/head.py `Head.evaluate_with`), so it works
for every search and never depends on the batch.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

META_KEY = 'vote_prior'


def vote_prior_meta(meta: dict[str, Any]) -> tuple[float, list[str]] | None:
    """(beta, listed class names) of a section's meta, or None when it has no vote prior."""
    vp = meta.get(META_KEY)
    if not vp:
        return None
    beta = float(vp.get('beta', 0.0))
    if not np.isfinite(beta) or beta < 0:
        raise ValueError(f'vote_prior beta must be finite and >= 0, got {beta}')
    return beta, [str(c) for c in vp.get('classes', [])]


def vote_log_bias(meta: dict[str, Any], class_names: list[str], labels: torch.Tensor
                  ) -> torch.Tensor | None:
    """Per-class log-vote bias (C,) float32 of a section (module docstring), or None.

    labels: (N,) int64 class ids of the entries that vote (the active bank). None when the
    section has no vote prior, beta is 0 or no listed class has entries.
    """
    vp = vote_prior_meta(meta)
    if vp is None or vp[0] == 0:
        return None
    beta, listed = vp
    counts = np.bincount(labels.cpu().numpy(), minlength=len(class_names)).astype(np.float64)
    scaled = np.zeros(len(class_names), dtype=bool)
    scaled[[class_names.index(c) for c in listed if c in class_names]] = True
    scaled &= counts > 0
    if not scaled.any():
        return None
    others = counts[~scaled & (counts > 0)]
    n_ref = float(others.mean()) if len(others) else float(counts[scaled].mean())
    bias = np.zeros(len(class_names))
    bias[scaled] = beta * np.log(n_ref / counts[scaled])
    return torch.from_numpy(bias.astype(np.float32))


def is_listed(meta: dict[str, Any], class_name: str) -> bool:
    """Whether `class_name` has the vote prior in this section's meta."""
    return class_name in (meta.get(META_KEY) or {}).get('classes', [])


def with_listed(meta: dict[str, Any], beta: float, class_name: str) -> dict[str, Any]:
    """Meta with `class_name` listed under a vote prior of `beta` (a copy; others kept)."""
    vp = dict(meta.get(META_KEY) or {})
    classes = [c for c in vp.get('classes', []) if c != class_name] + [class_name]
    return {**meta, META_KEY: {'beta': float(beta), 'classes': classes}}


def without(meta: dict[str, Any], class_name: str) -> dict[str, Any]:
    """Meta with `class_name` no longer listed (a copy); the key is dropped when empty."""
    vp = meta.get(META_KEY)
    if not vp or class_name not in vp.get('classes', []):
        return meta
    classes = [c for c in vp['classes'] if c != class_name]
    out = dict(meta)
    if classes:
        out[META_KEY] = {**vp, 'classes': classes}
    else:
        out.pop(META_KEY)
    return out
