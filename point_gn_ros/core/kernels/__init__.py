"""Compiled C kernels for the fast encoder: built with the system C compiler, cached on disk.

The sources (pgn_*.c, pgn_common.h) ship with the package; `load()` compiles
them on first use (about a second with gcc) into a per-user cache keyed by the
source text, the compiler, its flags and the CPU, then loads the shared library
with ctypes. ctypes releases the GIL during calls, so Python threads run
clouds in parallel. No network, no Python headers, no torch headers.

The stage loops have three builds, chosen at compile time by what -march=native enables:
AVX-512 (pgn_avx512.c, pgn_avx512_sep.c, pgn_avx512_lanes.c), AVX2 + FMA (pgn_avx2.c,
pgn_avx2_d18.c, pgn_avx2_lanes.c; CPUs without AVX-512) and portable C; `simd_width()` says
which one runs.

pgn_geom.c, pgn_slab.c, pgn_knn.c, pgn_knn16.c, pgn_project.c and pgn_prepare.c are compiled
without fast-math and with -ffp-contract=off (distances must round exactly like the oracle's;
an index row's projection must not depend on the rows beside it; prepare()'s normalisation
rounds like numpy's). The stage files (pgn_stage.c, pgn_plan.c, pgn_avx512.c,
pgn_avx512_sep.c, pgn_avx512_lanes.c, pgn_avx2.c, pgn_avx2_d18.c, pgn_avx2_lanes.c,
pgn_encode.c, pgn_phases.c) and pgn_search.c use -ffast-math (vectorised code, glibc's
libmvec); the two lanes files add -ffp-contract=off (their init rows must round a centre and
its neighbours alike). pgn_dots.c (the exact
vote's cosines) is built without fast-math and with -ffp-contract=off, so that a dot's
summation order is its source's in any batch.
pgn_head.c (a lone query's head, bank/lone.py: -inf marks absent classes), pgn_lone.c (a
lone cloud's helper thread) and pgn_peak.c (roofline micro-benchmarks) are built without
fast-math. The link step omits -ffast-math so that gcc does not add crtfastmath.o, which
would flush denormals to zero process-wide.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
from pathlib import Path
import platform
import shutil
import subprocess
import tempfile
import threading

import numpy as np

_SRC_DIR = Path(__file__).resolve().parent
_SOURCES = {'pgn_geom.c': ['-ffp-contract=off', '-fno-fast-math'],
            'pgn_knn.c': ['-ffp-contract=off', '-fno-fast-math'],
            # the kNN on 16-bit distance codes (AVX-512 BW and VBMI2)
            'pgn_knn16.c': ['-ffp-contract=off', '-fno-fast-math'],
            # slabs: a stage's points in buckets, for FPS and the kNN
            'pgn_slab.c': ['-ffp-contract=off', '-fno-fast-math'],
            'pgn_stage.c': ['-ffast-math'],
            'pgn_plan.c': ['-ffast-math'],  # a stage's kernel plan (separable, lanes)
            'pgn_avx512.c': ['-ffast-math'],
            'pgn_avx512_sep.c': ['-ffast-math'],  # the separable stages 2-4 on AVX-512
            # stage 1 with neighbours in the lanes; no contraction: its init_rows must
            # round a centre and its neighbours alike
            'pgn_avx512_lanes.c': ['-ffast-math', '-ffp-contract=off'],
            'pgn_avx2.c': ['-ffast-math'],  # AVX2 + FMA stage loops (CPUs without AVX-512)
            'pgn_avx2_d18.c': ['-ffast-math'],  # AVX2 stage 1 with derived Gaussians
            # AVX2 stage 1, neighbours in the lanes (no contraction: as pgn_avx512_lanes.c)
            'pgn_avx2_lanes.c': ['-ffast-math', '-ffp-contract=off'],
            'pgn_encode.c': ['-ffast-math'],
            'pgn_phases.c': ['-ffast-math'],  # the steps over a range of centres
            # a lone cloud's helper thread (no arithmetic: the chunks run in pgn_encode.c)
            'pgn_lone.c': ['-fno-fast-math'],
            'pgn_search.c': ['-ffast-math'],  # bank scans (bank/search.py)
            'pgn_scan4.c': ['-ffast-math'],  # the coarse pass over packed 4-bit codes
            # the exact vote's dot products: one summation order in any batch
            'pgn_dots.c': ['-fno-fast-math', '-ffp-contract=off'],
            # the index's projection: row results must not depend on the batch
            'pgn_project.c': ['-fno-fast-math', '-ffp-contract=off'],
            # prepare()'s normalisation and yaw alignment: numpy's operations as written
            'pgn_prepare.c': ['-fno-fast-math', '-ffp-contract=off'],
            # a lone query through a section's head: -inf marks absent classes
            'pgn_head.c': ['-fno-fast-math'],
            'pgn_peak.c': ['-fno-fast-math']}  # micro-benchmarks for the roofline table
# included by the C files: part of the snapshot and the cache key
_HEADERS = ('pgn_common.h', 'pgn_geom.h', 'pgn_knn.h', 'pgn_lone.h', 'pgn_phases.h')
_COMMON = ['-O3', '-fPIC', '-fopenmp-simd', '-std=gnu11']
ABI_VERSION = 3
_log = logging.getLogger(__name__)

_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_error: str | None = None


def cache_dir() -> Path:
    """Where built kernels live: $POINT_GN_KERNEL_CACHE, else ~/.cache/point_gn_ros/kernels."""
    env = os.environ.get('POINT_GN_KERNEL_CACHE')
    if env:
        return Path(env)
    base = os.environ.get('XDG_CACHE_HOME') or str(Path.home() / '.cache')
    return Path(base) / 'point_gn_ros' / 'kernels'


def _compiler() -> str | None:
    return os.environ.get('CC') or shutil.which('gcc') or shutil.which('cc')


def _arch_flags() -> list[str]:
    # -march=native is safe because the library is built on the machine that runs it
    # (the cache key includes the CPU description).
    return ['-march=native'] if platform.machine() in ('x86_64', 'AMD64', 'aarch64') else []


def _cpu_id() -> str:
    try:
        text = Path('/proc/cpuinfo').read_text()
    except OSError:
        return platform.processor()
    keep = [ln for ln in text.splitlines()
            if ln.split(':')[0].strip() in ('model name', 'flags', 'Features', 'CPU part')]
    return '\n'.join(sorted(set(keep)))


def _flags() -> list[str]:
    # POINT_GN_KERNEL_PROFILE=1 builds per-phase CPU timers (pgn_prof) for profiling.
    profile = ['-DPGN_PROFILE'] if os.environ.get('POINT_GN_KERNEL_PROFILE') else []
    return _COMMON + _arch_flags() + profile


# Build variants, best first: a compiler that rejects -march=native still gets a portable
# build (same results, slower).
_VARIANTS = ('native', 'portable')


def _variant_flags(variant: str) -> list[str]:
    return _flags() if variant == 'native' else [f for f in _flags() if f not in _arch_flags()]


def _sources() -> dict[str, bytes]:
    """One snapshot of the sources: what is hashed is exactly what is compiled."""
    return {name: (_SRC_DIR / name).read_bytes() for name in (*_SOURCES, *_HEADERS)}


def _key(cc: str, sources: dict[str, bytes]) -> str | None:
    h = hashlib.sha256()
    for name in sorted(sources):
        h.update(name.encode())
        h.update(sources[name])
        h.update(' '.join(_SOURCES.get(name, [])).encode())
    try:
        version = subprocess.run([cc, '--version'], capture_output=True, text=True,
                                 check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    h.update(' '.join(_flags() + _arch_flags()).encode())
    # the compiler as named too: a wrapper (CC=...) reports its compiler's version but may
    # build otherwise, and must not share that compiler's cached builds
    h.update(cc.encode())
    h.update(version.encode())
    h.update(_cpu_id().encode())
    return h.hexdigest()[:20]


def _compile(cc: str, sources: dict[str, bytes], variant: str, out: Path) -> None:
    flags = _variant_flags(variant)
    with tempfile.TemporaryDirectory(prefix='pgn_build_') as tmp:
        objs = []
        for name in _HEADERS:
            (Path(tmp) / name).write_bytes(sources[name])
        for name, extra in _SOURCES.items():
            src = Path(tmp) / name
            src.write_bytes(sources[name])
            obj = Path(tmp) / (name + '.o')
            subprocess.run([cc, *flags, *extra, '-c', str(src), '-o', str(obj)],
                           check=True, capture_output=True, text=True)
            objs.append(str(obj))
        tmp_lib = Path(tmp) / out.name
        subprocess.run([cc, '-shared', '-pthread', '-o', str(tmp_lib), *objs, '-lm'],
                       check=True, capture_output=True, text=True)
        out.parent.mkdir(parents=True, exist_ok=True)
        staged = out.with_name(f'{out.name}.{os.getpid()}.tmp')
        shutil.copyfile(tmp_lib, staged)
        os.replace(staged, out)  # atomic: concurrent builders never see half a file


def library_path(variant: str = 'native') -> Path | None:
    """Where the kernel library for these sources/compiler/CPU is (or would be) cached."""
    cc = _compiler()
    key = _key(cc, _sources()) if cc else None
    return None if key is None else cache_dir() / f'libpgn_{key}_{variant}.so'


def _find_or_build() -> tuple[Path, str]:
    """Best cached variant, else build one: (path, variant). Raises the last build error."""
    cc = _compiler()
    if cc is None:
        raise OSError('no C compiler (gcc/cc) found')
    sources = _sources()
    key = _key(cc, sources)
    if key is None:
        raise OSError(f'C compiler {cc} does not run')
    dirs = [cache_dir(), Path(tempfile.gettempdir()) / f'point_gn_ros_kernels_{os.getuid()}']
    last: Exception | None = None
    # The best variant already built wins, unless a better one may still be buildable.
    for variant in _VARIANTS:
        name = f'libpgn_{key}_{variant}.so'
        hit = next((d / name for d in dirs if (d / name).exists()), None)
        if hit is not None:
            return hit, variant
        if not any((d / (name + '.failed')).exists() for d in dirs):
            break  # not built yet and not known to fail: build it below
    for variant in _VARIANTS:
        name = f'libpgn_{key}_{variant}.so'
        if any((d / (name + '.failed')).exists() for d in dirs):
            continue
        for d in dirs:  # the cache, else a temp dir when the cache is not writable
            try:
                _compile(cc, sources, variant, d / name)
                return d / name, variant
            except subprocess.CalledProcessError as exc:
                last = exc
                try:  # remembered, so that every start does not retry (clear the cache to)
                    d.mkdir(parents=True, exist_ok=True)
                    (d / (name + '.failed')).write_text(f'{exc.cmd}\n{exc.stderr}')
                except OSError:
                    pass
                break
            except OSError as exc:
                last = exc
    if last is not None:
        raise last
    raise OSError(f'kernel build failed earlier; see {dirs[0]}/libpgn_{key}_*.failed '
                  '(delete them to retry)')


def _declare(lib: ctypes.CDLL) -> None:
    p, i64, f32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float
    lib.pgn_abi_version.restype = ctypes.c_int
    lib.pgn_simd_width.restype = ctypes.c_int
    lib.pgn_simd_width.argtypes = []
    lib.pgn_encode.restype = ctypes.c_int
    lib.pgn_encode.argtypes = [p, i64, i64, i64, i64, i64, f32, p, i64, p]
    lib.pgn_gelu.restype = None
    lib.pgn_gelu.argtypes = [p, i64]
    lib.pgn_encode_lone.restype = ctypes.c_int
    lib.pgn_encode_lone.argtypes = [p, i64, i64, i64, i64, f32, p, i64, p]
    lib.pgn_fps.restype = None
    lib.pgn_fps.argtypes = [p, p, p, p, i64, i64, p, p]
    lib.pgn_fps_from.restype = None
    lib.pgn_fps_from.argtypes = [p, p, p, i64, i64, i64, p, p]
    lib.pgn_knn.restype = None
    lib.pgn_knn.argtypes = [p, p, p, i64, p, p, p, i64, i64, p, p, p, ctypes.c_float]
    for name, args in (('pgn_peak_ops', [i64]), ('pgn_peak_exp', [i64]),
                       ('pgn_peak_read', [p, i64, i64])):
        getattr(lib, name).restype = ctypes.c_double
        getattr(lib, name).argtypes = args
    lib.pgn_scan_i8.restype = None
    lib.pgn_scan_i8.argtypes = [p, i64, i64, p, p]
    lib.pgn_top_m.restype = i64
    lib.pgn_top_m.argtypes = [p, i64, i64, p, p]
    lib.pgn_scan_f32.restype = None
    lib.pgn_scan_f32.argtypes = [p, i64, p, i64, p, p]
    lib.pgn_scan_i8_multi.restype = None
    lib.pgn_scan_i8_multi.argtypes = [p, i64, i64, p, i64, p]
    lib.pgn_scan_i4.restype = None
    lib.pgn_scan_i4.argtypes = [p, i64, i64, p, p]
    lib.pgn_scan_i4_multi.restype = None
    lib.pgn_scan_i4_multi.argtypes = [p, i64, i64, p, i64, p]
    lib.pgn_dots_f32.restype = None
    lib.pgn_dots_f32.argtypes = [p, i64, i64, p, i64, p]
    lib.pgn_dots_i8.restype = None
    lib.pgn_dots_i8.argtypes = [p, p, i64, i64, p, i64, p]
    lib.pgn_dots_i4.restype = None
    lib.pgn_dots_i4.argtypes = [p, p, i64, i64, p, p]
    lib.pgn_normalize.restype = None
    lib.pgn_normalize.argtypes = [p, i64, p]
    lib.pgn_canonical_yaw.restype = None
    lib.pgn_canonical_yaw.argtypes = [p, i64, p, p, p]
    lib.pgn_canonical_order.restype = ctypes.c_int
    lib.pgn_canonical_order.argtypes = [p, i64, p]
    lib.pgn_midpoint_neighbours.restype = ctypes.c_int
    lib.pgn_midpoint_neighbours.argtypes = [p, i64, i64, p]
    lib.pgn_project_f32.restype = None
    lib.pgn_project_f32.argtypes = [p, i64, i64, p, i64, p]
    f64 = ctypes.c_double
    lib.pgn_head_embed.restype = None
    lib.pgn_head_embed.argtypes = [p, i64, p, p, p, i64, p, p, p, p]
    lib.pgn_head_linear.restype = None
    lib.pgn_head_linear.argtypes = [p, i64, p, i64, p, p]
    lib.pgn_head_finish.restype = ctypes.c_int
    lib.pgn_head_finish.argtypes = [p, p, i64, i64, p, f64, p, f64, f64, p, i64, p, p,
                                    f64, f64, p, p, p]


def load() -> ctypes.CDLL | None:
    """The compiled kernels (built on first call), or None when no C compiler works.

    `last_error()` says why it is None. Thread-safe; builds at most once per process.
    """
    global _lib, _error
    with _lock:
        if _lib is not None or _error is not None:
            return _lib
        if os.environ.get('POINT_GN_NO_KERNELS'):
            _error = 'disabled by POINT_GN_NO_KERNELS'
            return None
        try:
            path, variant = _find_or_build()
            if variant != 'native':
                _log.warning('point_gn: using the %s kernel build (slower): %s', variant, path)
            lib = ctypes.CDLL(str(path))
            _declare(lib)
            if lib.pgn_abi_version() != ABI_VERSION:
                raise OSError(f'kernel ABI {lib.pgn_abi_version()} != {ABI_VERSION}')
            _lib = lib
        except (OSError, subprocess.CalledProcessError) as exc:
            detail = getattr(exc, 'stderr', '') or ''
            _error = f'{type(exc).__name__}: {exc} {detail}'.strip()
        return _lib


def simd_width() -> int:
    """Lanes of the stage kernels in use: 16 (AVX-512), 8 (AVX2 + FMA), 0 (portable C)."""
    return int(_require().pgn_simd_width())


def cpu_flags() -> set[str]:
    """The CPU's feature flags from /proc/cpuinfo (empty where there is none)."""
    try:
        text = Path('/proc/cpuinfo').read_text()
    except OSError:
        return set()
    for line in text.splitlines():
        if line.split(':')[0].strip() in ('flags', 'Features'):
            return set(line.split(':', 1)[1].split())
    return set()


def last_error() -> str | None:
    """Why `load()` returned None (None when it did not)."""
    return _error


def _require() -> ctypes.CDLL:
    lib = load()
    if lib is None:
        raise RuntimeError(f'compiled kernels unavailable: {last_error()}')
    return lib


def bank_dots(feats: np.ndarray, queries: np.ndarray, norms: np.ndarray | None = None
              ) -> np.ndarray:
    """Dot products of every query with every bank row: (N, d), (B, d) -> (B, N) float32.

    feats: C-contiguous float32 rows, or int8 codes with norms (N,) float32 (the rows are
    then codes / norms, a bank stored as int8 or int4; not copied). pgn_dots.c: the bank is
    read once per call, and each query's row of the result is the same bit for bit whatever
    the batch.
    """
    lib = _require()
    codes = feats.dtype == np.int8
    if not feats.flags.c_contiguous or feats.dtype != (np.int8 if codes else np.float32):
        raise ValueError('bank rows must be C-contiguous float32 or int8')
    if codes and (norms is None or norms.dtype != np.float32 or norms.shape != feats.shape[:1]
                  or not norms.flags.c_contiguous):
        raise ValueError('int8 bank codes need their (N,) float32 norms')
    q = np.ascontiguousarray(queries, dtype=np.float32)
    if q.ndim != 2 or q.shape[1] != feats.shape[1]:
        raise ValueError(f'queries must be (B, {feats.shape[1]}), got {q.shape}')
    out = np.empty((q.shape[0], feats.shape[0]), np.float32)
    if codes:
        lib.pgn_dots_i8(feats.ctypes.data, norms.ctypes.data, feats.shape[0], feats.shape[1],
                        q.ctypes.data, q.shape[0], out.ctypes.data)
    else:
        lib.pgn_dots_f32(feats.ctypes.data, feats.shape[0], feats.shape[1], q.ctypes.data,
                         q.shape[0], out.ctypes.data)
    return out


def pack_nibbles(codes: np.ndarray) -> np.ndarray:
    """(N, d) int8 codes in [-8, 7], d % 16 == 0 -> (N, d / 2) uint8 for `lone_dots_i4`.

    Byte b of each group of 16 codes holds code b (low nibble) and code 8 + b (high), + 8:
    one 8-byte load gives two 8-lane steps of pgn_dots.c in index order. (The index's coarse
    codes pair slices of 64 for integer dot products, and bank files pair neighbours:
    bank/index_basis.py, bank/quant.py.)
    """
    n, d = codes.shape
    if d % 16 or codes.dtype != np.int8:
        raise ValueError(f'nibble packing needs int8 codes, 16 a group, got {codes.dtype} x {d}')
    u = (codes.astype(np.int16) + 8).astype(np.uint8).reshape(n, d // 16, 2, 8)
    return np.ascontiguousarray((u[:, :, 0] | (u[:, :, 1] << 4)).reshape(n, d // 2))


def lone_dots_i4(packed: np.ndarray, norms: np.ndarray, query: np.ndarray) -> np.ndarray:
    """One query's cosines to rows codes / norms from `pack_nibbles(codes)`: (d,) -> (N,).

    Bit for bit `bank_dots(codes, query[None], norms)[0]`, from half its bytes.
    """
    lib = _require()
    n, half = packed.shape
    q = np.ascontiguousarray(query, dtype=np.float32)
    if (packed.dtype != np.uint8 or not packed.flags.c_contiguous or q.shape != (2 * half,)
            or norms.dtype != np.float32 or norms.shape != (n,) or not norms.flags.c_contiguous):
        raise ValueError(f'packed rows {packed.dtype} {packed.shape}, norms {norms.dtype} '
                         f'{norms.shape} and query {q.shape} do not fit')
    out = np.empty(n, np.float32)
    lib.pgn_dots_i4(packed.ctypes.data, norms.ctypes.data, n, 2 * half, q.ctypes.data,
                    out.ctypes.data)
    return out


def fps_indices(xyz: np.ndarray, m: int) -> np.ndarray:
    """The encoder's FPS (start: farthest from torch's centroid): (N, 3) float32 -> (m,) int64."""
    lib = _require()
    xyz = np.ascontiguousarray(xyz, dtype=np.float32)
    n = xyz.shape[0]
    if not 1 <= m <= n:
        raise ValueError(f'need 1 <= m <= N, got m={m}, N={n}')
    soa = np.ascontiguousarray(xyz.T)
    idx = np.empty(m, dtype=np.int64)
    scratch = np.empty(n, dtype=np.float32)
    lib.pgn_fps(xyz.ctypes.data, soa[0].ctypes.data, soa[1].ctypes.data, soa[2].ctypes.data,
                n, m, idx.ctypes.data, scratch.ctypes.data)
    return idx


def fps_from(xyz: np.ndarray, m: int, start: int) -> np.ndarray:
    """FPS from a given start index: xyz (N, 3) float32 -> (m,) int64, ties to the lowest index.

    The same loop as sampling.fps_indices' numpy version, compiled (releases the GIL).
    """
    lib = _require()
    xyz = np.ascontiguousarray(xyz, dtype=np.float32)
    n = xyz.shape[0]
    if not (1 <= m <= n and 0 <= start < n):
        raise ValueError(f'need 1 <= m <= N and 0 <= start < N, got m={m}, start={start}, N={n}')
    soa = np.ascontiguousarray(xyz.T)
    idx = np.empty(m, dtype=np.int64)
    scratch = np.empty(n, dtype=np.float32)
    lib.pgn_fps_from(soa[0].ctypes.data, soa[1].ctypes.data, soa[2].ctypes.data, n, m, start,
                     idx.ctypes.data, scratch.ctypes.data)
    return idx


def knn_indices(xyz: np.ndarray, centres: np.ndarray, k: int) -> np.ndarray:
    """The encoder's kNN: xyz (N, 3), centres (S, 3) -> (S, min(k, N)) int64.

    Each row sorted by (distance, index) like the oracle's stable sort.
    """
    lib = _require()
    xyz = np.ascontiguousarray(xyz, dtype=np.float32)
    centres = np.ascontiguousarray(centres, dtype=np.float32)
    n, s = xyz.shape[0], centres.shape[0]
    k = min(k, n)
    p = np.ascontiguousarray(xyz.T)
    c = np.ascontiguousarray(centres.T)
    nb = np.empty(s * k + 16, dtype=np.int32)
    dist = np.empty(n, dtype=np.float32)
    keys = np.empty(2 * n + 32, dtype=np.uint64)
    lib.pgn_knn(p[0].ctypes.data, p[1].ctypes.data, p[2].ctypes.data, n, c[0].ctypes.data,
                c[1].ctypes.data, c[2].ctypes.data, s, k, nb.ctypes.data, dist.ctypes.data,
                keys.ctypes.data, 0.0)
    out = nb[:s * k].reshape(s, k).astype(np.int64)
    # order each row like the oracle: by distance, then index
    d = centres[:, None, :] - xyz[out]
    dd = d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]
    order = np.lexsort((out, dd), axis=-1)
    return np.take_along_axis(out, order, axis=1)
