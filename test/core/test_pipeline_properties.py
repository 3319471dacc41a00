"""Product-level guarantees of prepare + encoder + bank, on real ModelNet40 clouds.

Run with whatever encoder the node uses (make_encoder: the fast path when present).
"""

from pathlib import Path

from conftest import load_modelnet_subset
import numpy as np
import pytest
import torch

from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.recognizer import Recognizer, encode_clouds, make_encoder
from point_gn_ros.core.sampling import prepare, rotate_z


@pytest.fixture(scope='module')
def encoder():
    enc = make_encoder()
    enc.warmup()
    return enc


@pytest.fixture(scope='module')
def test_clouds() -> tuple[np.ndarray, np.ndarray]:
    xyz, labels, _ = load_modelnet_subset('test', 1)  # one per class: 40 clouds
    return xyz, labels


def _encode(encoder, clouds) -> torch.Tensor:
    return encode_clouds(list(clouds), encoder, batch_size=len(clouds))


def test_feature_shape_and_finiteness(encoder, test_clouds) -> None:
    f = _encode(encoder, test_clouds[0][:4])
    assert f.shape == (4, 1620) and f.dtype == torch.float32 and torch.isfinite(f).all()


def test_batch_invariance(encoder, test_clouds) -> None:
    xyz = test_clouds[0][:12]
    together = _encode(encoder, xyz)
    alone = torch.cat([_encode(encoder, xyz[i:i + 1]) for i in range(4)])
    reordered = _encode(encoder, xyz[::-1].copy())
    assert (together[:4] - alone).abs().max() <= 1e-5
    assert (together - reordered.flip(0)).abs().max() <= 1e-5


def test_determinism(encoder, test_clouds) -> None:
    a = _encode(encoder, test_clouds[0][:6])
    b = _encode(encoder, test_clouds[0][:6])
    assert torch.equal(a, b)


def test_sensor_frame_placement_does_not_change_features(encoder, test_clouds) -> None:
    xyz = test_clouds[0][:6]
    placed = xyz * 0.8 + np.array([3.0, -1.5, 0.4], dtype=np.float32)  # metres, offset
    a, b = _encode(encoder, xyz), _encode(encoder, placed)
    assert ((a - b).abs().amax(1) / a.abs().amax(1)).max() < 1e-3


def test_point_order_does_not_change_labels(encoder, test_clouds,
                                            small_bank_path: Path) -> None:
    rec = Recognizer(FeatureBank.load(small_bank_path), encoder=encoder)
    xyz = test_clouds[0]
    rng = np.random.default_rng(0)
    shuffled = [c[rng.permutation(len(c))] for c in xyz]
    np.testing.assert_array_equal(rec.classify_clouds(list(xyz)).labels,
                                  rec.classify_clouds(shuffled).labels)


@pytest.mark.parametrize('name, cloud', [
    ('one point', np.ones((1, 3), np.float32)),
    ('identical points', np.full((300, 3), 2.0, np.float32)),
    ('a line', np.stack([np.linspace(-1, 1, 500)] * 3, 1).astype(np.float32)),
    ('a plane', np.c_[np.random.default_rng(0).uniform(-1, 1, (800, 2)),
                      np.zeros(800)].astype(np.float32)),
    ('two points', np.array([[0, 0, 0], [1, 1, 1]], np.float32)),
])
def test_degenerate_clouds_give_finite_features(encoder, name: str, cloud: np.ndarray) -> None:
    f = encoder.encode(torch.from_numpy(prepare(cloud))[None])
    assert torch.isfinite(f).all(), name


def test_yaw_aligned_bank_classifies_any_heading_alike(encoder, test_clouds,
                                                       tmp_path: Path) -> None:
    from dataclasses import replace

    from conftest import ArrayDataset

    from point_gn_ros.bank.builder import build_bank
    from point_gn_ros.recognizer import make_encoder

    xyz, labels, names = load_modelnet_subset('train', 3)
    yaw_enc = make_encoder(replace(encoder.cfg, yaw_align=True))
    bank = build_bank(ArrayDataset(xyz, labels, names), encoder=yaw_enc, folds=2, progress=False)
    assert bank.config.yaw_align
    rec = Recognizer(FeatureBank.load(bank.save(tmp_path / 'yaw.npz')))
    assert rec.encoder.cfg.yaw_align
    rng = np.random.default_rng(3)
    queries = test_clouds[0]
    yawed = [rotate_z(c, rng.uniform(0, 2 * np.pi)) for c in queries]
    same = rec.classify_clouds(list(queries)).labels == rec.classify_clouds(yawed).labels
    assert same.mean() >= 0.95  # exact up to rounding in FPS/kNN ties
