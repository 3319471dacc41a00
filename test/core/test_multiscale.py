"""Multi-scale features (EncoderConfig.extra_sigmas): encoder, configuration, banks, cache."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import ArrayDataset
from point_gn_ros.bank.builder import build_bank, encode_dataset
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.core.config import MAX_EXTRA_SIGMAS, EncoderConfig
from point_gn_ros.errors import BankError
from point_gn_ros.recognizer import Recognizer, make_encoder

CFG = EncoderConfig(num_points=64, k=16, extra_sigmas=(0.25,))


def _clouds(n: int, seed: int = 0) -> torch.Tensor:
    return torch.rand(n, 64, 3, generator=torch.Generator().manual_seed(seed)) - 0.5


def test_features_are_each_sigmas_features_concatenated_and_match_the_oracle() -> None:
    x = _clouds(3)
    got = make_encoder(CFG, naive=False).encode(x)
    assert got.shape == (3, CFG.feature_dim) and CFG.feature_dim == 2 * CFG.scale_dim
    parts = [make_encoder(EncoderConfig(num_points=64, k=16, sigma=s), naive=False).encode(x)
             for s in (0.4, 0.25)]
    assert torch.equal(got, torch.cat(parts, 1))
    assert not torch.equal(parts[0], parts[1])          # the second scale is not a copy
    oracle = make_encoder(CFG, naive=True).encode(x)
    # a single-sigma encoder given the multi-scale configuration would fill half a row
    from point_gn_ros.core.encoder import PointGNEncoder
    from point_gn_ros.core.encoder_naive import NaiveEncoder
    for cls in (PointGNEncoder, NaiveEncoder):
        with pytest.raises(ValueError, match='one encoder per sigma'):
            cls(CFG)
    rel = ((got - oracle).abs() / oracle.abs().clamp_min(1e-3)).max()
    assert float(rel) < 1e-4


def test_configuration_round_trips_and_single_scale_dicts_are_unchanged() -> None:
    assert 'extra_sigmas' not in EncoderConfig().to_dict()   # old banks' metadata and cache keys
    back = EncoderConfig.from_dict(json.loads(json.dumps(CFG.to_dict())))
    assert back == CFG and back.extra_sigmas == (0.25,) and back.sigmas == (0.4, 0.25)
    assert CFG.single(0.25) == EncoderConfig(num_points=64, k=16, sigma=0.25)
    for bad in ([0.0], [float('nan')], [0.3] * (MAX_EXTRA_SIGMAS + 1)):
        with pytest.raises(ValueError, match='extra_sigmas'):
            EncoderConfig(extra_sigmas=bad)


@pytest.fixture(scope='module')
def multiscale_bank(tmp_path_factory: pytest.TempPathFactory) -> Path:
    rng = np.random.default_rng(0)
    # three shapes: a flat disc, a tall stick, a ball; 6 noisy examples each
    xyz, labels = [], []
    for c in range(3):
        for _ in range(6):
            p = rng.normal(size=(64, 3)).astype(np.float32)
            p *= np.array([[1, 1, 0.05], [0.1, 0.1, 1], [1, 1, 1]][c], np.float32)
            xyz.append(p)
            labels.append(c)
    data = ArrayDataset(np.stack(xyz), np.array(labels), ['disc', 'stick', 'ball'])
    bank = build_bank(data, CFG, folds=2, progress=False)
    return bank.save(tmp_path_factory.mktemp('ms') / 'bank.npz', dtype='float32')


def test_a_multiscale_bank_saves_loads_and_classifies(multiscale_bank: Path) -> None:
    bank = FeatureBank.load(multiscale_bank)
    assert bank.config == CFG and bank.transform.in_dim == CFG.feature_dim
    rec = Recognizer(bank)
    assert rec.encoder.cfg == CFG
    stick = np.random.default_rng(5).normal(size=(64, 3)).astype(np.float32)
    stick[:, :2] *= 0.1
    res = rec.classify_clouds([stick])
    assert bank.class_names[int(res.labels[0])] == 'stick'


def test_a_single_scale_encoder_is_refused_naming_the_difference(multiscale_bank: Path) -> None:
    with pytest.raises(BankError, match=r'extra_sigmas.*\(\(0\.25,\), \(\)\)'):
        FeatureBank.load(multiscale_bank, expected_config=CFG.single(0.4))


def test_features_are_cached_per_scale(tmp_path: Path) -> None:
    xyz = _clouds(5, seed=1).numpy()
    data = ArrayDataset(xyz, np.arange(5) % 2, ['a', 'b'], str(tmp_path / 'data'))
    both = encode_dataset(data, make_encoder(CFG), progress=False, cache_dir=tmp_path)
    assert len(list(tmp_path.glob('feats_*.npy'))) == 2
    # a single-scale encoding of the same data is the first block, read from the cache
    first = encode_dataset(data, make_encoder(CFG.single(0.4)), progress=False,
                           cache_dir=tmp_path)
    assert torch.equal(first, both[:, :CFG.scale_dim])
    assert len(list(tmp_path.glob('feats_*.npy'))) == 2


def test_the_node_answers_with_a_multiscale_bank_as_offline(
        tmp_path: Path, modelnet_dir: Path) -> None:
    """Over real DDS: the node builds the bank's multi-scale encoder and agrees offline."""
    from node_testing import (BANK_CLASSES, NODE_FQN, TEST_NUM_POINTS, Harness, NodeProcess,
                              assert_same_labels, build_tiny_bank, cloud_msg, pick,
                              reliable_qos, stamp, stamp_key, to_sensor_frame)
    from sensor_msgs.msg import PointCloud2

    from point_gn_ros.pointcloud2 import decode_classifications

    bank = build_tiny_bank(tmp_path / 'ms_bank.npz', extra_sigmas=(0.25,))
    assert FeatureBank.load(bank).config.extra_sigmas == (0.25,)
    rng = np.random.default_rng(3)
    clouds = [to_sensor_frame(c, rng) for c in pick('test', BANK_CLASSES, 1)[0]]
    node = NodeProcess({'bank_path': str(bank), 'num_points': TEST_NUM_POINTS},
                       tmp_path / 'node.log')
    harness = Harness('multiscale_test')
    try:
        pub = harness.node.create_publisher(PointCloud2, 'segmented_objects', reliable_qos(20))
        got = harness.collect(PointCloud2, f'{NODE_FQN}/classifications', reliable_qos(50))
        harness.wait_for_subscribers([pub], node)
        harness.spin_for(0.5)
        for i, cloud in enumerate(clouds):   # one at a time: the input queue holds 5
            pub.publish(cloud_msg(cloud, 'lidar', stamp(100 + i)))
            assert harness.spin_until(lambda n=i + 1: len(got) >= n, 60.0), node.log()
        keys = [(100 + i, 0) for i in range(len(clouds))]
        by_key = {stamp_key(m.header): m for m in got}
        labels = [int(decode_classifications(by_key[k])['class_id'][0]) for k in keys]
    finally:
        harness.close()
        node.stop()
    assert_same_labels(labels, bank, clouds)
