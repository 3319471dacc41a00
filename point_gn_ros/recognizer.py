"""Clouds in, labels out: sampling + encoder + classifier behind one object.

This is what the ROS node, the CLI and the rosbag tools call; it holds no ROS code.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
import os
import time
from typing import Any, Protocol

import numpy as np
import torch

from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.bank.classifier import Classification, Classifier
from point_gn_ros.bank.taught import DEFAULT_FIT_THRESHOLD, fit_rule
from point_gn_ros.core.augment import Augment, yaw_variants
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.core.sampling import ResampleMethod, prepare
from point_gn_ros.core.size import size_descriptors
from point_gn_ros.core.surface import (DEFAULT_SCENE_THRESHOLD, DEFAULT_VOLUME_THRESHOLD,
                                       scene_rule, separated_shares, volume_rule,
                                       volumetric_shares)


class Encoder(Protocol):
    """What the recognizer needs from an encoder."""

    cfg: EncoderConfig

    def encode(self, xyz: torch.Tensor) -> torch.Tensor: ...

    def warmup(self) -> None: ...


def make_encoder(cfg: EncoderConfig = EncoderConfig(), device: str = 'cpu',
                 naive: bool | None = None, threads: int | None = None) -> Encoder:
    """The fast encoder, or the naive oracle if asked (or POINT_GN_NAIVE=1).

    threads: worker threads of the fast encoder (default: every usable CPU). A
    configuration with extra_sigmas gets one such encoder per sigma (core/multiscale.py).
    """
    if cfg.extra_sigmas:
        from point_gn_ros.core.multiscale import MultiScaleEncoder
        return MultiScaleEncoder(cfg, lambda c: make_encoder(c, device, naive, threads))
    if naive is None:
        naive = os.environ.get('POINT_GN_NAIVE', '') == '1'
    if not naive:
        try:
            from point_gn_ros.core.encoder import PointGNEncoder
            return PointGNEncoder(cfg, device=device, threads=threads)
        except ImportError:
            pass
    from point_gn_ros.core.encoder_naive import NaiveEncoder
    enc = NaiveEncoder(cfg, device=device)
    enc.warmup = lambda: None  # type: ignore[attr-defined]
    return enc  # type: ignore[return-value]


def _prepared(cloud: np.ndarray, cfg: EncoderConfig, resample: ResampleMethod, seed: int
              ) -> np.ndarray:
    """One cloud as the encoder with `cfg` takes it: (N, 3) -> (num_points, 3) float32."""
    return prepare(cloud, cfg.num_points, resample, seed, cfg.yaw_align, cfg.upsample)


def encode_clouds(clouds: Iterable[np.ndarray] | np.ndarray, encoder: Encoder,
                  resample: ResampleMethod = 'fps', seed: int = 0, batch_size: int = 64,
                  progress: str | None = None, total: int | None = None,
                  augment: Augment = 'none') -> torch.Tensor:
    """Prepare and encode clouds: each (N_i, 3) float32 finite -> (M * k, feature_dim) float32.

    progress: a tqdm description, or None for no progress bar. augment: encode each prepared
    cloud in the k frames of core/augment.py's group (enrollment examples; k = 1 for 'none'),
    example-major: rows i * k ... i * k + k - 1 are cloud i.
    """
    cfg = encoder.cfg
    if total is None and hasattr(clouds, '__len__'):
        total = len(clouds)  # type: ignore[arg-type]
    bar = None
    if progress is not None:
        from tqdm import tqdm
        bar = tqdm(total=total, desc=progress, unit='cloud', smoothing=0.1)
    out, batch = [], []

    def flush() -> None:
        out.append(encoder.encode(torch.from_numpy(yaw_variants(np.stack(batch), augment))))
        if bar is not None:
            bar.update(len(batch))
        batch.clear()

    for cloud in clouds:
        batch.append(_prepared(cloud, cfg, resample, seed))
        if len(batch) == batch_size:
            flush()
    if batch:
        flush()
    if bar is not None:
        bar.close()
    return torch.cat(out) if out else torch.zeros(0, encoder.cfg.feature_dim)


def rule_thresholds(fit: float = DEFAULT_FIT_THRESHOLD, volume: float = DEFAULT_VOLUME_THRESHOLD,
                    scene: float = DEFAULT_SCENE_THRESHOLD) -> dict[str, float | None]:
    """The node's fit, volume and scene thresholds -> the Recognizer's keyword arguments.

    -10 (fit) and 1.0 (volume, scene) are off (None: no such rule); the defaults are the
    node's.
    """
    return {'fit_threshold': fit_rule(fit), 'volume_threshold': volume_rule(volume),
            'scene_threshold': scene_rule(scene)}


class Recognizer:
    """Classify segmented object clouds against a feature bank."""

    def __init__(self, bank: FeatureBank, device: str = 'cpu', resample: ResampleMethod = 'fps',
                 top_k: int = 5, unknown_threshold: float | None = None,
                 encoder: Encoder | None = None, threads: int | None = None,
                 search: str = 'auto', previous: 'Recognizer | None' = None,
                 object_test: bool = True, metric_size: bool = True,
                 fit_threshold: float | None = None,
                 volume_threshold: float | None = None,
                 scene_threshold: float | None = None) -> None:
        """Encoder + classifier for one bank.

        search: the classifier's bank search, 'auto', 'exact' or 'indexed'
        (bank/classifier.py; 'auto' indexes large banks once, here); previous: the
        recognizer of the bank version this one follows (its index is extended, not rebuilt);
        object_test: apply the bank's object test to taught classes (bank/model.py);
        metric_size: the clouds are in metres, z up: their size (core/size.py) is evidence
        (bank/taught.py); False for inputs without metric meaning (unit-sphere data);
        fit_threshold: shape-and-size fit below which a cloud is unknown (None: no such rule);
        volume_threshold: share of volumetric neighbourhoods (core/surface.py) above which a
        cloud is unknown, a volume of points rather than a view of surfaces (None: no such rule);
        scene_threshold: share of the area seen from above apart from the cloud's largest part
        (core/surface.py) above which a cloud is unknown, several objects rather than one
        (None: no such rule).
        """
        self.bank = bank
        self.encoder = encoder or make_encoder(bank.config, device, threads=threads)
        bank.check_config(self.encoder.cfg)
        self.classifier = Classifier(bank, device, unknown_threshold, search=search,
                                     previous=None if previous is None else previous.classifier,
                                     object_test=object_test, fit_threshold=fit_threshold,
                                     volume_threshold=volume_threshold,
                                     scene_threshold=scene_threshold)
        self.metric_size = metric_size
        self.resample = resample
        self.top_k = top_k

    def set_unknown_threshold(self, unknown_threshold: float | None) -> None:
        """Set the classifier's probability / calibrated unknown rule.

        As bank/classifier.py `unknown_rules` resolves it; raises ValueError as it does.
        """
        self.classifier.set_unknown_threshold(unknown_threshold)

    @classmethod
    def from_bank(cls, path: str | os.PathLike[str] | None = None, device: str = 'cpu',
                  resample: ResampleMethod = 'fps', top_k: int = 5,
                  unknown_threshold: float | None = None,
                  threads: int | None = None, search: str = 'auto',
                  fit_threshold: float | None = None,
                  volume_threshold: float | None = None,
                  scene_threshold: float | None = None,
                  metric_size: bool = True) -> 'Recognizer':
        """Load a bank (None: the shipped default) and build the matching encoder."""
        return cls(FeatureBank.load(path), device, resample, top_k, unknown_threshold,
                   threads=threads, search=search, fit_threshold=fit_threshold,
                   volume_threshold=volume_threshold, scene_threshold=scene_threshold,
                   metric_size=metric_size)

    @classmethod
    def as_node(cls, path: str | os.PathLike[str] | None = None, *, metric_size: bool = True,
                **kwargs: Any) -> 'Recognizer':
        """`from_bank` with the node's default unknown rules (docs/SIZE.md).

        What the offline tools use, so that they answer as a node at its defaults does.
        metric_size: False for clouds without metric meaning (unit-sphere data).
        """
        return cls.from_bank(path, metric_size=metric_size, **rule_thresholds(), **kwargs)

    @property
    def class_names(self) -> list[str]:
        return self.bank.class_names

    def warmup(self) -> float:
        """Pay compile and first-call costs now; returns the seconds it took."""
        t0 = time.perf_counter()
        self.encoder.warmup()
        cloud = np.random.default_rng(0).normal(size=(2000, 3)).astype(np.float32)
        self.classify_clouds([cloud])
        # a sparse cloud too: filling it up (upsample 'midpoint') has first-call costs of its
        # own (without the compiled kernels its numpy form), which must not land on the
        # first real scan
        self.classify_clouds([cloud[:300]])
        return time.perf_counter() - t0

    def encode(self, clouds: Sequence[np.ndarray], augment: Augment = 'none') -> torch.Tensor:
        """clouds: list of (N_i, 3) float32 finite, N_i >= 1 -> (B * k, feature_dim) float32.

        augment: see `encode_clouds` (k variants per cloud; 'none' for queries).
        """
        return encode_clouds(clouds, self.encoder, self.resample, batch_size=max(1, len(clouds)),
                             augment=augment)

    def classify_clouds(self, clouds: Sequence[np.ndarray]) -> Classification:
        """clouds: list of (N_i, 3) float32 finite, N_i >= 1 -> Classification of B rows."""
        if not clouds:
            return self.classifier.classify(torch.zeros(0, self.encoder.cfg.feature_dim),
                                            self.top_k)
        return self.classifier.classify(self.encode(clouds), self.top_k, self.sizes(clouds),
                                        self.volumes(clouds), self.separations(clouds))

    def volumes(self, clouds: Sequence[np.ndarray]) -> np.ndarray | None:
        """(B,) share of volumetric neighbourhoods (core/surface.py); None without the rule."""
        return None if self.classifier.volume_threshold is None else volumetric_shares(clouds)

    def separations(self, clouds: Sequence[np.ndarray]) -> np.ndarray | None:
        """(B,) share of area apart from each cloud's largest part (core/surface.py).

        None without the scene rule.
        """
        return None if self.classifier.scene_threshold is None else separated_shares(clouds)

    def sizes(self, clouds: Sequence[np.ndarray]) -> np.ndarray | None:
        """(B, SIZE_DIM) metric log sizes (core/size.py); None without metric_size."""
        return size_descriptors(list(clouds)) if self.metric_size else None

    def classify_later(self, clouds: Sequence[np.ndarray]) -> Callable[[], Classification]:
        """`classify_clouds(clouds)` in two parts: started now, finished by the returned call.

        The clouds are prepared and their encoding started on the encoder's workers now; the
        returned call waits for it and classifies. Between the two the caller can finish an
        earlier batch (node/pipeline.py), so that the encoder's threads and the caller's work
        overlap. The same answers, bit for bit.
        """
        start = getattr(self.encoder, 'encode_later', None)
        if not clouds or start is None:
            result = self.classify_clouds(clouds)
            return lambda: result
        cfg = self.encoder.cfg
        batch = np.stack([_prepared(c, cfg, self.resample, 0) for c in clouds])
        features = start(torch.from_numpy(batch))
        sizes, volumes, apart = self.sizes(clouds), self.volumes(clouds), self.separations(clouds)
        return lambda: self.classifier.classify(features(), self.top_k, sizes, volumes, apart)
