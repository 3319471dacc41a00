"""Fast encoder (point_gn_ros.core.encoder) against the oracle (encoder_naive).

The oracle is slow (~0.25 s a cloud), so each oracle result is computed once per
session and shared by the tests that need it.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import numpy as np
import pytest
import torch

from point_gn_ros.core import kernels
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.core.encoder import PointGNEncoder
from point_gn_ros.core.encoder_naive import NaiveEncoder, fps, knn
from point_gn_ros.core.sampling import prepare

from conftest import MODELNET, require_shared
REL_TOL = 1e-4  # max|fast - naive| <= REL_TOL * max|naive|, per cloud


def _kernels_or_skip() -> None:
    # Skip only where there is no C compiler at all; a compiler that fails must fail here,
    # not hide behind the (correct but ~100x slower) torch fallback.
    if kernels.load() is None:
        if kernels._compiler() is None or os.environ.get('POINT_GN_NO_KERNELS'):
            pytest.skip(f'compiled kernels unavailable: {kernels.last_error()}')
        pytest.fail(f'a C compiler exists but the kernels did not build: {kernels.last_error()}')


@pytest.fixture(scope='session')
def real_clouds() -> np.ndarray:
    """Six prepared ModelNet40 test clouds of different classes: (6, 1024, 3) float32."""
    import h5py

    root = require_shared(MODELNET)
    with h5py.File(root / 'ply_data_test0.h5', 'r') as f:
        labels = f['label'][:].reshape(-1)
        pick = [int(np.flatnonzero(labels == c)[0]) for c in (0, 2, 8, 17, 30, 35)]
        raw = f['data'][sorted(pick)].astype(np.float32)
    return np.stack([prepare(c) for c in raw])


def _degenerate() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(7)
    line = np.zeros((1024, 3), np.float32)
    line[:, 0] = np.linspace(-1, 1, 1024, dtype=np.float32)
    g = np.linspace(-1, 1, 32, dtype=np.float32)
    plane = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    plane = np.concatenate([plane, np.zeros((1024, 1), np.float32)], axis=1)
    repeated = np.repeat(rng.standard_normal((8, 3)).astype(np.float32) * 0.5, 128, axis=0)
    lattice = (rng.integers(-3, 4, (1024, 3)) / 3.0).astype(np.float32)
    return {'all_equal': np.zeros((1024, 3), np.float32), 'line': line, 'plane': plane,
            'repeated_points': repeated, 'integer_lattice': lattice}


@pytest.fixture(scope='session')
def encoder() -> PointGNEncoder:
    enc = PointGNEncoder()
    enc.warmup()
    return enc


@pytest.fixture(scope='session')
def naive_real(real_clouds: np.ndarray) -> np.ndarray:
    return NaiveEncoder().encode(torch.from_numpy(real_clouds)).numpy()


def _assert_close(fast: np.ndarray, naive: np.ndarray, what: str) -> None:
    assert np.isfinite(fast).all(), f'{what}: non-finite features'
    for i, (a, b) in enumerate(zip(fast, naive, strict=True)):
        scale = max(float(np.abs(b).max()), 1e-12)
        err = float(np.abs(a - b).max())
        assert err <= REL_TOL * scale, f'{what}[{i}]: max diff {err:.3g} vs scale {scale:.3g}'


def test_contract_shape_dtype(encoder: PointGNEncoder) -> None:
    cfg = EncoderConfig()
    out = encoder.encode(torch.zeros(3, cfg.num_points, 3))
    assert out.shape == (3, cfg.feature_dim) and out.dtype == torch.float32
    assert out.device.type == 'cpu'
    assert encoder.encode(torch.zeros(0, cfg.num_points, 3)).shape == (0, cfg.feature_dim)
    with pytest.raises(ValueError):
        encoder.encode(torch.zeros(2, cfg.num_points - 1, 3))
    with pytest.raises(ValueError):
        encoder.encode(torch.full((1, cfg.num_points, 3), float('nan')))


def test_auto_backend_is_kernel_on_cpu(encoder: PointGNEncoder) -> None:
    _kernels_or_skip()
    assert encoder.backend == 'kernel'


def test_agrees_with_oracle_on_modelnet(encoder: PointGNEncoder, real_clouds: np.ndarray,
                                        naive_real: np.ndarray) -> None:
    fast = encoder.encode(torch.from_numpy(real_clouds)).numpy()
    _assert_close(fast, naive_real, 'modelnet')


def test_torch_backend_agrees_with_oracle(real_clouds: np.ndarray,
                                          naive_real: np.ndarray) -> None:
    # The torch back-end (CUDA path, and the fallback without a C compiler) on the CPU.
    enc = PointGNEncoder(backend='torch')
    fast = enc.encode(torch.from_numpy(real_clouds[:2])).numpy()
    _assert_close(fast, naive_real[:2], 'torch backend')


def test_same_fps_and_knn_as_oracle(real_clouds: np.ndarray) -> None:
    _kernels_or_skip()
    clouds = list(real_clouds[:3]) + list(_degenerate().values())
    for xyz in clouds:
        x = torch.from_numpy(np.ascontiguousarray(xyz))
        for n, m in ((1024, 512), (512, 256), (128, 64)):
            assert np.array_equal(kernels.fps_indices(xyz[:n], m), fps(x[:n], m).numpy())
        centres = x[fps(x, 512)]
        for n, k in ((1024, 120), (256, 120), (128, 120)):
            expect = knn(x[:n], centres[:64], k).numpy()
            got = kernels.knn_indices(xyz[:n], centres[:64].numpy(), k)
            assert np.array_equal(got, expect), f'kNN differs for n={n}, k={k}'


def test_batch_invariance(encoder: PointGNEncoder, real_clouds: np.ndarray) -> None:
    clouds = torch.from_numpy(real_clouds)
    alone = torch.cat([encoder.encode(clouds[i:i + 1]) for i in range(len(clouds))])
    together = encoder.encode(clouds)
    mixed = encoder.encode(torch.cat([clouds.flip(0), clouds[:2]]))
    assert float((alone - together).abs().max()) <= 1e-5
    assert float((alone.flip(0) - mixed[:len(clouds)]).abs().max()) <= 1e-5
    # thread count must not matter either
    single = PointGNEncoder(threads=1, backend=encoder.backend)
    assert float((single.encode(clouds) - together).abs().max()) <= 1e-5


def test_batch_sizes_up_to_256(encoder: PointGNEncoder, real_clouds: np.ndarray) -> None:
    _kernels_or_skip()  # the torch fallback would take minutes
    clouds = torch.from_numpy(real_clouds)
    big = clouds.repeat(43, 1, 1)[:256]
    out = encoder.encode(big)
    assert out.shape == (256, EncoderConfig().feature_dim)
    ref = encoder.encode(clouds)
    assert float((out[:len(clouds)] - ref).abs().max()) <= 1e-5
    assert float((out[-1] - ref[255 % len(clouds)]).abs().max()) <= 1e-5


def test_deterministic(encoder: PointGNEncoder, real_clouds: np.ndarray) -> None:
    clouds = torch.from_numpy(real_clouds[:3])
    first = encoder.encode(clouds)
    for _ in range(2):
        assert torch.equal(encoder.encode(clouds), first)


@pytest.mark.parametrize('name', sorted(_degenerate()))
def test_degenerate_clouds_match_oracle(encoder: PointGNEncoder, name: str) -> None:
    xyz = _degenerate()[name][None]
    fast = encoder.encode(torch.from_numpy(xyz)).numpy()
    naive = NaiveEncoder().encode(torch.from_numpy(xyz)).numpy()
    _assert_close(fast, naive, name)


@pytest.mark.parametrize('cfg', [
    # widths that are not multiples of 16, k above a late stage's point count
    EncoderConfig(num_points=128, init_dim=6, stages=3, k=40, sigma=0.3),
    EncoderConfig(num_points=100, init_dim=9, stages=3, k=17, sigma=0.25),
    # sharp Gaussians: separable evaluation near its float-range limit (sigma 0.1) and
    # refused for it (sigma 0.05)
    EncoderConfig(num_points=256, init_dim=48, stages=2, k=60, sigma=0.1),
    EncoderConfig(num_points=256, init_dim=48, stages=2, k=60, sigma=0.05),
    # wide Gaussians: the chained block factors (sep_t.C) over four blocks an axis, and
    # near the edge chain_ok allows (|q| (sqrt(87 / |q|) - 2)^2 = 30.3 against 30)
    EncoderConfig(num_points=256, init_dim=48, stages=2, k=60, sigma=0.6),
    EncoderConfig(num_points=256, init_dim=48, stages=2, k=60, sigma=0.37),
    # stage 1's rows from the points (AVX-512's lanes_init_t): two blocks an axis for the
    # initial Gaussians (sigma 0.2), and 10 of them an axis
    EncoderConfig(num_points=512, init_dim=27, stages=2, k=60, sigma=0.2),
    EncoderConfig(num_points=256, init_dim=30, stages=2, k=50, sigma=0.5),
], ids=['small', 'odd_sizes', 'sigma_0.1', 'sigma_0.05', 'sigma_0.6', 'sigma_0.37',
        'init_two_blocks', 'init_30'])
def test_other_configs_match_oracle(cfg: EncoderConfig) -> None:
    _kernels_or_skip()
    rng = np.random.default_rng(3)
    raw = [rng.standard_normal((700, 3)).astype(np.float32) * np.float32([1, 0.5, 0.2])
           for _ in range(2)]
    xyz = torch.from_numpy(np.stack([prepare(c, n=cfg.num_points) for c in raw]))
    fast = PointGNEncoder(cfg).encode(xyz).numpy()
    _assert_close(fast, NaiveEncoder(cfg).encode(xyz).numpy(), 'config')


def test_lone_cloud_on_two_threads_is_bit_identical(real_clouds: np.ndarray) -> None:
    # a lone cloud may run on the caller plus a helper thread (stage chunks claimed from
    # a counter): the split must never change a bit, for any configuration path
    _kernels_or_skip()
    for cfg in (EncoderConfig(), EncoderConfig(num_points=256, init_dim=48, stages=2, k=60,
                                               sigma=0.05)):
        xyz = torch.from_numpy(np.stack([prepare(c, n=cfg.num_points) for c in real_clouds]))
        one, two = PointGNEncoder(cfg, lone_threads=1), PointGNEncoder(cfg, lone_threads=2)
        for i in range(len(xyz)):
            assert torch.equal(one.encode(xyz[i:i + 1]), two.encode(xyz[i:i + 1]))
        assert torch.equal(two.encode(xyz[:1]), one.encode(xyz)[:1])  # and batches
    with pytest.raises(ValueError):
        PointGNEncoder(lone_threads=3)


@pytest.mark.filterwarnings('ignore:.*multi-threaded.*fork:DeprecationWarning')
def test_lone_clouds_from_several_threads_and_a_forked_child(real_clouds: np.ndarray) -> None:
    # the process keeps one helper thread for lone clouds: callers racing for it (one gets
    # it, the others run on their own thread) and a child forked after it started (which
    # has no helper thread until it starts its own) must all get the one-thread answers
    _kernels_or_skip()
    cfg = EncoderConfig()
    xyz = torch.from_numpy(np.stack([prepare(c, n=cfg.num_points) for c in real_clouds]))
    expected = PointGNEncoder(cfg, lone_threads=1).encode(xyz)
    two = PointGNEncoder(cfg, lone_threads=2)
    two.encode(xyz[:1])                                   # the helper thread now runs
    got: dict[tuple[int, int], torch.Tensor] = {}

    def caller(t: int) -> None:
        for rep in range(3):
            for i in range(len(xyz)):
                got[t, rep * len(xyz) + i] = two.encode(xyz[i:i + 1])

    threads = [threading.Thread(target=caller, args=(t,)) for t in range(3)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert len(got) == 3 * 3 * len(xyz)
    for (_, j), row in got.items():
        assert torch.equal(row, expected[j % len(xyz):j % len(xyz) + 1])
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:                                          # the child: exit code = verdict
        ok = all(torch.equal(two.encode(xyz[i:i + 1]), expected[i:i + 1])
                 for i in range(len(xyz)))
        os.write(write, b'1' if ok else b'0')
        os._exit(0)
    os.close(write)
    _, status = os.waitpid(pid, 0)
    assert os.read(read, 1) == b'1' and os.waitstatus_to_exitcode(status) == 0
    os.close(read)


def test_simd_build_matches_the_cpu() -> None:
    # the stage loops are chosen at build time by what -march=native enables: AVX-512
    # (16 lanes), AVX2 + FMA (8 lanes, CPUs without AVX-512) or portable C
    _kernels_or_skip()
    flags = kernels.cpu_flags()
    if not flags:
        pytest.skip('no CPU flags in /proc/cpuinfo: cannot say which build should run')
    if 'avx512f' in flags:
        expected = 16
    elif {'avx2', 'fma'} <= flags:
        expected = 8
    else:
        expected = 0
    assert kernels.simd_width() == expected


def test_kernel_gelu_matches_erf_gelu() -> None:
    # the stages' gelu (AVX-512: a piecewise polynomial of erf; elsewhere libmvec's erff)
    # against torch's exact-erf gelu in double, over the whole float range: within about an
    # ULP of erf near 1 times |x| / 2, exactly 0 far below 0, exactly x far above
    _kernels_or_skip()
    x = np.concatenate([np.linspace(-12.0, 12.0, 240_001),
                        [0.0, -0.0, 1e-30, -1e-30, 5.54, -5.54, 5.55, -5.55, 100.0, -100.0,
                         1e6, -1e6, 3e38, -3e38]]).astype(np.float32)
    y = x.copy()
    kernels.load().pgn_gelu(y.ctypes.data, len(y))
    ref = torch.nn.functional.gelu(torch.from_numpy(x).double()).numpy()
    err = np.abs(y.astype(np.float64) - ref)
    assert np.all(err <= 1.5e-7 * np.maximum(1.0, np.abs(x))), float((err / np.maximum(
        1.0, np.abs(x))).max())
    far = np.abs(x) >= 6.0
    assert np.all(y[far & (x < 0)] == 0.0) and np.all(y[far & (x > 0)] == x[far & (x > 0)])
    assert np.all(y[x == 0.0] == 0.0)


def test_avx2_path_agrees_with_oracle(encoder: PointGNEncoder, real_clouds: np.ndarray,
                                      naive_real: np.ndarray) -> None:
    # The AVX2 + FMA kernels (pgn_avx2.c, pgn_avx2_d18.c: stage 1, separable stages, feature
    # std; AVX2 FPS and kNN in pgn_geom.c) run only on CPUs with AVX2 and without AVX-512;
    # there the other oracle tests of this file exercise them too.
    _kernels_or_skip()
    if kernels.simd_width() != 8:
        pytest.skip(f'AVX2 path not built here (simd width {kernels.simd_width()}: '
                    'the CPU lacks AVX2 + FMA or has AVX-512)')
    fast = encoder.encode(torch.from_numpy(real_clouds)).numpy()
    _assert_close(fast, naive_real, 'avx2 modelnet')
    # stage 1 in registers needs 16 < D <= 32: D = 18, 21 (derived Gaussians, no tail
    # vector) and 30 (direct Gaussians) besides the default 27 (derived, with the tail)
    for init_dim in (18, 21, 30):
        cfg = EncoderConfig(num_points=256, init_dim=init_dim, stages=2, k=40, sigma=0.4)
        xyz = torch.from_numpy(np.stack([prepare(c, n=cfg.num_points) for c in real_clouds[:2]]))
        _assert_close(PointGNEncoder(cfg).encode(xyz).numpy(),
                      NaiveEncoder(cfg).encode(xyz).numpy(), f'avx2 init_dim {init_dim}')


@pytest.mark.parametrize('init_dim,k,sigma', [
    (27, 120, 0.4),   # the default stage 1: one block per axis, 8 groups of 16
    (18, 40, 0.4),    # 12 Gaussians per axis, a partial last group
    (21, 10, 0.4),    # fewer neighbours than lanes: one partial group
    (21, 150, 0.4),   # past 128 neighbours: two chunks of groups (AVX2: three of 64)
    (30, 37, 0.25),
    (27, 60, 0.1),    # sharp Gaussians: 5 blocks per axis
    (27, 60, 0.05),   # sharper: a block per Gaussian
    (27, 60, 0.02),   # too sharp for any block: the channels-in-lanes kernel instead
])
def test_stage1_with_neighbours_in_the_lanes_agrees_with_oracle(
        real_clouds: np.ndarray, init_dim: int, k: int, sigma: float) -> None:
    # AVX-512 and AVX2 builds run stage 1 (16 < D <= 32) with 16 or 8 neighbours in the
    # lanes and the Gaussians of an axis as running products (pgn_avx512_lanes.c,
    # pgn_avx2_lanes.c); the blocks per axis depend on sigma (lanes_range_ok)
    _kernels_or_skip()
    if kernels.simd_width() == 0:
        pytest.skip('the portable build runs stage 1 with channels in the lanes')
    cfg = EncoderConfig(num_points=256, init_dim=init_dim, stages=2, k=k, sigma=sigma)
    xyz = torch.from_numpy(np.stack([prepare(c, n=cfg.num_points) for c in real_clouds[:3]]))
    _assert_close(PointGNEncoder(cfg).encode(xyz).numpy(),
                  NaiveEncoder(cfg).encode(xyz).numpy(), f'lanes {init_dim}/{k}/{sigma}')


def test_the_lone_cloud_helper_is_kept_off_its_callers_cpu(real_clouds: np.ndarray) -> None:
    # woken on its caller's CPU, the helper waited behind the busy caller for up to a
    # scheduler tick (~3 ms): each lone cloud pins it to the process's other CPUs
    _kernels_or_skip()
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else []
    if len(cpus) < 2 or not Path('/proc/self/task').is_dir():
        pytest.skip('needs Linux (/proc, sched_setaffinity) and two usable CPUs')
    cfg = EncoderConfig()
    xyz = torch.from_numpy(prepare(real_clouds[0], n=cfg.num_points)[None])
    two = PointGNEncoder(cfg, lone_threads=2)

    def helper_cpus() -> set[int]:
        for task in Path('/proc/self/task').iterdir():
            if (task / 'comm').read_text().strip() == 'pgn_lone':
                return os.sched_getaffinity(int(task.name))
        raise AssertionError('no pgn_lone thread')

    seen = {}

    def caller(cpu: int) -> None:
        os.sched_setaffinity(0, {cpu})              # this thread only: runs on `cpu` now
        two.encode(xyz)
        seen[cpu] = helper_cpus()

    for cpu in cpus[:2]:
        th = threading.Thread(target=caller, args=(cpu,))
        th.start()
        th.join()
    for cpu in cpus[:2]:
        assert seen[cpu] == set(cpus) - {cpu}


def test_batch_workers_are_named_for_the_os(real_clouds: np.ndarray) -> None:
    # `top -H` on a robot tells the encoder's workers from the node's other threads
    _kernels_or_skip()
    if not Path('/proc/self/task').is_dir():
        pytest.skip('needs Linux (/proc/self/task/*/comm)')
    cfg = EncoderConfig()
    xyz = torch.from_numpy(np.stack([prepare(c, n=cfg.num_points) for c in real_clouds[:4]]))
    encoder = PointGNEncoder(cfg, threads=2)
    encoder.encode(xyz)
    names = {(task / 'comm').read_text().strip() for task in Path('/proc/self/task').iterdir()}
    encoder.close()
    assert {'point_gn_enc_0', 'point_gn_enc_1'} <= names


def test_encoding_started_ahead_gives_the_same_bits(encoder: PointGNEncoder,
                                                    real_clouds: np.ndarray) -> None:
    # the node starts a batch's encoding on the pool and collects it later (encode_later)
    clouds = torch.from_numpy(real_clouds)
    later = encoder.encode_later(clouds)
    other = encoder.encode(clouds[:2])          # the pool serves another call meanwhile
    assert torch.equal(later(), encoder.encode(clouds))
    assert torch.equal(other, encoder.encode(clouds[:2]))
