"""The coarse pass over packed 4-bit codes (core/kernels/bank/pgn_scan_i4.c, bank/index.py).

The kernel's integers must equal the plain product of the unpacked codes with the query in
every build: the one -march=native picks here, and the AVX2, AVX-512 without VNNI and
portable paths compiled from the same file (each run where this CPU can execute it), since
CI machines differ in which one they take.
"""

from __future__ import annotations

import ctypes
from pathlib import Path

from conftest import KERNEL_BUILDS, kernel_build
import numpy as np
import pytest

from point_gn_ros.bank.index import pack_codes, unpack_codes
from point_gn_ros.core import kernels

# widths: one 16-byte chunk, a 48-byte one, 2 full chunks, 64 + 64 + 16 (the scan
# section's 288), 4 full chunks, 5 (more than a batch's split-nibble blocks take), and
# 2,080 (beyond the SIMD paths' 2,048: the plain loop)
_WIDTHS = (32, 96, 256, 288, 512, 640, 2080)


def _cases(rng: np.random.Generator, r: int, n: int = 301, nq: int = 5):
    codes = rng.integers(-7, 8, (n, r)).astype(np.int8)
    codes[0] = 7
    codes[1] = -7                                   # the extremes of both nibbles
    q = rng.integers(-127, 128, (nq, r)).astype(np.int8)
    q[0] = 127
    q[1] = -127
    return codes, q, q.astype(np.int64) @ codes.astype(np.int64).T


def _check(lib, r: int, seed: int) -> None:
    codes, q, ref = _cases(np.random.default_rng(seed), r)
    packed = pack_codes(codes)
    assert packed.shape == (len(codes), r // 2) and packed.dtype == np.uint8
    one = np.empty(len(codes), np.int32)
    for b in range(len(q)):
        lib.pgn_scan_i4(packed.ctypes.data, len(codes), r, q[b].ctypes.data, one.ctypes.data)
        assert np.array_equal(one, ref[b]), (r, b)
    for nq in (1, 2, len(q)):
        out = np.empty((nq, len(codes)), np.int32)
        lib.pgn_scan_i4_multi(packed.ctypes.data, len(codes), r, q.ctypes.data, nq,
                              out.ctypes.data)
        assert np.array_equal(out, ref[:nq]), (r, nq)
    # a slice of the rows: nothing read past the last row (the prefetches stay inside)
    part = np.empty(7, np.int32)
    lib.pgn_scan_i4(packed[-7:].ctypes.data, 7, r, q[2].ctypes.data, part.ctypes.data)
    assert np.array_equal(part, ref[2, -7:])


@pytest.mark.parametrize('r', _WIDTHS)
def test_pack_codes_round_trip(r: int) -> None:
    codes = np.random.default_rng(r).integers(-8, 8, (9, r)).astype(np.int8)
    assert np.array_equal(unpack_codes(pack_codes(codes), r), codes)
    with pytest.raises(ValueError, match='multiple of 32'):
        pack_codes(codes[:, :r - 16])


@pytest.mark.parametrize('r', _WIDTHS)
def test_scan_i4_equals_the_unpacked_product(r: int) -> None:
    lib = kernels.load()
    if lib is None:
        pytest.skip(f'compiled kernels unavailable: {kernels.last_error()}')
    _check(lib, r, seed=r)


@pytest.mark.parametrize('build', list(KERNEL_BUILDS))
def test_every_simd_path_equals_the_plain_loop(build: str, tmp_path: Path) -> None:
    lib = kernel_build('bank/pgn_scan_i4.c', build, tmp_path)
    p, i64 = ctypes.c_void_p, ctypes.c_int64
    lib.pgn_scan_i4.restype = lib.pgn_scan_i4_multi.restype = None
    lib.pgn_scan_i4.argtypes = [p, i64, i64, p, p]
    lib.pgn_scan_i4_multi.argtypes = [p, i64, i64, p, i64, p]
    for r in _WIDTHS:
        _check(lib, r, seed=r + 1)
