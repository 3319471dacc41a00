"""Bank checks beyond the file structure: everything a bank could hold that the node cannot run.

`check_bank_arrays(path, arrays)` runs before `FeatureBank` parses anything (store.py) and
raises one `BankError` naming the file and the reason, so a bad bank gives the node's one
FATAL line and `point_gn bank info` exit code 2, never a traceback or a silently useless bank:

* metadata: at most META_MAX_BYTES bytes and META_MAX_DEPTH levels of nesting, checked on
  the raw bytes before JSON parsing (a deeply nested document used to raise RecursionError);
* encoder configuration: every field's type and range (ENCODER_RANGES; k <= num_points);
* class names: a non-empty list of distinct, non-empty strings without line breaks (the
  ``~/class_names`` topic is one name per line);
* labels: every class has at least one entry;
* features: every row has a non-zero norm (store.py already refuses non-finite values);
* gamma and the unknown-score threshold: finite numbers.

What store.py checks itself (missing arrays, versions, shapes, label range, non-finite
values, tf_scale) is left to it: a condition it reports is passed over here.
"""

from __future__ import annotations

from collections.abc import Mapping
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from point_gn_ros.errors import BankError

# The shipped bank's metadata is ~2 KB; a megabyte leaves room for long provenance.
META_MAX_BYTES = 1_000_000
META_MAX_DEPTH = 32

# field -> (type, min, max). sigma: below 1e-3 the Gaussian embedding underflows to all-zero
# features (1e-30 gave NaN scores), above 1e3 it is flat; both are useless banks.
ENCODER_RANGES: dict[str, tuple[type, float, float]] = {
    'num_points': (int, 16, 65536),       # as the node parameter num_points
    'init_dim': (int, 3, 300),
    'stages': (int, 1, 8),
    'k': (int, 1, 65536),                 # and k <= num_points, below
    'sigma': (float, 1e-3, 1e3),
    'yaw_align': (bool, 0, 1),
}
MAX_CLASS_NAME = 256


def _json_depth(raw: bytes) -> int:
    """Deepest nesting of [ and { outside strings (linear scan, no recursion)."""
    depth = deepest = 0
    in_str = escaped = False
    for b in raw:
        if in_str:
            if escaped:
                escaped = False
            elif b == 0x5C:          # backslash
                escaped = True
            elif b == 0x22:          # closing quote
                in_str = False
        elif b == 0x22:
            in_str = True
        elif b in (0x5B, 0x7B):      # [ {
            depth += 1
            deepest = max(deepest, depth)
        elif b in (0x5D, 0x7D):
            depth -= 1
    return deepest


def parse_meta(raw: np.ndarray) -> Any:
    """Metadata bytes -> JSON value, size and depth checked first; None if not JSON.

    Raises ValueError with the reason when the bytes are over a limit.
    """
    if raw.size > META_MAX_BYTES:
        raise ValueError(f'metadata is {raw.size:,} bytes, more than the limit of '
                         f'{META_MAX_BYTES:,}')
    data = raw.tobytes()
    depth = _json_depth(data)
    if depth > META_MAX_DEPTH:
        raise ValueError(f'metadata nests {depth} levels deep, more than the limit of '
                         f'{META_MAX_DEPTH}')
    try:
        return json.loads(data.decode())
    except (ValueError, UnicodeDecodeError, RecursionError):
        return None                  # store.py reports invalid JSON in its own words


def _check_number(name: str, value: Any, kind: type, lo: float, hi: float) -> str | None:
    if kind is bool:
        return None if isinstance(value, bool) else f'{name} must be true or false, got {value!r}'
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return f'{name} must be a number, got {type(value).__name__} {value!r}'
    if kind is int and not isinstance(value, int):
        return f'{name} must be an integer, got {value!r}'
    if not (math.isfinite(value) and lo <= value <= hi):
        return f'{name}={value!r} is out of range [{lo:g}, {hi:g}]'
    return None


def check_encoder_config(cfg: Mapping[str, Any]) -> str | None:
    """The first problem of an encoder configuration dict, or None (unknown keys: None)."""
    if set(cfg) - set(ENCODER_RANGES) - {'extra_sigmas', 'upsample'}:
        return None                  # store.py: 'incomplete metadata (unknown keys)'
    for name, (kind, lo, hi) in ENCODER_RANGES.items():
        if name in cfg:
            problem = _check_number(name, cfg[name], kind, lo, hi)
            if problem:
                return f'encoder configuration: {problem}'
    from point_gn_ros.core.config import MAX_EXTRA_SIGMAS, UPSAMPLE_METHODS, EncoderConfig
    if cfg.get('upsample', 'repeat') not in UPSAMPLE_METHODS:
        return (f"encoder configuration: upsample must be one of {list(UPSAMPLE_METHODS)}, "
                f"got {cfg['upsample']!r}"[:300])
    extra = cfg.get('extra_sigmas', [])
    if not isinstance(extra, list) or len(extra) > MAX_EXTRA_SIGMAS:
        return (f'encoder configuration: extra_sigmas must be a list of at most '
                f'{MAX_EXTRA_SIGMAS} numbers, got {extra!r}'[:300])
    for s in extra:
        problem = _check_number('extra_sigmas', s, *ENCODER_RANGES['sigma'])
        if problem:
            return f'encoder configuration: {problem}'
    full = {**EncoderConfig().to_dict(), **cfg}
    if full['k'] > full['num_points']:
        return (f"encoder configuration: k={full['k']} neighbours is more than "
                f"num_points={full['num_points']}")
    return None


def class_name_problem(name: str) -> str | None:
    """Why one class name cannot be in a bank, or None: THE rule, at enrollment and at load.

    A name is a non-empty single line (no line feed or carriage return: ``~/class_names``
    is one name per line) of at most MAX_CLASS_NAME characters; anything else (unicode,
    '/', '..', escape codes) is a valid name.
    """
    if not name.strip() or '\n' in name or '\r' in name or len(name) > MAX_CLASS_NAME:
        shown = name if len(name) <= 60 else f'{name[:60]}... ({len(name):,} characters)'
        return (f'class names must be non-empty single lines of at most {MAX_CLASS_NAME} '
                f'characters, got {shown!r}')
    return None


def check_meta_writable(raw: np.ndarray) -> None:
    """Raise ValueError unless metadata bytes about to be saved pass the load checks.

    The limits `check_bank_arrays` applies at load (size, depth, class names), so that a
    save that succeeds always gives a file that loads.
    """
    try:
        meta = parse_meta(np.asarray(raw))
    except ValueError as exc:
        raise ValueError(f'not saved: {exc}') from None
    names = meta.get('class_names') if isinstance(meta, dict) else None
    problem = None if names is None else check_class_names(names)
    if problem:
        raise ValueError(f'not saved: {problem}')


def check_class_names(names: Any) -> str | None:
    """The first problem of a class_names value, or None."""
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        got = type(names).__name__ if not isinstance(names, list) else 'a list with ' + \
            ', '.join(sorted({type(n).__name__ for n in names if not isinstance(n, str)}))
        return f'class_names must be a list of strings, got {got}'
    if not names:
        return 'class_names is empty'
    for n in names:
        problem = class_name_problem(n)
        if problem:
            return problem
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        return f'class names are not unique: {", ".join(dupes[:5])}'
    return None


def check_bank_arrays(path: Path, arrays: Mapping[str, np.ndarray], section: str = '') -> None:
    """Raise BankError('<path>: <section><reason>') for the first problem found.

    See the module docstring; section names a bank's second section ('views section: ').
    """
    def fail(problem: str) -> BankError:
        return BankError(f'{path}: {section}{problem}')

    raw = arrays.get('meta')
    if raw is None:
        return
    try:
        meta = parse_meta(np.asarray(raw))
    except ValueError as exc:
        raise fail(str(exc)) from None
    if not isinstance(meta, dict):
        return
    cfg = meta.get('encoder_config')
    if isinstance(cfg, dict):
        problem = check_encoder_config(cfg)
        if problem:
            raise fail(problem)
    names = meta.get('class_names')
    if names is not None:
        problem = check_class_names(names)
        if problem:
            raise fail(problem)
    cal = meta.get('unknown_calibration')
    threshold = cal.get('threshold') if isinstance(cal, dict) else None
    for key, value in (('gamma', meta.get('gamma')), ('unknown threshold', threshold)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))
                                  or not math.isfinite(value)):
            raise fail(f'{key} must be a finite number, got {value!r}')
    labels, feats = arrays.get('labels'), arrays.get('features')
    if (isinstance(names, list) and labels is not None and labels.ndim == 1
            and labels.dtype.kind in 'iu' and labels.size and feats is not None
            and feats.ndim >= 1 and labels.shape[0] == feats.shape[0]
            and 0 <= labels.min() and labels.max() < len(names)):
        counts = np.bincount(labels.astype(np.int64), minlength=len(names))
        empty = [names[i] for i in np.flatnonzero(counts == 0)]
        if empty:
            raise fail(f'{len(empty)} class(es) have no entries: {", ".join(empty[:5])}'
                       + (' ...' if len(empty) > 5 else ''))
    if (feats is not None and feats.ndim == 2 and feats.dtype in (np.float16, np.float32, np.int8)
            and np.isfinite(feats).all()):
        norms = np.linalg.norm(feats.astype(np.float32), axis=1)
        zero = np.flatnonzero(~(norms > 0))
        if zero.size:
            raise fail(f'{zero.size} feature row(s) are all zero (e.g. entry {int(zero[0])})')
