"""The encoder's dispatch table (core/kernels/encoder/pgn_dispatch.c): ISA x variant."""

from __future__ import annotations

import itertools
import os

import numpy as np
import pytest
import torch

from point_gn_ros.core import kernels
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.core.encoder import PointGNEncoder
from point_gn_ros.core.encoder_naive import NaiveEncoder
from point_gn_ros.core.sampling import prepare

ISAS = ('avx512', 'avx2', 'portable')
VARIANTS = ('direct', 'separable', 'narrow', 'narrow_derived', 'neighbour_lanes')


@pytest.fixture(scope='module')
def table() -> list[kernels.KernelEntry]:
    if kernels.load() is None:
        if kernels._compiler() is None or os.environ.get('POINT_GN_NO_KERNELS'):
            pytest.skip(f'compiled kernels unavailable: {kernels.last_error()}')
        pytest.fail(f'a C compiler exists but the kernels did not build: {kernels.last_error()}')
    return kernels.dispatch_table()


def test_every_entry_loads_or_says_which_isa_it_lacks(table: list[kernels.KernelEntry]) -> None:
    built, cpu = kernels.build_isa(), kernels.cpu_flags()
    assert built in ISAS
    assert {e.isa for e in table} == set(ISAS) and {e.variant for e in table} == set(VARIANTS)
    assert len({(e.isa, e.variant) for e in table}) == len(table), 'one entry per ISA x variant'
    for e in table:
        if e.available:
            # only this build's ISA and the portable fallback are compiled, and their code
            # runs here: the CPU has every flag it uses
            assert e.isa in (built, 'portable'), e
            assert e.needs <= cpu, e
            assert e.reason is None
        else:
            assert e.isa != 'portable', f'portable C builds everywhere: {e}'
            missing = e.needs - cpu
            # an ISA reason: a CPU flag this machine lacks, or another ISA than the build's
            if missing:
                assert all(flag in e.reason for flag in missing), e
            else:
                assert e.isa != built and built in e.reason, e
    # a default build (no PGN_NO_* flags) holds every entry of its own ISA
    assert all(e.available for e in table if e.isa in (built, 'portable'))


def test_simd_width_agrees_with_the_build_isa(table: list[kernels.KernelEntry]) -> None:
    assert kernels.simd_width() == {'avx512': 16, 'avx2': 8, 'portable': 0}[kernels.build_isa()]


def test_the_default_encoder_runs_the_variants_the_readme_names(
        table: list[kernels.KernelEntry]) -> None:
    cfg = EncoderConfig()
    got = kernels.stage_variants(cfg.init_dim, cfg.stages, cfg.sigma)
    first = 'separable' if kernels.build_isa() == 'portable' else 'neighbour_lanes'
    assert got == [first] + ['separable'] * (cfg.stages - 1)


def test_every_variant_of_this_build_runs_and_agrees_with_the_oracle(
        table: list[kernels.KernelEntry]) -> None:
    # each variant the build holds for its ISA is the choice of some stage width and sigma
    # (kernels.stage_variants); an encoder that reaches it matches the oracle
    built = kernels.build_isa()
    want = {e.variant for e in table if e.isa == built}
    reached: dict[str, EncoderConfig] = {}
    for init_dim, sigma in itertools.product((18, 21, 24, 27, 30), (0.4, 0.1, 0.02, 0.01)):
        cfg = EncoderConfig(num_points=256, init_dim=init_dim, stages=2, k=24, sigma=sigma)
        for v in kernels.stage_variants(cfg.init_dim, cfg.stages, cfg.sigma):
            reached.setdefault(v, cfg)
    assert want <= set(reached), f'variants no configuration reaches: {want - set(reached)}'
    rng = np.random.default_rng(3)
    for v in sorted(want):
        cfg = reached[v]
        xyz = np.stack([prepare(rng.standard_normal((400, 3)).astype(np.float32),
                                n=cfg.num_points) for _ in range(2)])
        fast = PointGNEncoder(cfg).encode(torch.from_numpy(xyz)).numpy()
        naive = NaiveEncoder(cfg).encode(torch.from_numpy(xyz)).numpy()
        for a, b in zip(fast, naive, strict=True):
            scale = float(np.abs(b).max())
            assert float(np.abs(a - b).max()) <= 1e-4 * scale, (v, cfg)
