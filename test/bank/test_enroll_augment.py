"""Enrollment augmentation: examples stored in the D4 frames of the yaw alignment."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from point_gn_ros.bank.enroll import (BankFile, EnrollError, add_examples, class_counts,
                                      predictable, remove_class)
from point_gn_ros.bank.refit import RefitPolicy, example_counts
from point_gn_ros.bank.live import LiveBank
from point_gn_ros.bank.refit import example_groups
from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.bank.model import FeatureTransform
from point_gn_ros.core.augment import AUGMENTS, variants_per_example, yaw_variants
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.core.sampling import prepare
from point_gn_ros.recognizer import Recognizer, encode_clouds, make_encoder

CFG = EncoderConfig(num_points=256, k=32, yaw_align=True)


def _shape(kind: int, rng: np.random.Generator, n: int = 600) -> np.ndarray:
    """Asymmetric x-y shapes (an L, a T, a wedge...) with noise: (n, 3) float32."""
    t = rng.uniform(size=(n, 3))
    if kind == 0:      # L: a long bar and a short one
        pts = np.where(t[:, :1] < 0.6, t * [2.0, 0.3, 1], t * [0.3, 1.2, 1])
    elif kind == 1:    # wedge: thick at one end
        pts = t * [2.0, 1.0, 0.5]
        pts[:, 1] *= pts[:, 0] / 2.0
    else:              # off-centre block on a plate
        pts = np.where(t[:, :1] < 0.5, t * [2.0, 1.5, 0.1], t * [0.5, 0.4, 1.0] + [1.2, 0.9, 0])
    return (pts + rng.normal(0, 0.01, pts.shape)).astype(np.float32)


@pytest.fixture(scope='module')
def encoder():  # noqa: ANN201
    return make_encoder(CFG, 'cpu', threads=1)


@pytest.fixture(scope='module')
def bank_and_shape(encoder) -> tuple[BankFile, np.ndarray]:  # noqa: ANN001
    """A 3-class bank of real encoder features (8 noisy copies per shape) + a shape to enroll."""
    rng = np.random.default_rng(0)
    clouds = [_shape(k, rng) for k in range(3) for _ in range(8)]
    feats = encode_clouds(clouds, encoder)
    tf = FeatureTransform.fit(feats, 'standardize')
    bank = FeatureBank(features=tf(feats), labels=torch.arange(3).repeat_interleave(8),
                       class_names=['L', 'wedge', 'plate'], config=CFG, transform=tf,
                       gamma=50.0)
    new = np.concatenate([_shape(0, rng, 300) * [1, 2, 1], _shape(1, rng, 300) + [0, 2.5, 0]])
    return BankFile.of(bank, 'float32'), new.astype(np.float32)


def test_variants_are_the_d4_group_identity_first() -> None:
    rng = np.random.default_rng(1)
    xyz = prepare(_shape(0, rng), 256, yaw_align=True)[None]           # (1, 256, 3)
    for name, mats in AUGMENTS.items():
        out = yaw_variants(xyz, name)
        assert out.shape == (len(mats), 256, 3) == (variants_per_example(name), 256, 3)
        assert np.array_equal(out[0], xyz[0])                          # canonical frame first
        assert np.array_equal(out[:, :, 2], np.repeat(xyz[:, :, 2], len(mats), 0))
        # Isometries of the x-y plane: every point keeps its distance to the axis.
        r = np.hypot(out[..., 0], out[..., 1])
        assert np.allclose(r, r[0])
    d4 = yaw_variants(xyz, 'd4')
    keys = {tuple(np.round(v[:8, :2].ravel(), 5)) for v in d4}
    assert len(keys) == 8                                              # 8 distinct frames
    # Closed under the group: the d4 variants of any variant are the same 8 clouds.
    again = {tuple(np.round(v[:8, :2].ravel(), 5)) for v in yaw_variants(d4[5:6], 'd4')}
    assert again == keys
    # Example-major: rows b*k ... b*k + k - 1 belong to cloud b.
    two = yaw_variants(np.concatenate([xyz, xyz + 1]), 'rot4')
    assert np.array_equal(two[4], xyz[0] + 1)
    with pytest.raises(ValueError, match='augment must be one of'):
        yaw_variants(xyz, 'd8')


def test_encode_clouds_augmented_rows(encoder) -> None:  # noqa: ANN001
    rng = np.random.default_rng(2)
    clouds = [_shape(k, rng) for k in range(3)]
    plain = encode_clouds(clouds, encoder)
    aug = encode_clouds(clouds, encoder, augment='d4', batch_size=2)
    assert aug.shape == (24, CFG.feature_dim)
    assert torch.allclose(aug[::8], plain, atol=1e-5)       # canonical frame = plain encoding
    assert not torch.allclose(aug[1], aug[0], atol=1e-3)     # other frames: other features


def test_d4_enrollment_holds_8x_entries_counts_examples(bank_and_shape, encoder,  # noqa: ANN001
                                                        tmp_path: Path) -> None:
    bf, new = bank_and_shape
    rng = np.random.default_rng(3)
    scans = [new + rng.normal(0, 0.01, new.shape).astype(np.float32) for _ in range(3)]
    feats = encode_clouds(scans, encoder, augment='d4')
    res = add_examples(bf, feats, 'mine', source='test', augment='d4')
    assert res.count == 24 and res.examples == 3 and class_counts(res.bank)['mine'] == 24
    assert example_counts(res.bank).tolist() == [8, 8, 8, 3]
    assert '3 example(s)' in res.describe() and '24 entries, d4' in res.describe()
    entry = res.bank.enrollments[-1]
    assert (entry.count, entry.examples, entry.augment) == (24, 3, 'd4')
    # min_examples counts examples, not frames: 3 examples do not pass a gate of 4.
    assert 'mine' not in predictable(res.bank, 4) and 'mine' in predictable(res.bank, 3)
    # Each example's 8 frames form one CV group; built entries stay singletons.
    g = example_groups(res.bank)
    assert g is not None and len(np.unique(g[-24:])) == 3 and len(np.unique(g[:24])) == 24
    assert all(len(np.unique(g[-24:][i * 8:(i + 1) * 8])) == 1 for i in range(3))
    # Survives save + load; a plain add of the same class counts 1 example per entry.
    back = BankFile.load(res.file.save(tmp_path / 'b.npz'))
    more = add_examples(back, encode_clouds(scans[:1], encoder), 'mine')
    assert example_counts(more.bank)[-1] == 4 and class_counts(more.bank)['mine'] == 25
    assert len(np.unique(example_groups(more.bank)[-25:])) == 4
    gone = remove_class(more.file, 'mine')
    assert not gone.bank.augmented_entries
    assert example_groups(gone.bank) is None
    with pytest.raises(EnrollError, match='M \\* 8'):
        add_examples(bf, feats[:20], 'bad', augment='d4')
    with pytest.raises(EnrollError, match='augment must be one of'):
        add_examples(bf, feats, 'bad', augment='d16')


def test_query_in_another_d4_frame_is_matched_only_with_augmentation(
        bank_and_shape, encoder) -> None:  # noqa: ANN001
    """A view aligned into a D4 image of the enrolled scan's frame matches an augmented class.

    (What canonical_yaw does on partial scans: axis swaps and sign flips.)
    """
    bf, new = bank_and_shape
    canon = prepare(new, CFG.num_points, yaw_align=True)[None]
    frames = yaw_variants(canon, 'd4')[1:]                               # 7 non-identity frames
    queries = encoder.encode(torch.from_numpy(frames))
    results = {}
    for augment in ('none', 'd4'):
        feats = encode_clouds([new], encoder, augment=augment)
        live = LiveBank(bf, lambda a: Recognizer(a, encoder=encoder), RefitPolicy(gamma='keep'))
        live.add(feats, 'mine', source='test', augment=augment)
        results[augment] = live.current().model.classifier.classify(queries)
    mine = 3
    assert (results['d4'].labels == mine).all()
    assert float(results['d4'].novelty.max()) < 1e-3                    # an exact stored frame
    # Without augmentation the other frames are not the stored entry (so the test can fail).
    assert float(results['none'].novelty.min()) > 10 * float(results['d4'].novelty.max())


def test_engine_splits_augmented_work_per_step(bank_and_shape, encoder) -> None:  # noqa: ANN001
    from point_gn_ros.node.enroll_engine import EnrollEngine

    bf, new = bank_and_shape
    live = LiveBank(bf, lambda a: Recognizer(a, encoder=encoder))
    done: list = []
    engine = EnrollEngine(live, lambda snap, res: done.append(res), lambda _t: None,
                          lambda _k, _t: None, chunk=16, augment='d4')
    try:
        assert engine.chunk == 2                # 2 examples x 8 frames = one 16-cloud step
        clouds = [new + np.float32(0.01 * i) for i in range(5)]
        engine.submit('mine', clouds, source='test')
        steps = 0
        while engine.step(live.current().model):
            steps += 1
        engine.flush(timeout=30.0)
        assert steps + 1 == 3                   # 5 examples in steps of 2
        assert len(done) == 1 and done[0].examples == 5 and done[0].count == 40
        assert done[0].augment == 'd4' and engine.counters['enrolled'] == 5
    finally:
        engine.close()
