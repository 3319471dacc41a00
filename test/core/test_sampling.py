"""Resampling and normalisation."""

import ctypes
from pathlib import Path

from conftest import KERNEL_BUILDS, kernel_build
import numpy as np
import pytest
import torch

from point_gn_ros.core.encoder_naive import fps as oracle_fps
from point_gn_ros.core.encoder_naive import knn as oracle_knn
from point_gn_ros.core.sampling import (FPS_MAX_INPUT, canonical_order, canonical_yaw,
                                        fps_indices, normalize,
                                        prepare, resample)


def _cloud(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, 3)).astype(np.float32)


@pytest.mark.parametrize('n_in', [1, 5, 700, 1024, 3000])
@pytest.mark.parametrize('method', ['fps', 'random'])
def test_any_count_becomes_1024(n_in: int, method: str) -> None:
    out = resample(_cloud(n_in), 1024, method)
    assert out.shape == (1024, 3) and out.dtype == np.float32


def test_upsampling_repeats_points_never_zero_pads() -> None:
    cloud = _cloud(10) + 5.0  # far from the origin: a zero pad would stand out
    out = resample(cloud, 1024)
    assert not np.any(np.all(out == 0, axis=1))
    assert {tuple(p) for p in out} == {tuple(p) for p in cloud}


def test_fps_spreads_points_better_than_random() -> None:
    cloud = _cloud(5000)
    def coverage(sub: np.ndarray) -> float:  # farthest any input point is from the subset
        d = ((cloud[:, None, :] - sub[None, :256, :]) ** 2).sum(-1)
        return float(d.min(1).max())
    assert coverage(resample(cloud, 256, 'fps')) < 0.7 * coverage(resample(cloud, 256, 'random'))


def test_fps_matches_the_oracle_encoder_fps() -> None:
    cloud = _cloud(2048, 3)
    ours = fps_indices(cloud, 512)
    oracle = oracle_fps(torch.from_numpy(cloud), 512).numpy()
    np.testing.assert_array_equal(ours, oracle)


@pytest.mark.parametrize('n', [63, 64, 65, 130, 1000, 5000])
@pytest.mark.parametrize('kind', ['normal', 'grid', 'duplicated'])
def test_compiled_fps_ties_like_the_oracle(n: int, kind: str) -> None:
    # the vector loops (AVX-512: 4 chains of 16 lanes, a scalar tail) keep each lane's first
    # maximum and merge by (distance, lowest index): exact ties must go where the oracle's do
    cloud = _cloud(n, 5)
    if kind == 'grid':           # coordinates on a coarse grid: many equal distances
        cloud = np.round(cloud * 2) / 2
    elif kind == 'duplicated':   # every point twice
        cloud[n // 2:] = cloud[:n - n // 2]
    m = min(n, 300)
    np.testing.assert_array_equal(fps_indices(cloud, m),
                                  oracle_fps(torch.from_numpy(cloud), m).numpy())


@pytest.mark.parametrize('build', sorted(KERNEL_BUILDS))
def test_every_simd_build_of_fps_ties_like_the_oracle(build: str, tmp_path: Path) -> None:
    # pgn_geom.c has a portable, an AVX2 and an AVX-512 FPS loop: each build that this CPU
    # runs, against the oracle, with exact ties and a tail beyond the vector blocks
    lib = kernel_build('pgn_geom.c', build, tmp_path,
                       ('-ffp-contract=off', '-fno-fast-math', '-fopenmp-simd'))
    ptr, i64 = ctypes.c_void_p, ctypes.c_int64
    lib.pgn_fps_from.argtypes = [ptr, ptr, ptr, i64, i64, i64, ptr, ptr]
    for n, kind in ((1000, 'grid'), (517, 'duplicated'), (4099, 'normal')):
        cloud = _cloud(n, 8)
        if kind == 'grid':
            cloud = np.round(cloud * 2) / 2
        elif kind == 'duplicated':
            cloud[n // 2:] = cloud[:n - n // 2]
        want = oracle_fps(torch.from_numpy(cloud), 300).numpy()
        soa = np.ascontiguousarray(cloud.T)
        got, scratch = np.empty(300, np.int64), np.empty(n, np.float32)
        lib.pgn_fps_from(soa[0].ctypes.data, soa[1].ctypes.data, soa[2].ctypes.data, n, 300,
                         int(want[0]), got.ctypes.data, scratch.ctypes.data)
        np.testing.assert_array_equal(got, want, err_msg=f'{build}, {n} points, {kind}')


@pytest.mark.parametrize('build', sorted(KERNEL_BUILDS))
def test_fps_over_a_slab_ties_like_the_oracle(build: str, tmp_path: Path) -> None:
    # the encoder's FPS over points in buckets (pgn_slab.c; pgn_fps_in updates only the
    # buckets near each new point on AVX-512, elsewhere it ignores the slab), each build,
    # against the oracle: exact ties, every point taken (the distances fall to 0), blocks
    # past n
    lib = kernel_build(('pgn_geom.c', 'pgn_slab.c'), build, tmp_path,
                       ('-ffp-contract=off', '-fno-fast-math', '-fopenmp-simd'))
    ptr, i64 = ctypes.c_void_p, ctypes.c_int64
    lib.pgn_fps_in.argtypes = [ptr, ptr, ptr, ptr, i64, i64, ptr, ptr, ptr]
    lib.pgn_slab_build.argtypes = [ptr, ptr, ptr, i64, i64, ptr, ptr]
    lib.pgn_slab_floats.restype = i64
    lib.pgn_slab_floats.argtypes = [i64]
    slab = ctypes.create_string_buffer(256)
    for n, m, kind in ((1024, 512, 'normal'), (1000, 1000, 'grid'), (517, 517, 'duplicated'),
                       (1030, 700, 'normal'), (800, 400, 'grid')):
        cloud = _cloud(n, 9)
        if kind == 'grid':
            cloud = np.round(cloud * 2) / 2
        elif kind == 'duplicated':
            cloud[n // 2:] = cloud[:n - n // 2]
        cloud = np.ascontiguousarray(cloud, np.float32)
        want = oracle_fps(torch.from_numpy(cloud), m).numpy()
        soa = np.ascontiguousarray(cloud.T)
        buf = np.empty(lib.pgn_slab_floats(n), np.float32)
        built = lib.pgn_slab_build(soa[0].ctypes.data, soa[1].ctypes.data, soa[2].ctypes.data,
                                   n, 1, buf.ctypes.data, slab)
        assert bool(built) == build.startswith('avx512')
        for with_slab in (False, True) if built else (False,):
            got, scratch = np.empty(m, np.int64), np.empty(n, np.float32)
            lib.pgn_fps_in(cloud.ctypes.data, soa[0].ctypes.data, soa[1].ctypes.data,
                           soa[2].ctypes.data, n, m, got.ctypes.data, scratch.ctypes.data,
                           slab if with_slab else None)
            np.testing.assert_array_equal(got, want, err_msg=f'{build}, {n} points, {kind}, '
                                                             f'slab {with_slab}')


@pytest.mark.parametrize('build', sorted(KERNEL_BUILDS))
def test_every_simd_build_of_knn_ties_like_the_oracle(build: str, tmp_path: Path) -> None:
    # pgn_knn.c counts and splits on floats (portable, AVX2, AVX-512), pgn_knn16.c on 16-bit
    # codes (AVX-512 BW + VBMI2, 64 <= n): each build that this CPU runs, against the oracle's
    # stable sort, with exact ties, tails past the vector blocks, a middle past 32 keys
    # (duplicates) and centres whose k-th distances differ from their predecessor's guess
    lib = kernel_build(('pgn_knn.c', 'pgn_knn16.c', 'pgn_slab.c'), build, tmp_path,
                       ('-ffp-contract=off', '-fno-fast-math', '-fopenmp-simd'))
    ptr, i64 = ctypes.c_void_p, ctypes.c_int64
    lib.pgn_knn.argtypes = [ptr, ptr, ptr, i64, ptr, ptr, ptr, i64, i64, ptr, ptr, ptr,
                            ctypes.c_float]
    lib.pgn_knn_in.argtypes = [*lib.pgn_knn.argtypes, ptr]
    lib.pgn_slab_build.argtypes = [ptr, ptr, ptr, i64, i64, ptr, ptr]
    lib.pgn_slab_floats.restype = i64
    lib.pgn_slab_floats.argtypes = [i64]
    slab = ctypes.create_string_buffer(256)       # a pgn_slab (96 bytes on x86-64)
    rng = np.random.default_rng(3)
    for n, k, kind in ((1024, 120, 'normal'), (1000, 120, 'grid'), (517, 120, 'duplicated'),
                       (512, 200, 'normal'), (63, 20, 'normal'), (64, 63, 'grid'),
                       (100, 1, 'duplicated'), (2100, 7, 'normal'), (800, 120, 'duplicated')):
        cloud = _cloud(n, 8)
        if kind == 'grid':
            cloud = np.round(cloud * 2) / 2
        elif kind == 'duplicated':
            cloud[n // 2:] = cloud[:n - n // 2]
        cloud = cloud.astype(np.float32)
        # centres: cloud points (a distance of +0), others near and far
        centres = np.concatenate([cloud[rng.choice(n, 40)],
                                  rng.normal(0, 1.5, (24, 3)).astype(np.float32)])
        want = oracle_knn(torch.from_numpy(cloud), torch.from_numpy(centres), k).numpy()
        p, c = np.ascontiguousarray(cloud.T), np.ascontiguousarray(centres.T)
        nb = np.empty(len(centres) * k + 16, np.int32)
        dist, keys = np.empty(n, np.float32), np.empty(2 * n + 32, np.uint64)
        # the guess at the k-th distance (0: computed from the points) only steers the
        # counting: far too small or too large, the rows must not change
        # the points in buckets along an axis (AVX-512, n >= 6 k): a centre searches its slab
        # (the 16-bit codes' builds), or all points when fewer than k of them are near enough
        buf = np.empty(lib.pgn_slab_floats(n), np.float32)
        sorted_ = lib.pgn_slab_build(p[0].ctypes.data, p[1].ctypes.data, p[2].ctypes.data, n,
                                     k, buf.ctypes.data, slab)
        assert bool(sorted_) == (build.startswith('avx512') and n >= 6 * k)
        for guess in (0.0, 1e-6, 50.0):
            for with_slab in (False, True) if sorted_ else (False,):
                lib.pgn_knn_in(p[0].ctypes.data, p[1].ctypes.data, p[2].ctypes.data, n,
                               c[0].ctypes.data, c[1].ctypes.data, c[2].ctypes.data,
                               len(centres), k, nb.ctypes.data, dist.ctypes.data,
                               keys.ctypes.data, guess, slab if with_slab else None)
                rows = nb[:len(centres) * k].reshape(-1, k)
                np.testing.assert_array_equal(np.sort(rows, axis=1), np.sort(want, axis=1),
                                              err_msg=f'{build}, {n} points, k {k}, {kind}, '
                                                      f'guess {guess}, slab {with_slab}')
                if guess == 0.0 and not with_slab:
                    unsorted = rows.copy()
                elif guess == 0.0 and k > 1 and 'vbmi2' in build:
                    # the slab was searched (on 16-bit codes): its rows come in its order
                    assert not np.array_equal(rows, unsorted), f'{build}, {n}, {kind}'



def test_fps_start_is_geometric_so_order_does_not_matter() -> None:
    cloud = _cloud(3000, 4)
    perm = np.random.default_rng(1).permutation(len(cloud))
    a = resample(cloud, 1024, 'fps')
    b = resample(cloud[perm], 1024, 'fps')
    assert {tuple(p) for p in a} == {tuple(p) for p in b}


def test_random_resampling_is_seeded() -> None:
    cloud = _cloud(4000)
    np.testing.assert_array_equal(resample(cloud, 1024, 'random', 7),
                                  resample(cloud, 1024, 'random', 7))
    assert not np.array_equal(resample(cloud, 1024, 'random', 7),
                              resample(cloud, 1024, 'random', 8))


def test_huge_cloud_is_subsampled_before_fps() -> None:
    out = resample(_cloud(FPS_MAX_INPUT * 4), 1024, 'fps')
    assert out.shape == (1024, 3)


def test_unknown_method_is_rejected() -> None:
    with pytest.raises(ValueError, match='fps'):
        resample(_cloud(3000), 1024, 'grid')  # type: ignore[arg-type]


def test_normalize_puts_sensor_frame_cloud_in_unit_sphere() -> None:
    cloud = _cloud(1024) * 0.3 + np.array([4.0, -2.0, 0.7], dtype=np.float32)
    out = normalize(cloud)
    assert np.abs(out.mean(0)).max() < 1e-5
    assert abs(np.linalg.norm(out, axis=1).max() - 1.0) < 1e-5


def test_normalize_is_scale_and_translation_invariant() -> None:
    cloud = _cloud(1024)
    np.testing.assert_allclose(normalize(cloud), normalize(cloud * 2.5 + 3.0), atol=1e-5)


@pytest.mark.parametrize('cloud', [
    np.zeros((1, 3), np.float32),
    np.full((50, 3), 7.0, np.float32),
    np.stack([np.linspace(0, 1, 100)] * 3, 1).astype(np.float32),
])
def test_degenerate_clouds_prepare_to_finite_points(cloud: np.ndarray) -> None:
    out = prepare(cloud)
    assert out.shape == (1024, 3) and np.isfinite(out).all()


def _yaw(xyz: np.ndarray, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return (xyz @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float32).T).astype(np.float32)


def test_canonical_yaw_undoes_any_rotation_about_z() -> None:
    rng = np.random.default_rng(5)
    cloud = normalize(rng.normal(size=(1024, 3)) * np.array([3.0, 1.0, 0.5]) + np.array(
        [0.0, 0.0, 0.0]) + rng.exponential(size=(1024, 3)))
    ref = canonical_yaw(cloud)
    for angle in (0.3, 1.7, np.pi, 4.0):
        np.testing.assert_allclose(canonical_yaw(_yaw(cloud, angle)), ref, atol=1e-4)
    # heights untouched, only a rotation (+ reflection) of x-y
    np.testing.assert_array_equal(ref[:, 2], cloud[:, 2])
    np.testing.assert_allclose(np.linalg.norm(ref, axis=1), np.linalg.norm(cloud, axis=1),
                               atol=1e-5)


def _canonical_yaw_as_built(xyz: np.ndarray) -> np.ndarray:
    """canonical_yaw as the shipped banks were built: np.cov and x ** 3."""
    xy = xyz[:, :2].astype(np.float64)
    _, vecs = np.linalg.eigh(np.cov(xy.T))
    c, s = vecs[:, 1]
    xy = xy @ np.array([[c, -s], [s, c]])
    signs = np.sign((xy ** 3).mean(axis=0))
    signs[signs == 0] = 1.0
    out = xyz.copy()
    out[:, :2] = xy * signs
    return out.astype(np.float32)


def test_canonical_yaw_gives_the_frames_the_banks_were_built_in() -> None:
    # The fast third moment (|x|^3 with x's sign) must not move any cloud's frame, or the
    # shipped banks' entries and new queries would disagree: bit for bit, on clouds with
    # one and with both third moments near zero (mirror-symmetric in x, and in x and y).
    rng = np.random.default_rng(11)
    clouds = [normalize(rng.normal(size=(1024, 3)) * rng.uniform(0.3, 2.0, 3)
                        + rng.exponential(size=(1024, 3)) * rng.uniform(0, 1, 3))
              for _ in range(40)]
    half = rng.normal(size=(512, 3)) * np.array([2.0, 1.0, 0.5])
    mirror_x = np.concatenate([half, half * np.array([-1.0, 1.0, 1.0])])
    mirror_xy = np.concatenate([mirror_x, mirror_x * np.array([1.0, -1.0, 1.0])])
    clouds += [normalize(mirror_x), normalize(mirror_xy), _cloud(1024)]
    for cloud in clouds:
        np.testing.assert_array_equal(canonical_yaw(cloud), _canonical_yaw_as_built(cloud))


def test_prepare_yaw_align_only_when_asked() -> None:
    cloud = _cloud(2000)
    np.testing.assert_array_equal(prepare(cloud), normalize(resample(cloud, 1024)))
    assert not np.allclose(prepare(cloud, yaw_align=True), prepare(cloud))
    assert np.isfinite(prepare(np.zeros((3, 3), np.float32), yaw_align=True)).all()


def test_compiled_prepare_matches_its_numpy_forms(monkeypatch: pytest.MonkeyPatch) -> None:
    # With the kernels, prepare() normalises and yaw-aligns in C (pgn_prepare.c): normalize's
    # bits, the yaw within a float32 rounding and in the same frame (axis and signs), on
    # clouds with third moments near zero and on degenerate ones
    from point_gn_ros.core import sampling
    if sampling._compiled_prepare() is None:
        pytest.skip('compiled kernels unavailable: prepare() runs its numpy forms')
    rng = np.random.default_rng(12)
    half = rng.normal(size=(512, 3)) * np.array([2.0, 1.0, 0.5])
    mirror_x = np.concatenate([half, half * np.array([-1.0, 1.0, 1.0])])
    g = np.linspace(-1.0, 1.0, 32)
    square = np.concatenate([np.stack(np.meshgrid(g, g), -1).reshape(-1, 2),
                             np.zeros((1024, 1))], axis=1)
    line = np.linspace(-1.0, 1.0, 300)[:, None] * np.eye(3)[:, None, :]  # along x, y, z
    clouds = [rng.normal(size=(n, 3)) * rng.uniform(0.3, 2.0, 3) + rng.uniform(-5, 5, 3)
              for n in (700, 1024, 3000) for _ in range(10)]
    clouds += [mirror_x, mirror_x * np.array([1.0, -1.0, 1.0]) + mirror_x, square, *line,
               np.array([[1.5, -2.0, 3.0]]), np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]]),
               np.full((50, 3), 7.0), rng.normal(size=(2000, 3)) * 1e15]
    got = [(prepare(c.astype(np.float32)), prepare(c.astype(np.float32), yaw_align=True))
           for c in clouds]
    for cloud, (plain, yawed) in zip(clouds, got, strict=True):
        x = resample(cloud.astype(np.float32), 1024)
        np.testing.assert_array_equal(plain, normalize(x))
        ref = canonical_yaw(normalize(x))
        # an axis whose third moment is zero but for rounding (a cloud exactly symmetric
        # about it) may get either sign: the two sums round differently
        flip = np.where(np.abs((ref[:, :2].astype(np.float64) ** 3).mean(0)) < 1e-12, -1, 1)
        assert min(np.abs(yawed[:, :2] - ref[:, :2] * f).max()
                   for f in ([1, 1], [flip[0], 1], [1, flip[1]], flip)) <= 1e-6
        np.testing.assert_array_equal(yawed[:, 2], ref[:, 2])
    # and prepare() does not call the numpy forms at all
    def numpy_form(*_: object) -> np.ndarray:
        raise AssertionError('prepare() ran a numpy form')
    monkeypatch.setattr(sampling, 'normalize', numpy_form)
    monkeypatch.setattr(sampling, 'canonical_yaw', numpy_form)
    np.testing.assert_array_equal(prepare(clouds[0].astype(np.float32), yaw_align=True),
                                  got[0][1])


def test_compiled_canonical_order_and_neighbours_match_their_numpy_forms() -> None:
    # canonical_order: a radix sort against np.lexsort (ties and -0 against +0 keep their
    # input order); midpoint_neighbours: the float kNN then the float64 order against the
    # numpy form (float64 input takes it), with exact ties (grid, duplicates), near ties
    # (the fallback over every point), distances too small for float and large coordinates
    from point_gn_ros.core import sampling
    if sampling._compiled_prepare() is None:
        pytest.skip('compiled kernels unavailable: both run their numpy forms')
    rng = np.random.default_rng(21)
    for i in range(40):
        n = int(rng.integers(1, 1400))
        x = rng.normal(size=(n, 3)).astype(np.float32)
        if i % 4 == 1:
            x = np.round(x * 2) / 2
        elif i % 4 == 2:
            x[n // 2:] = x[:n - n // 2]
        elif i % 4 == 3:
            x[rng.random(x.shape) < 0.4] = 0.0
            x[rng.random(x.shape) < 0.4] = -0.0
        x = np.ascontiguousarray(x, dtype=np.float32)
        np.testing.assert_array_equal(sampling.canonical_order(x),
                                      np.lexsort((x[:, 2], x[:, 1], x[:, 0])), err_msg=str(i))
    g = np.arange(6, dtype=np.float32)
    grid = np.stack(np.meshgrid(g, g, g), -1).reshape(-1, 3)         # many exact ties
    near = grid + rng.normal(size=grid.shape).astype(np.float32) * 1e-7 * grid.max()
    clouds = [grid, near, np.concatenate([grid[:80], grid[:80]]),
              rng.normal(size=(300, 3)).astype(np.float32) * 1e-21,  # float squares underflow
              rng.normal(size=(300, 3)).astype(np.float32) * 1e17,
              rng.normal(size=(2, 3)).astype(np.float32)]
    # a point amid a circle: float distances tie where float64 ones do not (the fallback)
    t = rng.uniform(0, 2 * np.pi, 400)
    ring = np.concatenate([[[0.0, 0.0, 0.0]], np.c_[np.cos(t), np.sin(t), np.zeros(400)]])
    clouds += [ring.astype(np.float32)]
    clouds += [rng.normal(size=(n, 3)).astype(np.float32) for n in (17, 340, 1000)]
    for c in clouds:
        c = np.ascontiguousarray(c[sampling.canonical_order(c)], dtype=np.float32)
        for k in sorted({1, 2, 5, len(c) - 1}):
            if 1 <= k < len(c):
                np.testing.assert_array_equal(sampling.midpoint_neighbours(c, k),
                                              sampling.midpoint_neighbours(c.astype(np.float64),
                                                                           k),
                                              err_msg=f'{len(c)} points, k {k}')


@pytest.mark.parametrize('n_in', [2, 3, 16, 340, 1000, 1023])
def test_midpoint_fill_keeps_every_point_and_adds_midpoints_of_near_neighbours(n_in: int
                                                                               ) -> None:
    cloud = _cloud(n_in, 7) + 5.0
    out = resample(cloud, 1024, upsample='midpoint')
    assert out.shape == (1024, 3) and out.dtype == np.float32
    np.testing.assert_array_equal(out[:n_in], cloud[canonical_order(cloud)])
    # every new point is the midpoint of a point a and one of a's nearest few others b
    rounds = -(-(1024 - n_in) // n_in)
    order = np.argsort(((cloud[:, None, :] - cloud[None, :, :]) ** 2).sum(-1), axis=1)
    for m in out[n_in:]:
        other = 2 * m[None, :] - cloud                   # b for every choice of a
        gap = ((other[:, None, :] - cloud[None, :, :]) ** 2).sum(-1)
        a, b = np.unravel_index(np.argmin(gap), gap.shape)
        assert gap[a, b] < 1e-8 and a != b
        assert b in order[a, 1:min(rounds, n_in - 1) + 1] or a in order[b, 1:rounds + 1]


def test_midpoint_fill_stays_on_the_surface_and_spreads_its_last_round() -> None:
    rng = np.random.default_rng(3)
    plane = np.c_[rng.uniform(-1, 1, (400, 2)), np.zeros(400)].astype(np.float32)
    out = resample(plane, 1024, upsample='midpoint')
    assert np.all(out[:, 2] == 0)                       # a flat scan stays flat
    # the partial last round (1024 - 3 x 400 < 0: 224 of 400 points) is spread over the
    # cloud, not taken from one end of the (x, y, z) order
    last = out[400 + 400:]
    assert len(last) == 224 and last[:, 0].min() < -0.8 and last[:, 0].max() > 0.8


def test_midpoint_fill_is_order_free_and_leaves_dense_clouds_alone() -> None:
    cloud = _cloud(340, 9)
    perm = np.random.default_rng(2).permutation(len(cloud))
    np.testing.assert_array_equal(resample(cloud, 1024, upsample='midpoint'),
                                  resample(cloud[perm], 1024, upsample='midpoint'))
    dup = np.concatenate([cloud, cloud[:50]])           # exact duplicates are harmless
    assert np.isfinite(resample(dup, 1024, upsample='midpoint')).all()
    for n_in in (1024, 3000):
        dense = _cloud(n_in, 4)
        np.testing.assert_array_equal(resample(dense, 1024, upsample='midpoint'),
                                      resample(dense, 1024))
    np.testing.assert_array_equal(resample(cloud[:1], 1024, upsample='midpoint'),
                                  np.repeat(cloud[:1], 1024, axis=0))
    with pytest.raises(ValueError, match='upsample'):
        resample(cloud, 1024, upsample='cubic')  # type: ignore[arg-type]
    huge = np.full((20, 3), 3e38, np.float32) * np.linspace(0.9, 1, 20, dtype=np.float32)[:, None]
    assert np.isfinite(prepare(huge, upsample='midpoint')).all()    # no overflow to inf


def test_encoder_config_records_upsample_only_when_not_repeat() -> None:
    from point_gn_ros.core.config import EncoderConfig
    assert 'upsample' not in EncoderConfig().to_dict()   # old banks' metadata and cache keys
    cfg = EncoderConfig(upsample='midpoint')
    assert cfg.to_dict()['upsample'] == 'midpoint'
    assert EncoderConfig.from_dict(cfg.to_dict()) == cfg
    assert EncoderConfig.from_dict(EncoderConfig().to_dict()).upsample == 'repeat'
    with pytest.raises(ValueError, match='upsample'):
        EncoderConfig(upsample='cubic')
