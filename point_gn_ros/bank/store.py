"""Feature bank file: encoded reference objects, their labels and how they were made.

Format (one `.npz`, read with allow_pickle=False, never unpickled):
  features     (N, d) float16 or float32  transformed, L2-normalised bank features
  labels       (N,) int32                 class index of each entry
  tf_mean      (D,) float32               feature transform fitted on the bank
  tf_scale     (D,) float32
  tf_projection (D, d) float32            optional PCA projection
  meta         (M,) uint8                 UTF-8 JSON: versions, encoder config, class
                                          names, gamma, calibration, provenance
"""

from __future__ import annotations

from dataclasses import dataclass, field
import io
import json
import os
from pathlib import Path
from typing import Any
import zipfile

import numpy as np
import torch

from point_gn_ros.core.config import ENCODER_VERSION, EncoderConfig
from point_gn_ros.errors import BankError
from point_gn_ros.bank.transform import FeatureTransform
from point_gn_ros.bank.validate import check_bank_arrays

FORMAT_VERSION = 1
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

    @property
    def num_classes(self) -> int:
        return len(self.class_names)

    def __len__(self) -> int:
        return int(self.features.shape[0])

    def summary(self) -> str:
        prov = self.meta.get('provenance', {})
        src = prov.get('dataset', '?')
        split = prov.get('split', '?')
        return (f'{len(self)} entries, {self.num_classes} classes, dim {self.features.shape[1]} '
                f'({self.meta.get("stored_dtype", "float32")}), gamma {self.gamma:g}, '
                f'encoder v{self.meta.get("encoder_version")} {self.config.to_dict()}, '
                f'from {src} [{split}]')

    def check_config(self, cfg: EncoderConfig) -> None:
        """Raise BankError unless the bank was built by an encoder configured as cfg."""
        if cfg != self.config:
            diff = {k: (v, cfg.to_dict()[k]) for k, v in self.config.to_dict().items()
                    if cfg.to_dict()[k] != v}
            raise BankError(f'{self.path}: bank encoder configuration differs from the running '
                            f'encoder (bank, running): {diff}')

    def save(self, path: str | os.PathLike[str], dtype: str = 'float16') -> Path:
        """Write the bank atomically; dtype of stored features: float16 or float32."""
        if dtype not in ('float16', 'float32'):
            raise ValueError(f'dtype must be float16 or float32, got {dtype}')
        path = Path(path)
        meta = dict(self.meta)
        meta.update(format_version=FORMAT_VERSION, encoder_version=ENCODER_VERSION,
                    encoder_config=self.config.to_dict(), class_names=list(self.class_names),
                    gamma=float(self.gamma), stored_dtype=dtype)
        arrays = {
            'features': self.features.cpu().numpy().astype(dtype),
            'labels': self.labels.cpu().numpy().astype(np.int32),
            'tf_mean': self.transform.mean.cpu().numpy().astype(np.float32),
            'tf_scale': self.transform.scale.cpu().numpy().astype(np.float32),
            'meta': np.frombuffer(json.dumps(meta, sort_keys=True).encode(), dtype=np.uint8),
        }
        if self.transform.projection is not None:
            arrays['tf_projection'] = self.transform.projection.cpu().numpy().astype(np.float32)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + '.tmp')
        with open(tmp, 'wb') as f:
            np.savez_compressed(f, **arrays)
        os.replace(tmp, path)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike[str] | None = None,
             expected_config: EncoderConfig | None = None) -> 'FeatureBank':
        """Read and validate a bank file; any problem raises one BankError naming the file."""
        path = Path(path) if path else default_bank_path()
        if not path.is_file():
            raise BankError(f'{path}: bank file not found')
        if not zipfile.is_zipfile(path):
            raise BankError(f'{path}: not a bank (.npz zip archive) file, or truncated')
        try:
            with np.load(path, allow_pickle=False) as z:
                missing = [k for k in _REQUIRED if k not in z.files]
                if missing:
                    raise BankError(f'{path}: not a point_gn bank (missing arrays {missing})')
                arrays = {k: z[k] for k in z.files}
        except BankError:
            raise
        except (zipfile.BadZipFile, OSError, ValueError, EOFError, io.UnsupportedOperation) as exc:
            raise BankError(f'{path}: unreadable or corrupt bank file ({exc})') from None
        bank = cls._from_arrays(path, arrays)
        if expected_config is not None:
            bank.check_config(expected_config)
        return bank

    @classmethod
    def _from_arrays(cls, path: Path, a: dict[str, np.ndarray]) -> 'FeatureBank':
        def bad(problem: str) -> BankError:
            return BankError(f'{path}: {problem}')

        check_bank_arrays(path, a)   # limits and ranges first (bank/validate.py)
        try:
            meta = json.loads(a['meta'].tobytes().decode())
            if not isinstance(meta, dict):
                raise ValueError('not an object')
        except (ValueError, UnicodeDecodeError) as exc:
            raise bad(f'metadata is not valid JSON ({exc})') from None
        if meta.get('format_version') != FORMAT_VERSION:
            raise bad(f'format version {meta.get("format_version")!r} is not supported '
                      f'(expected {FORMAT_VERSION})')
        if meta.get('encoder_version') != ENCODER_VERSION:
            raise bad(f'built by encoder version {meta.get("encoder_version")!r}, running '
                      f'encoder is version {ENCODER_VERSION}: rebuild the bank')
        try:
            cfg = EncoderConfig.from_dict(meta['encoder_config'])
            class_names = [str(n) for n in meta['class_names']]
            gamma = float(meta['gamma'])
        except (KeyError, TypeError, ValueError) as exc:
            raise bad(f'incomplete metadata ({exc})') from None
        feats, labels = a['features'], a['labels']
        mean, scale = a['tf_mean'], a['tf_scale']
        proj = a.get('tf_projection')
        if feats.dtype not in (np.float16, np.float32) or feats.ndim != 2 or len(feats) == 0:
            raise bad(f'features must be a non-empty 2-D float16/float32 array, got '
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
        tf = FeatureTransform(torch.from_numpy(mean.astype(np.float32)),
                              torch.from_numpy(scale.astype(np.float32)),
                              None if proj is None else torch.from_numpy(proj.astype(np.float32)))
        features = torch.nn.functional.normalize(torch.from_numpy(feats.astype(np.float32)), dim=1)
        return cls(features=features, labels=torch.from_numpy(labels.astype(np.int64)),
                   class_names=class_names, config=cfg, transform=tf, gamma=gamma, meta=meta,
                   path=path)
