"""Feature bank file: encoded reference objects, their labels and how they were made.

Format version 2 (one `.npz`, read with allow_pickle=False, never unpickled):
  features      (N, d) float16 or float32  bank features in the vote's space: transformed,
                                           L2-normalised and, when the head whitens,
                                           whitened and re-normalised (`Head.vote_space`)
  labels        (N,) int32                 class index of each entry
  tf_mean       (D,) float32               feature transform fitted on the bank
  tf_scale      (D,) float32
  tf_projection (D, d) float32             optional PCA projection
  head_whiten   (d, d) float32             optional: whitening of the vote (bank/model.py)
  head_lda_coef (C, d) float32             optional: LDA logits = z coef^T + bias
  head_lda_bias (C,) float32
  head_lda_precision (D(D+1)/2,) float32   with meta head.lda_wide: the wide LDA (bank/model.py)
  head_lda_means     (C, D) float32        reads the standardised D-dim rows; coef is (C, D);
                                           precision Sigma_a^-1 as its upper triangle, row-major
  meta          (M,) uint8                 UTF-8 JSON: versions, encoder config, class
                                           names, gamma, head (fusion weight, temperature,
                                           shrinkage, CV figures), calibration, provenance

Format version 4 (only a bank whose head has a kernel ridge term, bank/discriminant.py) adds
  head_ridge_coef (N, C) float32           the ridge coefficients, one row per entry
  head_whiten_triu (d(d+1)/2,) float32     instead of head_whiten when that is exactly
                                           symmetric: its upper triangle, row-major
and meta head.ridge (gamma, lambda, weight, CV table).

Format version 5 (a section whose meta `matrix_dtype` is 'float16', bank/store.py) stores
tf_projection, head_whiten / head_whiten_triu and head_lda_precision as float16 values
m / 2^e, e per array in meta `matrix_scale_log2`; otherwise as version 4.

Format version 3 adds, optionally (written as version 2 when it has neither):
  features      may be int8: each row scaled so its largest coordinate is +-127 (rows are
                L2-normalised at load, so no scale is stored), or int4 (meta stored_dtype
                'int4'): each row scaled to +-7, stored + 8 as two 4-bit values per byte,
                (N, ceil(d / 2)) uint8, the first value in the high half
  views_*       a second section, the single-view scans (`views_features`, `views_labels`,
                `views_tf_*`, `views_head_*`, `views_meta`: the same arrays as above, with
                the same class names and encoder), and
  gate_*        the gate that mixes the two sections (bank/model.py)

Format version 6 (a two-section bank with an object-level test of taught classes,
bank/model.py) adds `objects_projection`, `objects_means`, `objects_labels`,
`objects_counts` and `objects_meta` (JSON); otherwise as version 5 (or 3-4).

Version-1 banks (kernel vote only, no head) still load, as the plain vote, with a
log line saying so; `point_gn bank build` rebuilds them with the head.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
import copy
from dataclasses import asdict, dataclass, field, replace
import json
import logging
import math
import os
from pathlib import Path
import threading
from typing import Any, Literal
import zipfile

import numpy as np
import torch

from point_gn_ros.bank.discriminant import fit_ridge
from point_gn_ros.bank.model import FeatureTransform, Gate, Head, ObjectTest
from point_gn_ros.core.config import ENCODER_VERSION, EncoderConfig
from point_gn_ros.errors import BankError

# ---- quant
# Stored row values of a bank file: float16/32 casts, int8 and packed int4 rows (store.py).

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


# ---- half
# A bank's large fitted matrices as float16 with a power-of-two scale (format 5).
#
# The PCA projection (D, d), the vote's whitening (d, d) and a wide LDA's precision (D, D)
# are most of a bank file's bytes beside its rows. With meta `matrix_dtype` 'float16' they
# are stored as float16 values m / 2^e, e per matrix in meta `matrix_scale_log2` (a wide
# LDA's precision reaches 2e5, past float16's 65504; the scale puts the largest entry in
# [2^14, 2^15)). Multiplying by a power of two is exact, so a file holds exactly the values
# the bank computed with, provided the fit rounded them first (`round_matrix`, called where
# the matrices are fitted: builder.py, refit.py); `encode` refuses values that were not.
# Entries 2^24 below a matrix's largest become float16 subnormals (absolute error
# < 2^-10 ulp of the largest): nothing a product with unit rows can see.

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
                     '(bank/store.py round_matrix)')


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


# ---- npz_read
# Read a bank `.npz` with bounds: nothing is allocated or decompressed before it is checked.
#
# `read_npz_bounded(path)` looks at the zip directory first: every member must be a `.npy`
# whose uncompressed size (as the directory states it) fits, and all of them together at most
# `BANK_MAX_BYTES`. Then each member's `.npy` header is read (a few hundred bytes
# decompressed): a plain (no object) dtype whose shape times item size is exactly the member's
# size. Only then is the array read, and zipfile never decompresses a member past the size
# its directory entry states. So a header claiming 10^12 x 256 floats, or a zip bomb of a
# gigabyte of zeros, is refused in milliseconds with one line (`BankError`), never a
# MemoryError, a traceback or gigabytes of RSS. Never unpickles (allow_pickle=False).

BANK_MAX_BYTES = 1 << 30
# Members of one bank file at most (the largest bank format has ~40 arrays).
BANK_MAX_MEMBERS = 256



def read_npz_bounded(path: str | os.PathLike[str], max_bytes: int = BANK_MAX_BYTES
                     ) -> dict[str, np.ndarray]:
    """Every member of an .npz, name -> array; BankError('<path>: <reason>') otherwise."""
    path = Path(path)

    def fail(problem: str) -> BankError:
        return BankError(f'{path}: {problem}')

    try:
        with zipfile.ZipFile(path) as zf:
            infos = zf.infolist()
            if len(infos) > BANK_MAX_MEMBERS:
                raise fail(f'{len(infos)} arrays, more than the limit of {BANK_MAX_MEMBERS}')
            total = 0
            for info in infos:
                if not info.filename.endswith('.npy') or info.is_dir():
                    raise fail(f'member {info.filename[:80]!r} is not an .npy array')
                total += info.file_size
            if total > max_bytes:
                raise fail(f'arrays hold {total:,} bytes uncompressed, more than the limit of '
                           f'{max_bytes:,} (read nothing)')
            arrays = {}
            for info in infos:
                name = info.filename[:-len('.npy')]
                if name in arrays:
                    raise fail(f'array {name[:80]!r} is stored twice')
                with zf.open(info) as f:
                    _check_header(f, info, fail)
                with zf.open(info) as f:
                    arrays[name] = np.lib.format.read_array(f, allow_pickle=False)
            return arrays
    except BankError:
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError, EOFError,
            NotImplementedError, RuntimeError) as exc:
        raise fail(f'unreadable or corrupt bank file ({type(exc).__name__}: '
                   f'{str(exc)[:200]})') from None


def _check_header(f, info: zipfile.ZipInfo, fail) -> None:  # noqa: ANN001
    """The member's .npy header: a plain dtype whose shape fills the member exactly."""
    name = info.filename
    try:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(f)
        elif version in ((2, 0), (3, 0)):
            shape, _, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise ValueError(f'npy format version {version}')
    except (ValueError, EOFError, SyntaxError) as exc:
        raise fail(f'{name}: not a valid .npy header ({str(exc)[:200]})') from None
    if dtype.hasobject:
        raise fail(f'{name}: holds Python objects (never unpickled)')
    count = 1
    for n in shape:
        count *= int(n)
    data = count * dtype.itemsize
    header = f.tell()
    if header + data != info.file_size:
        raise fail(f'{name}: header says {shape} {dtype} ({data:,} bytes), the member holds '
                   f'{max(0, info.file_size - header):,}')


# ---- validate
# Bank checks beyond the file structure: everything a bank could hold that the node cannot run.
#
# `check_bank_arrays(path, arrays)` runs before `FeatureBank` parses anything (store.py) and
# raises one `BankError` naming the file and the reason, so a bad bank gives the node's one
# FATAL line and `point_gn bank info` exit code 2, never a traceback or a silently useless bank:
#
# * metadata: at most META_MAX_BYTES bytes and META_MAX_DEPTH levels of nesting, checked on
#   the raw bytes before JSON parsing (a deeply nested document cannot raise RecursionError);
# * encoder configuration: every field's type and range (ENCODER_RANGES; k <= num_points);
# * class names: a non-empty list of distinct, non-empty strings without line breaks (the
#   ``~/class_names`` topic is one name per line);
# * labels: every class has at least one entry;
# * features: every row has a non-zero norm (store.py already refuses non-finite values);
# * gamma and the unknown-score threshold: finite numbers.
#
# What store.py checks itself (missing arrays, versions, shapes, label range, non-finite
# values, tf_scale) is left to it: a condition it reports is passed over here.

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


# ---- rows
# Bank rows that grow by appending without copying the whole bank each version.
#
# An enrollment's bank is the previous version's rows plus a few new ones. Concatenating
# copies every row (a scan section of 39,372 x 320 float32: 50 MB, ~45 ms of CPU per
# enrollment, more on a loaded machine). Instead the rows live in a buffer with spare room
# after them: version k's features are a view of the buffer's first n_k rows, and the next
# version writes its new rows after them and views n_k + m rows.
#
# Copy-on-write still holds: a row once visible to a published version is never written
# again. Only the version whose rows end where the buffer's claimed rows end may append in
# place (claimed under a lock); any other (an older version appended to again, a branch) gets
# a fresh buffer, as a copy would.

_SPARE_SHARE = 0.125
_MIN_SPARE = 256


class _Buffer:
    """(capacity, d) rows of which the first `claimed` are in use by some version."""

    def __init__(self, n: int, tail: tuple[int, ...], dtype: torch.dtype) -> None:
        spare = max(_MIN_SPARE, int(n * _SPARE_SHARE))
        self.data = torch.empty((n + spare, *tail), dtype=dtype)
        self.claimed = n
        self.lock = threading.Lock()

    @classmethod
    def of(cls, rows: torch.Tensor, extra: torch.Tensor) -> '_Buffer':
        """A buffer holding rows then extra (same trailing shape and dtype)."""
        n0 = rows.shape[0]
        buf = cls(n0 + extra.shape[0], tuple(rows.shape[1:]), rows.dtype)
        buf.data[:n0] = rows
        buf.data[n0:buf.claimed] = extra
        return buf


def append_rows(rows: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
    """torch.cat([rows, new]) (rows (N, d), new (M, d), CPU): in place when it is safe.

    The result is a view of a shared buffer (module docstring); `rows` and every earlier
    version keep exactly the values they had.
    """
    new = new.to(dtype=rows.dtype)
    if rows.device.type != 'cpu' or new.shape[1:] != rows.shape[1:]:
        return torch.cat([rows, new])
    buf: _Buffer | None = getattr(rows, '_pgn_rows', None)
    n, m = rows.shape[0], new.shape[0]
    if buf is not None and rows.data_ptr() == buf.data.data_ptr() and rows.is_contiguous():
        with buf.lock:
            ok = buf.claimed == n and n + m <= buf.data.shape[0]
            if ok:
                buf.claimed = n + m
        if ok:
            buf.data[n:n + m] = new
            return _view(buf, n + m)
    return _view(_Buffer.of(rows, new), n + m)


def with_room(rows: torch.Tensor) -> torch.Tensor:
    """The same values (N, d) in a buffer with spare room, so the first append is in place.

    For a bank about to take enrollments (bank/live.py): the one copy happens here, once
    (none for rows `FeatureBank.load` made, which already have room).
    """
    if rows.device.type != 'cpu' or getattr(rows, '_pgn_rows', None) is not None:
        return rows
    return _view(_Buffer.of(rows, rows[:0]), rows.shape[0])


def empty_rows(n: int, d: int) -> torch.Tensor:
    """(n, d) float32, uninitialised, in a buffer with spare room: fill it before use.

    What `FeatureBank.load` fills, so a bank about to take enrollments needs no second copy
    of its rows (`with_room` returns them as they are).
    """
    return _view(_Buffer(n, (d,), torch.float32), n)


def _view(buf: _Buffer, n: int) -> torch.Tensor:
    out = buf.data[:n]
    out._pgn_rows = buf          # the next append finds its buffer here
    return out


# ---- head_file
# The discriminant head's arrays in a bank file: validated and built (store.py calls it).

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


# ---- the gate's and the object test's arrays (formats 3 and 6)
GATE_ARRAYS = ('gate_tf_mean', 'gate_tf_scale', 'gate_tf_projection', 'gate_coef', 'gate_bias')
OBJECTS_PREFIX = 'objects_'
OBJECTS_ARRAYS = tuple(OBJECTS_PREFIX + k for k in ('projection', 'means', 'labels', 'counts',
                                                    'meta'))


def gate_arrays(gate: Gate) -> dict[str, np.ndarray]:
    """The bank-file arrays (float32) of this gate."""
    tf = gate.transform
    out = {'gate_tf_mean': tf.mean, 'gate_tf_scale': tf.scale,
           'gate_tf_projection': tf.projection, 'gate_coef': gate.coef,
           'gate_bias': gate.bias}
    return {k: v.cpu().numpy().astype(np.float32) for k, v in out.items() if v is not None}

def gate_from_arrays(a: dict[str, np.ndarray], feature_dim: int) -> Gate:
    """Validate and build; raises ValueError naming the problem."""
    mean, scale = a.get('gate_tf_mean'), a.get('gate_tf_scale')
    proj, coef, bias = a.get('gate_tf_projection'), a.get('gate_coef'), a.get('gate_bias')
    if mean is None or scale is None or coef is None or bias is None:
        raise ValueError('gate arrays incomplete (gate_tf_mean, gate_tf_scale, gate_coef, '
                         'gate_bias)')
    d = feature_dim if proj is None else proj.shape[-1]
    shapes = {'gate_tf_mean': (mean, (feature_dim,)), 'gate_tf_scale': (scale, (feature_dim,)),
              'gate_tf_projection': (proj, (feature_dim, d)), 'gate_coef': (coef, (2, d)),
              'gate_bias': (bias, (2,))}
    for name, (arr, shape) in shapes.items():
        if arr is None:
            continue
        if arr.shape != shape or arr.dtype.kind != 'f' or not np.isfinite(arr).all():
            raise ValueError(f'{name} must be finite floats of shape {shape}, got '
                             f'{arr.dtype} {arr.shape}')
    if not (scale > 0).all():
        raise ValueError('gate_tf_scale must be positive')

    def t(x: np.ndarray | None) -> torch.Tensor | None:
        return None if x is None else torch.from_numpy(x.astype(np.float32))
    return Gate(FeatureTransform(t(mean), t(scale), t(proj)), t(coef), t(bias))


def objects_arrays(test: ObjectTest) -> dict[str, np.ndarray]:
    """The file arrays (bank/store.py, format 6)."""
    meta = {'rank': test.rank, 'alpha': test.alpha, 'lam': test.lam, 'theta': test.theta,
            'class_names': list(test.class_names)}
    return {OBJECTS_PREFIX + 'projection': test.projection.numpy().astype(np.float32),
            OBJECTS_PREFIX + 'means': test.means.numpy().astype(np.float32),
            OBJECTS_PREFIX + 'labels': test.labels.numpy().astype(np.int32),
            OBJECTS_PREFIX + 'counts': test.counts.numpy().astype(np.int32),
            OBJECTS_PREFIX + 'meta': np.frombuffer(json.dumps(meta, sort_keys=True).encode(),
                                           dtype=np.uint8)}

def objects_from_arrays(a: dict[str, np.ndarray], feature_dim: int) -> ObjectTest:
    """The test from a file's arrays; any inconsistency raises ValueError."""
    missing = [k for k in OBJECTS_ARRAYS if k not in a]
    if missing:
        raise ValueError(f'object test: missing arrays {missing}')
    try:
        meta = parse_meta(np.asarray(a[OBJECTS_PREFIX + 'meta']))     # size and depth capped
        names = tuple(str(n) for n in meta['class_names'])
        lam, theta, alpha = (float(meta[k]) for k in ('lam', 'theta', 'alpha'))
    except (ValueError, UnicodeDecodeError, KeyError, TypeError) as exc:
        raise ValueError(f'object test: bad metadata ({exc})') from None
    p, m = a[OBJECTS_PREFIX + 'projection'], a[OBJECTS_PREFIX + 'means']
    lab, cnt = a[OBJECTS_PREFIX + 'labels'], a[OBJECTS_PREFIX + 'counts']
    r = p.shape[0] if p.ndim == 2 else -1
    if (p.dtype != np.float32 or m.dtype != np.float32 or p.shape != (r, feature_dim)
            or r < 1 or m.ndim != 2 or m.shape[1] != r or len(m) < 2
            or lab.shape != (len(m),) or cnt.shape != (len(m),)
            or lab.dtype.kind not in 'iu' or cnt.dtype.kind not in 'iu'):
        raise ValueError(f'object test: arrays do not fit {feature_dim}-dim features: '
                         f'projection {p.dtype} {p.shape}, means {m.dtype} {m.shape}, '
                         f'labels {lab.shape}, counts {cnt.shape}')
    if not (np.isfinite(p).all() and np.isfinite(m).all() and np.isfinite([lam, theta])
            .all() and lab.min() >= 0 and lab.max() < len(names) and cnt.min() >= 1):
        raise ValueError('object test: non-finite values, labels out of range or counts < 1')
    return ObjectTest(torch.from_numpy(p), torch.from_numpy(m), torch.from_numpy(lab.astype(
        np.int64)), torch.from_numpy(cnt.astype(np.int64)), names, lam, theta, alpha)


def stored_rows(rows: torch.Tensor, dtype: str) -> torch.Tensor:
    """Unit rows (N, d) as a bank file of `dtype` gives them back (bank/store.py, load)."""
    return torch.nn.functional.normalize(
        torch.from_numpy(quantized(rows, dtype).astype(np.float32)), dim=1)


# ---- the bank and its file
# The format-version table: version -> what a file of it holds beyond the version before.
# A file is written in the lowest version that holds it; an older reader refuses a newer
# version instead of dropping what it cannot read. Version 1 loads as the plain kernel vote.
FORMAT_VERSIONS: dict[int, str] = {
    1: 'kernel vote only (no head): loads as the plain vote',
    2: 'the discriminant head',
    3: 'int8 / int4 rows, a single-view section and its gate',
    4: 'a kernel ridge term',
    5: 'large matrices as scaled float16',
    6: 'an object test of taught classes',
}
VOTE_ONLY_VERSIONS = (1,)
PLAIN_VERSION, FORMAT_VERSION, RIDGE_VERSION, HALF_VERSION, OBJECTS_VERSION = 2, 3, 4, 5, 6
SECTIONED_VERSIONS = tuple(v for v in FORMAT_VERSIONS if v >= FORMAT_VERSION)
VIEWS_PREFIX = 'views_'
REBUILD_HINT = 'point_gn bank build DATASET -o BANK (make default-bank for the shipped one)'
_HEAD_ARRAYS = ('head_whiten', 'head_lda_coef', 'head_lda_bias')
log = logging.getLogger(__name__)
DEFAULT_BANK_NAME = 'modelnet40_default.npz'
_REQUIRED = ('features', 'labels', 'tf_mean', 'tf_scale', 'meta')


def default_bank_path() -> Path:
    """The ModelNet40 bank shipped with the package.

    Found next to the module (pip / editable install), else in the ament share
    directory (colcon install).
    """
    here = Path(__file__).resolve().parents[1] / 'data' / DEFAULT_BANK_NAME
    if here.is_file():
        return here
    try:
        from ament_index_python.packages import get_package_share_directory
        share = Path(get_package_share_directory('point_gn_ros')) / 'banks' / DEFAULT_BANK_NAME
        if share.is_file():
            return share
    except (ImportError, LookupError, ValueError):
        pass
    return here


@dataclass(frozen=True)
class Enrollment:
    """One entry of a bank's enrollment log; never changed once written.

    count: the entries added or removed (an augmented add: its frames, `examples` examples
    stored in `augment`'s frames each); extra: keys of the file's entry this type does not
    name, kept as they are.
    """

    version: int
    action: str                     # 'add' or 'remove'
    class_name: str
    count: int
    time: str                       # ISO 8601, seconds
    source: str
    near_duplicates: int = 0
    examples: int | None = None
    augment: str | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    _KEYS = ('version', 'action', 'class', 'count', 'time', 'source', 'near_duplicates',
             'examples', 'augment')

    def to_json(self) -> dict[str, Any]:
        out = {'version': self.version, 'action': self.action, 'class': self.class_name,
               'count': self.count, 'time': self.time, 'source': self.source,
               'near_duplicates': self.near_duplicates}
        if self.examples is not None:
            out.update(examples=self.examples, augment=self.augment)
        return {**out, **self.extra}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> 'Enrollment':
        """Raises ValueError, KeyError or TypeError on an entry that is not one."""
        examples = d.get('examples')
        return cls(int(d['version']), str(d['action']), str(d['class']), int(d['count']),
                   str(d.get('time', '')), str(d.get('source', '')),
                   int(d.get('near_duplicates') or 0),
                   None if examples is None else int(examples),
                   None if d.get('augment') is None else str(d['augment']),
                   {k: v for k, v in d.items() if k not in cls._KEYS})


# State a bank file keeps in its metadata under these keys; a FeatureBank holds it as fields
# of the same names instead (never in `meta`).
_FIELD_KEYS = ('provenance', 'enrollments', 'enrollments_compacted', 'augmented_entries')


@dataclass
class FeatureBank:
    """Bank features, labels, transform and metadata (see module docstring)."""

    features: torch.Tensor            # (N, d) float32, unit rows
    labels: torch.Tensor              # (N,) int64
    class_names: list[str]
    config: EncoderConfig
    transform: FeatureTransform
    gamma: float
    meta: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None
    head: Head | None = None          # None: the plain kernel vote with `gamma`
    views: 'FeatureBank | None' = None  # the single-view scan section (same classes)
    gate: Gate | None = None          # with views: p(query is a scan), mixes the sections
    objects: ObjectTest | None = None  # with views: the object test of taught classes
    # What enrollment did (bank/enroll.py): its log (the last MAX_HISTORY entries, oldest
    # first), how many older entries were dropped from it, and per class the entries beyond
    # one per example that augmented adds stored.
    enrollments: tuple[Enrollment, ...] = ()
    enrollments_compacted: int = 0
    augmented_entries: Mapping[str, int] = field(default_factory=dict)
    # How the build made it: dataset, format, split, count, per_class {class: entries},
    # created (bank/builder.py); empty for banks not built from a dataset.
    provenance: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        """State given as metadata keys (a build's or a caller's `meta`) becomes the fields.

        A key in `meta` is always meant (a bank never keeps one there): it replaces the field.
        """
        if not any(k in self.meta for k in _FIELD_KEYS):
            return
        meta = dict(self.meta)
        if 'provenance' in meta:
            self.provenance = dict(meta.pop('provenance'))
        if 'enrollments' in meta:
            self.enrollments = tuple(e if isinstance(e, Enrollment) else Enrollment.from_json(e)
                                     for e in meta.pop('enrollments'))
        if 'enrollments_compacted' in meta:
            self.enrollments_compacted = int(meta.pop('enrollments_compacted'))
        if 'augmented_entries' in meta:
            self.augmented_entries = {str(c): int(n)
                                      for c, n in meta.pop('augmented_entries').items()}
        self.meta = meta

    @property
    def built_classes(self) -> set[str]:
        """The classes the build made (all of them when it recorded none)."""
        return set(self.provenance.get('per_class', self.class_names))

    def file_meta(self) -> dict[str, Any]:
        """The metadata as the bank file holds it: `meta` with the fields' keys."""
        meta = dict(self.meta)
        if self.provenance:
            meta['provenance'] = dict(self.provenance)
        if self.enrollments:
            meta['enrollments'] = [e.to_json() for e in self.enrollments]
        if self.enrollments_compacted:
            meta['enrollments_compacted'] = int(self.enrollments_compacted)
        if self.augmented_entries:
            meta['augmented_entries'] = {str(c): int(n)
                                         for c, n in self.augmented_entries.items()}
        return meta

    @property
    def classifier_head(self) -> Head:
        """The head the classifier runs: the stored one, else the plain vote."""
        return self.head if self.head is not None else Head(self.gamma)

    @property
    def num_classes(self) -> int:
        return len(self.class_names)

    def __len__(self) -> int:
        return int(self.features.shape[0])

    def summary(self) -> str:
        prov = self.provenance
        src = prov.get('dataset', '?')
        split = prov.get('split', '?')
        head = self.classifier_head
        kind = ('plain kernel vote' if head.is_plain_vote else
                f'{"whitened " if head.whiten is not None else ""}vote'
                f'{f" + {head.fusion_weight:g} x LDA" if head.lda_coef is not None else ""}'
                f'{" (every dim)" if head.lda_wide else ""}'
                f'{f" + {head.ridge_weight:g} x kernel ridge" if head.has_ridge else ""}')
        return (f'{len(self)} entries, {self.num_classes} classes, dim {self.features.shape[1]} '
                f'({self.meta.get("stored_dtype", "float32")}), {kind}, gamma {self.gamma:g}, '
                f'T {head.temperature:.3g}, '
                f'encoder v{self.meta.get("encoder_version")} {self.config.to_dict()}, '
                f'from {src} [{split}]'
                + ('' if self.views is None else
                   f'; + single-view section: {self.views.summary().split(", encoder")[0]}, '
                   f'mixed by a gate'))

    def check_config(self, cfg: EncoderConfig) -> None:
        """Raise BankError unless the bank was built by an encoder configured as cfg."""
        if cfg != self.config:
            mine, theirs = asdict(self.config), asdict(cfg)
            diff = {k: (v, theirs[k]) for k, v in mine.items() if theirs[k] != v}
            raise BankError(f'{self.path}: bank encoder configuration differs from the running '
                            f'encoder (bank, running): {diff}')

    def save(self, path: str | os.PathLike[str], dtype: str = 'float16') -> Path:
        """Write the bank atomically; dtype of stored features: float16, float32 or int8."""
        path = Path(path)
        if self.objects is not None and self.views is None:
            raise ValueError('an object test needs the views section')
        arrays = self._arrays(dtype, sectioned=self.views is not None,
                              objects=self.objects is not None)
        if self.objects is not None:
            arrays.update(objects_arrays(self.objects))
        if self.views is not None:
            if self.gate is None:
                raise ValueError('a bank with a views section needs its gate')
            arrays.update({VIEWS_PREFIX + k: v for k, v in self.views._arrays(dtype).items()})
            arrays.update(gate_arrays(self.gate))
        for key in ('meta', VIEWS_PREFIX + 'meta'):
            if key in arrays:                  # a file that would not load is not written
                check_meta_writable(arrays[key])
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + '.tmp')
        try:
            with open(tmp, 'wb') as f:
                np.savez_compressed(f, **arrays)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)        # any failure (a full disk): no temp file left
        return path

    def _arrays(self, dtype: str, sectioned: bool = False, objects: bool = False
                ) -> dict[str, np.ndarray]:
        """The file arrays of this section alone (no views section, gate or object test).

        sectioned: the file also holds a views section (format 3, like int8/int4 features);
        objects: and an object test (format 6).
        """
        meta = self.file_meta()
        version = FORMAT_VERSION if dtype in _INTEGER_DTYPES or sectioned else PLAIN_VERSION
        head = self.classifier_head
        if head.has_ridge:
            version = RIDGE_VERSION
        half = meta.get('matrix_dtype') == 'float16'
        if half:
            version = HALF_VERSION
        if objects:
            version = OBJECTS_VERSION
        meta.update(format_version=version,
                    encoder_version=ENCODER_VERSION,
                    encoder_config=self.config.to_dict(), class_names=list(self.class_names),
                    gamma=float(self.gamma), stored_dtype=dtype)
        meta['head'] = {**meta.get('head', {}), 'fusion_weight': float(head.fusion_weight),
                        'temperature': float(head.temperature)}
        if head.has_ridge:
            fitted = meta['head'].get('ridge', {}).get('stored_dtype')
            if fitted not in (None, dtype):
                raise ValueError(f'the kernel ridge head was fitted on rows stored as {fitted}; '
                                 f'saving them as {dtype} would round them again (rebuild '
                                 f'with that dtype)')
            meta['head']['ridge'] = {**meta['head'].get('ridge', {}),
                                     'gamma': float(head.ridge_gamma),
                                     'lambda': float(head.ridge_lambda),
                                     'weight': float(head.ridge_weight)}
        elif isinstance(meta['head'].get('ridge'), dict):
            meta['head']['ridge'] = {**meta['head']['ridge'], 'weight': 0.0}
        arrays = {
            'features': to_stored(self.features, dtype),
            'labels': self.labels.cpu().numpy().astype(np.int32),
            'tf_mean': self.transform.mean.cpu().numpy().astype(np.float32),
            'tf_scale': self.transform.scale.cpu().numpy().astype(np.float32),
        }
        if self.transform.projection is not None:
            arrays['tf_projection'] = self.transform.projection.cpu().numpy().astype(np.float32)
        for name, t in zip(_HEAD_ARRAYS, (head.whiten, head.lda_coef, head.lda_bias),
                           strict=True):
            if t is not None:
                arrays[name] = t.cpu().numpy().astype(np.float32)
        w = arrays.get('head_whiten')
        if version >= RIDGE_VERSION and w is not None and np.array_equal(w, w.T):
            # Formats 4-5 keep an exactly symmetric whitening as its upper triangle (half the
            # bytes: the ridge coefficients' room under the shipped bank's 25 MB).
            arrays['head_whiten_triu'] = w[np.triu_indices(len(w))]
            del arrays['head_whiten']
        if head.has_ridge:
            arrays['head_ridge_coef'] = head.ridge_coef.cpu().numpy().astype(np.float32)
        if head.lda_wide:
            meta['head'].update(lda_wide=True, lda_trace=float(head.lda_trace))
            prec = head.lda_precision.cpu().numpy().astype(np.float32)
            arrays['head_lda_precision'] = prec[np.triu_indices(len(prec))]
            arrays['head_lda_means'] = head.lda_means.cpu().numpy().astype(np.float32)
        if half:
            scales = {}
            for name in HALF_MATRICES:
                if name in arrays:
                    arrays[name], scales[name] = encode(arrays[name])
            meta['matrix_scale_log2'] = scales
        else:
            meta.pop('matrix_scale_log2', None)
        arrays['meta'] = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), dtype=np.uint8)
        return arrays

    @classmethod
    def load(cls, path: str | os.PathLike[str] | None = None,
             expected_config: EncoderConfig | None = None) -> 'FeatureBank':
        """Read and validate a bank file; any problem raises one BankError naming the file."""
        path = Path(path) if path else default_bank_path()
        if not path.is_file():
            raise BankError(f'{path}: bank file not found')
        if not zipfile.is_zipfile(path):
            raise BankError(f'{path}: not a bank (.npz zip archive) file, or truncated')
        arrays = read_npz_bounded(path)   # sizes checked before anything is read
        missing = [k for k in _REQUIRED if k not in arrays]
        if missing:
            raise BankError(f'{path}: not a point_gn bank (missing arrays {missing})')
        bank = cls._from_sections(path, arrays)
        if expected_config is not None:
            bank.check_config(expected_config)
        return bank

    @classmethod
    def _from_sections(cls, path: Path, a: dict[str, np.ndarray]) -> 'FeatureBank':
        """The main section, plus the views section and gate when the file has them."""
        main = {k: v for k, v in a.items() if not k.startswith((VIEWS_PREFIX, OBJECTS_PREFIX))
                and k not in GATE_ARRAYS}
        sub = {k[len(VIEWS_PREFIX):]: v for k, v in a.items() if k.startswith(VIEWS_PREFIX)}
        bank = cls._from_arrays(path, main)
        has_gate = any(k in a for k in GATE_ARRAYS)
        has_objects = any(k.startswith(OBJECTS_PREFIX) for k in a)
        if has_objects != (bank.meta.get('format_version') == OBJECTS_VERSION):
            raise BankError(f'{path}: an object test comes with format {OBJECTS_VERSION}, and '
                            f'only with it (format {bank.meta.get("format_version")})')
        if not sub and not has_gate and not has_objects:
            return bank
        if bank.meta.get('format_version') not in SECTIONED_VERSIONS:
            raise BankError(f'{path}: views section or gate in a format '
                            f'{bank.meta.get("format_version")} bank')
        if not sub or not has_gate:
            raise BankError(f'{path}: a views section and a gate come together')
        views = cls._from_arrays(path, sub, section='views section: ')
        if views.class_names != bank.class_names or views.config != bank.config:
            raise BankError(f'{path}: views section: class names or encoder configuration '
                            'differ from the main section')
        try:
            gate = gate_from_arrays(a, bank.config.feature_dim)
            objects = objects_from_arrays(a, bank.config.feature_dim) if has_objects \
                else None
        except ValueError as exc:
            raise BankError(f'{path}: {exc}') from None
        return replace(bank, views=views, gate=gate, objects=objects)

    @classmethod
    def _from_arrays(cls, path: Path, a: dict[str, np.ndarray],
                     section: str = '') -> 'FeatureBank':
        def bad(problem: str) -> BankError:
            return BankError(f'{path}: {section}{problem}')

        check_bank_arrays(path, a, section)   # limits and ranges first (bank/store.py)
        try:
            meta = json.loads(a['meta'].tobytes().decode())
            if not isinstance(meta, dict):
                raise ValueError('not an object')
        except (ValueError, UnicodeDecodeError) as exc:
            raise bad(f'metadata is not valid JSON ({exc})') from None
        version = meta.get('format_version')
        if version in VOTE_ONLY_VERSIONS:
            log.warning('%s: bank format version %s holds no discriminant head: loaded as the '
                        'plain kernel vote (scores are vote shares, no novelty calibration); '
                        'rebuild it for calibrated probabilities: %s', path, version,
                        REBUILD_HINT)
        elif version not in (PLAIN_VERSION, *SECTIONED_VERSIONS):
            raise bad(f'format version {version!r} is not supported (expected {PLAIN_VERSION}-'
                      f'{OBJECTS_VERSION}; '
                      f'rebuild: {REBUILD_HINT})')
        if meta.get('encoder_version') != ENCODER_VERSION:
            raise bad(f'built by encoder version {meta.get("encoder_version")!r}, running '
                      f'encoder is version {ENCODER_VERSION}: rebuild the bank')
        try:
            cfg = EncoderConfig.from_dict(meta['encoder_config'])
            class_names = [str(n) for n in meta['class_names']]
            gamma = float(meta['gamma'])
        except (KeyError, TypeError, ValueError) as exc:
            raise bad(f'incomplete metadata ({exc})') from None
        a = decode_arrays(bad, a, meta, version == HALF_VERSION or (
            version == OBJECTS_VERSION and meta.get('matrix_dtype') == 'float16'))
        feats, labels = a['features'], a['labels']
        mean, scale = a['tf_mean'], a['tf_scale']
        proj = a.get('tf_projection')
        packed = meta.get('stored_dtype') == 'int4'
        if packed and (feats.dtype != np.uint8 or feats.ndim != 2 or len(feats) == 0):
            raise bad(f'int4 features must be a non-empty 2-D uint8 array, got {feats.dtype} '
                      f'{feats.shape}')
        if not packed and (feats.dtype not in (np.float16, np.float32, np.int8)
                           or feats.ndim != 2 or len(feats) == 0):
            raise bad(f'features must be a non-empty 2-D float16/float32/int8 array, got '
                      f'{feats.dtype} {feats.shape}')
        if labels.ndim != 1 or labels.shape[0] != feats.shape[0] or labels.dtype.kind not in 'iu':
            raise bad(f'labels must be (N,) integers matching {feats.shape[0]} features, got '
                      f'{labels.dtype} {labels.shape}')
        if not class_names or labels.min() < 0 or labels.max() >= len(class_names):
            raise bad(f'labels out of range for {len(class_names)} class names')
        if mean.shape != (cfg.feature_dim,) or scale.shape != (cfg.feature_dim,):
            raise bad(f'transform expects {cfg.feature_dim}-dim encoder features, got '
                      f'{mean.shape} / {scale.shape}')
        out_dim = cfg.feature_dim if proj is None else proj.shape[-1]
        if proj is not None and proj.shape != (cfg.feature_dim, out_dim):
            raise bad(f'projection shape {proj.shape} does not fit {cfg.feature_dim}-dim features')
        if packed:
            if feats.shape[1] != (out_dim + 1) // 2:
                raise bad(f'int4 features have {feats.shape[1]} bytes a row, {out_dim} dims '
                          f'need {(out_dim + 1) // 2}')
            feats = unpack_int4(feats, out_dim)
            if not np.abs(feats).any(axis=1).all():
                raise bad('int4 feature rows must not be all zero')
        if feats.shape[1] != out_dim:
            raise bad(f'features have {feats.shape[1]} dims, transform gives {out_dim}')
        for name, arr in (('features', feats), ('tf_mean', mean), ('tf_scale', scale),
                          ('tf_projection', proj)):
            if arr is not None and not np.isfinite(arr).all():
                raise bad(f'{name} holds non-finite values')
        if not (scale > 0).all():
            raise bad('tf_scale must be positive')
        if not (np.isfinite(gamma) and gamma > 0):
            raise bad(f'gamma must be positive, got {gamma}')
        head = None if version in VOTE_ONLY_VERSIONS else head_from_arrays(
            bad, a, meta, gamma, out_dim, len(class_names), len(labels), RIDGE_VERSION)
        tf = FeatureTransform(torch.from_numpy(mean.astype(np.float32)),
                              torch.from_numpy(scale.astype(np.float32)),
                              None if proj is None else torch.from_numpy(proj.astype(np.float32)))
        # F.normalize's arithmetic in place, in rows with room for enrollments (bank/store.py),
        # converted by copy_: a large bank's rows are not held twice at load, nor later.
        features = empty_rows(*feats.shape)
        features.copy_(torch.from_numpy(feats))
        features.div_(features.norm(dim=1, keepdim=True).clamp_min(1e-12))
        try:   # the fields' keys of meta become the fields (__post_init__)
            bank = cls(features=features, labels=torch.from_numpy(labels.astype(np.int64)),
                       class_names=class_names, config=cfg, transform=tf, gamma=gamma,
                       meta=meta, path=path, head=head)
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise bad(f'provenance or enrollment history is malformed ({exc})') from None
        return _ridge_fitted(bank)


def _ridge_fitted(section: FeatureBank) -> FeatureBank:
    """The section with a ridge term its file left unfitted, fitted; else the section itself.

    Files written before every published version had its ridge term fitted may mark it
    pending (meta head.ridge.pending, with its weight and temperature kept aside); it is
    fitted here on the loaded rows, so whatever loads the file answers the same.
    """
    settings = section.meta.get('head', {}).get('ridge', {})
    if not (isinstance(settings, dict) and settings.get('pending')) or section.head is None:
        return section
    g, lam, w = (float(settings[k]) for k in ('gamma', 'lambda', 'weight_pending'))
    meta = copy.deepcopy(section.meta)
    fitted = meta['head']['ridge']
    fitted.update(weight=w)
    for key in ('pending', 'weight_pending'):
        fitted.pop(key, None)
    meta.setdefault('refit', {})['ridge'] = 'refitted in full at load'
    head = replace(section.head, ridge_coef=fit_ridge(section.features, section.labels,
                                                      section.num_classes, g, lam),
                   ridge_gamma=g, ridge_lambda=lam, ridge_weight=w,
                   temperature=float(settings.get('temperature') or section.head.temperature))
    return replace(section, head=head, meta=meta)
