"""Real-data agreement of the compiled encoder path with its references (slow).

On ModelNet40 (../shared/datasets/modelnet40_1024):
- the fast encoder against the naive oracle (core/encoder_naive.py): features and labels;
- prepare()'s compiled normalisation and yaw alignment (pgn_prepare.c) against its numpy forms;
- midpoint_fill's compiled parts against their references (np.lexsort, the numpy neighbours,
  the k-d tree form that built the shipped bank).

Each test checks an evenly spaced subsample (every `step`-th object) so that it runs in well
under a minute on a 2-core machine; POINT_GN_FULL_AGREEMENT=1 checks every object (the
oracle then takes ~20 min); `-s` shows the measured figures. Agreement checks of
implementations of one function, not accuracy figures.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
import torch

from point_gn_ros.clients.node_client import place_in_sensor_frame
from point_gn_ros.core import kernels, sampling
from point_gn_ros.recognizer import Recognizer, encode_clouds, make_encoder

from conftest import agreement_rows, load_modelnet_split

pytestmark = pytest.mark.slow


def _require_kernels() -> None:
    if kernels.load() is None:
        pytest.skip(f'the compiled kernels are unavailable here: {kernels.last_error()}')


def _every_cloud(step: int) -> np.ndarray:
    """Every `step`-th ModelNet40 cloud of train and test (or all): (M, 1024, 3) float32."""
    clouds = np.concatenate([load_modelnet_split(s)[0] for s in ('train', 'test')])
    return clouds[agreement_rows(len(clouds), step)]


def test_fast_encoder_agrees_with_the_oracle_on_modelnet40() -> None:
    """Fast encoder vs the oracle on every 31st test object (80 of 2,468), shipped bank.

    Each cloud's largest feature difference is within 1e-4 of its largest feature, and the
    shipped bank's classifier gives every cloud the same label from either feature.
    """
    xyz, true, _ = load_modelnet_split('test')
    rows = agreement_rows(len(xyz), 31)
    clouds = list(xyz[rows])
    rec = Recognizer.from_bank(search='exact')
    fast = encode_clouds(clouds, rec.encoder)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)          # the oracle: more threads only spin on a shared machine
    try:
        oracle = encode_clouds(clouds, make_encoder(rec.bank.config, naive=True))
    finally:
        torch.set_num_threads(threads)
    assert fast.shape == oracle.shape == (len(rows), rec.bank.config.feature_dim)
    rel = (fast - oracle).abs().amax(1) / oracle.abs().amax(1)
    fast_lab = rec.classifier.classify(fast, top_k=1).labels
    oracle_lab = rec.classifier.classify(oracle, top_k=1).labels
    print(f'{len(rows)} test objects: largest relative feature difference {float(rel.max()):.3g}'
          f', {int((fast_lab != oracle_lab).sum())} labels differ')          # shown with -s
    assert float(rel.max()) < 1e-4, f'largest relative feature difference {float(rel.max()):.2e}'
    assert np.array_equal(fast_lab, oracle_lab), \
        f'{int((fast_lab != oracle_lab).sum())} of {len(rows)} labels differ'
    assert (fast_lab == true[rows]).mean() > 0.7      # real objects, classified as such


def test_compiled_prepare_agrees_with_its_numpy_forms_on_modelnet40() -> None:
    """prepare() compiled vs resample + normalize + canonical_yaw in numpy (shipped settings).

    Every 10th ModelNet40 cloud (train and test, 1,232 clouds), whole and as a simulated
    single-view scan in a sensor frame (the demo's placement): no prepared cloud differs by
    more than 1e-6 (a flipped sign or axis would), and nearly all are bit-identical.
    """
    _require_kernels()
    cfg = Recognizer.from_bank(search='exact').bank.config
    rng = np.random.default_rng(0)
    for single_view in (False, True):
        equal, worst, n = 0, 0.0, 0
        for cloud in _every_cloud(10):
            raw = place_in_sensor_frame(cloud, rng, single_view=single_view)
            ref = sampling.normalize(sampling.resample(raw, cfg.num_points,
                                                       upsample=cfg.upsample))
            if cfg.yaw_align:
                ref = sampling.canonical_yaw(ref)
            got = sampling.prepare(raw, cfg.num_points, yaw_align=cfg.yaw_align,
                                   upsample=cfg.upsample)
            assert got.shape == ref.shape == (cfg.num_points, 3)
            d = float(np.abs(got - ref).max())
            n, equal, worst = n + 1, equal + (d == 0.0), max(worst, d)
        what = 'scans' if single_view else 'whole clouds'
        print(f'{what}: {n}, {equal} bit-identical, largest difference {worst:.3g}')
        assert worst <= 1e-6, f'{what}: largest difference {worst:.3g}'
        assert equal >= 0.99 * n, f'{what}: {equal} of {n} bit-identical'


def _kdtree_fill(xyz: np.ndarray, n: int) -> np.ndarray:
    """midpoint_fill with its neighbours from scipy's cKDTree: (N, 3) -> (n, 3) float32.

    The form that built the shipped bank; cKDTree orders exactly tied distances its own way,
    which real scans do not have.
    """
    xyz = xyz[np.lexsort((xyz[:, 2], xyz[:, 1], xyz[:, 0]))]
    count = len(xyz)
    if count >= n or count < 2:
        return xyz[np.arange(n) % count]
    rounds = -(-(n - count) // count)
    k = min(rounds, count - 1)
    nb = cKDTree(xyz).query(xyz, k=k + 1)[1].reshape(count, k + 1)[:, 1:]
    parts, missing = [xyz], n - count
    for r in range(rounds):
        rows = (np.arange(count) if missing >= count
                else np.sort(sampling.hashed_subset(xyz, missing)))
        parts.append(xyz[rows] * np.float32(0.5) + xyz[nb[rows, r % k]] * np.float32(0.5))
        missing -= len(rows)
    return np.concatenate(parts).astype(np.float32, copy=False)


def test_compiled_midpoint_fill_agrees_with_its_references_on_modelnet40_scans() -> None:
    """canonical_order, midpoint_neighbours and midpoint_fill on simulated scans, bit for bit.

    Every 10th ModelNet40 cloud (train and test, 1,232) as a single-view scan in a sensor
    frame (nearly all under 1,024 points, which the shipped bank's midpoint upsampling fills
    up): the compiled order equals np.lexsort's, the compiled neighbours equal the numpy
    form's (float64 input takes it), and the fill equals the k-d tree form's.
    """
    _require_kernels()
    rng = np.random.default_rng(0)
    scans = filled = 0
    for cloud in _every_cloud(10):
        scan = np.ascontiguousarray(place_in_sensor_frame(cloud, rng, single_view=True),
                                    dtype=np.float32)
        order = sampling.canonical_order(scan)
        assert np.array_equal(order, np.lexsort((scan[:, 2], scan[:, 1], scan[:, 0])))
        x = scan[order]
        k = min(-(-(1024 - len(x)) // len(x)), len(x) - 1)
        assert np.array_equal(sampling.midpoint_neighbours(x, k),
                              sampling.midpoint_neighbours(x.astype(np.float64), k))
        assert np.array_equal(sampling.midpoint_fill(scan, 1024), _kdtree_fill(scan, 1024))
        scans, filled = scans + 1, filled + (len(scan) < 1024)
    print(f'{scans} scans ({filled} filled up): order, neighbours and fill equal in all')
    assert filled > 0.9 * scans > 1000       # most scans are filled up; the others pass through
