"""Feature bank file: encoded reference objects, their labels and how they were made.

Format version 2 (one `.npz`, read with allow_pickle=False, never unpickled):
  features      (N, d) float16 or float32  bank features in the vote's space: transformed,
                                           L2-normalised and, when the head whitens,
                                           whitened and re-normalised (`Head.vote_space`)
  labels        (N,) int32                 class index of each entry
  tf_mean       (D,) float32               feature transform fitted on the bank
  tf_scale      (D,) float32
  tf_projection (D, d) float32             optional PCA projection
  head_whiten   (d, d) float32             optional: whitening of the vote (bank/head.py)
  head_lda_coef (C, d) float32             optional: LDA logits = z coef^T + bias
  head_lda_bias (C,) float32
  head_lda_precision (D(D+1)/2,) float32   with meta head.lda_wide: the wide LDA (bank/head.py)
  head_lda_means     (C, D) float32        reads the standardised D-dim rows; coef is (C, D);
                                           precision Sigma_a^-1 as its upper triangle, row-major
  meta          (M,) uint8                 UTF-8 JSON: versions, encoder config, class
                                           names, gamma, head (fusion weight, temperature,
                                           shrinkage, CV figures), calibration, provenance

Format version 4 (only a bank whose head has a kernel ridge term, bank/ridge.py) adds
  head_ridge_coef (N, C) float32           the ridge coefficients, one row per entry
  head_whiten_triu (d(d+1)/2,) float32     instead of head_whiten when that is exactly
                                           symmetric: its upper triangle, row-major
and meta head.ridge (gamma, lambda, weight, CV table).

Format version 5 (a section whose meta `matrix_dtype` is 'float16', bank/half.py) stores
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
  gate_*        the gate that mixes the two sections (bank/gate.py)

Format version 6 (a two-section bank with an object-level test of taught classes,
bank/objects.py) adds `objects_projection`, `objects_means`, `objects_labels`,
`objects_counts` and `objects_meta` (JSON); otherwise as version 5 (or 3-4).

Version-1 banks (kernel vote only, no head) still load, as the plain vote, with a
log line saying so; `point_gn bank build` rebuilds them with the head.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
import json
import logging
import os
from pathlib import Path
from typing import Any
import zipfile

import numpy as np
import torch

from point_gn_ros.core.config import ENCODER_VERSION, EncoderConfig
from point_gn_ros.errors import BankError
from point_gn_ros.bank.gate import GATE_ARRAYS, Gate
from point_gn_ros.bank.head import Head
# Stored row values (bank/quant.py); re-exported: the enrollment code reads them from here.
from point_gn_ros.bank.quant import (_INTEGER_DTYPES, STORED_DTYPES, pack_int4,  # noqa: F401
                                     quantized, to_stored, unpack_int4)
from point_gn_ros.bank.transform import FeatureTransform
from point_gn_ros.bank.half import HALF_MATRICES, decode_arrays, encode
from point_gn_ros.bank.head_file import head_from_arrays
from point_gn_ros.bank.objects import ObjectTest, PREFIX as OBJECTS_PREFIX
from point_gn_ros.bank.rows import empty_rows
from point_gn_ros.bank.npz_read import read_npz_bounded
from point_gn_ros.bank.validate import check_bank_arrays, check_meta_writable

FORMAT_VERSION = 3
# Written as version 2 when a bank has no views section and no int8/int4 features (older
# readers).
PLAIN_VERSION = 2
# Written when a section's head has a kernel ridge term (bank/ridge.py): older readers would
# drop the term silently, so they refuse the file instead.
RIDGE_VERSION = 4
# Written when a section stores its large matrices as scaled float16 (bank/half.py): older
# readers would take the scaled values as they are.
HALF_VERSION = 5
# Written when a two-section bank holds an object test (bank/objects.py): older readers would
# drop it silently (taught classes answered by the head alone), so they refuse the file.
OBJECTS_VERSION = 6
SECTIONED_VERSIONS = (FORMAT_VERSION, RIDGE_VERSION, HALF_VERSION, OBJECTS_VERSION)
VIEWS_PREFIX = 'views_'
# Older formats that still load (as the plain kernel vote).
VOTE_ONLY_VERSIONS = (1,)
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
        prov = self.meta.get('provenance', {})
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
            arrays.update(self.objects.arrays())
        if self.views is not None:
            if self.gate is None:
                raise ValueError('a bank with a views section needs its gate')
            arrays.update({VIEWS_PREFIX + k: v for k, v in self.views._arrays(dtype).items()})
            arrays.update(self.gate.arrays())
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
        meta = dict(self.meta)
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
            gate = Gate.from_arrays(a, bank.config.feature_dim)
            objects = ObjectTest.from_arrays(a, bank.config.feature_dim) if has_objects \
                else None
        except ValueError as exc:
            raise BankError(f'{path}: {exc}') from None
        return replace(bank, views=views, gate=gate, objects=objects)

    @classmethod
    def _from_arrays(cls, path: Path, a: dict[str, np.ndarray],
                     section: str = '') -> 'FeatureBank':
        def bad(problem: str) -> BankError:
            return BankError(f'{path}: {section}{problem}')

        check_bank_arrays(path, a, section)   # limits and ranges first (bank/validate.py)
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
        # F.normalize's arithmetic in place, in rows with room for enrollments (bank/rows.py),
        # converted by copy_: a large bank's rows are not held twice at load, nor later.
        features = empty_rows(*feats.shape)
        features.copy_(torch.from_numpy(feats))
        features.div_(features.norm(dim=1, keepdim=True).clamp_min(1e-12))
        return cls(features=features, labels=torch.from_numpy(labels.astype(np.int64)),
                   class_names=class_names, config=cfg, transform=tf, gamma=gamma, meta=meta,
                   path=path, head=head)
