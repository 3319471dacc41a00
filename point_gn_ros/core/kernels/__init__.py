"""Compiled C kernels: built with the system C compiler, cached on disk, loaded with ctypes.

The sources ship with the package, in folders by subsystem (kernels/README.md names each
file and variant): encoder/ (the Point-GN encoder and what feeds it: FPS, kNN, prepare()),
bank/ (bank scans, the index's projection and coarse pass, the compiled head) and bench/
(micro-benchmarks: a library of their own, `load_bench()`, never loaded by the product).
`load()` compiles encoder/ and bank/ on first use (about a second with gcc) into a per-user
cache keyed by the source text, the compiler, its flags and the CPU. ctypes releases the
GIL during calls, so Python threads run clouds in parallel. No network, no Python headers.

`SOURCE_FLAGS` is the one table of compile flags. The encoder's stage kernels have one
build per ISA that -march=native enables (AVX-512, else AVX2 + FMA, else portable C);
encoder/pgn_dispatch.c maps ISA x variant to each stage's aggregation function, and
`dispatch_table()` lists it. The link step omits -ffast-math so that gcc does not add
crtfastmath.o, which would flush denormals to zero process-wide.
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass
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

# Flag sets, by the invariant each keeps.
# vectorised loops and glibc's libmvec; every sum's order is still fixed by the source
_FAST = ('-ffast-math',)
# as _FAST, and no contraction: a neighbour-lanes kernel's init rows round a centre and its
# neighbours alike
_FAST_UNCONTRACTED = ('-ffast-math', '-ffp-contract=off')
# every operation rounds as written (no reassociation, no FMA contraction): distances like
# the oracle's, a row's dots and projection the same bits in any batch, prepare() like numpy
_EXACT = ('-fno-fast-math', '-ffp-contract=off')
# no reassociation (the helper thread runs chunks with its caller's FP control word; the
# head's sums in double; the micro-benchmarks' timed chains must not be merged)
_STRICT = ('-fno-fast-math',)

# Every C file of the product library (path under kernels/) -> its flags beyond _COMMON.
SOURCE_FLAGS: dict[str, tuple[str, ...]] = {
    'encoder/pgn_encode.c': _FAST,            # one cloud through the stages; entry points
    'encoder/pgn_steps.c': _FAST,             # the steps over a range of a stage's centres
    'encoder/pgn_dispatch.c': _FAST,          # ISA x variant -> aggregation function
    'encoder/pgn_stage_plan.c': _FAST,        # a stage's separable / neighbour-lanes plan
    'encoder/pgn_stage_portable.c': _FAST,    # direct and separable aggregation, portable C
    'encoder/pgn_avx512.c': _FAST,            # narrow aggregation, feature std (AVX-512)
    'encoder/pgn_avx512_separable.c': _FAST,
    'encoder/pgn_avx512_neighbour_lanes.c': _FAST_UNCONTRACTED,
    'encoder/pgn_avx2.c': _FAST,              # narrow, separable, feature std (AVX2 + FMA)
    'encoder/pgn_avx2_narrow_derived.c': _FAST,
    'encoder/pgn_avx2_neighbour_lanes.c': _FAST_UNCONTRACTED,
    'encoder/pgn_helper.c': _STRICT,          # the helper thread of a one-cloud batch
    'encoder/pgn_geom.c': _EXACT,             # centroid, FPS
    'encoder/pgn_knn.c': _EXACT,              # kNN on float distances; entry points
    'encoder/pgn_knn_codes16.c': _EXACT,      # kNN on 16-bit distance codes (AVX-512 VBMI2)
    'encoder/pgn_slab.c': _EXACT,             # a stage's points in buckets along one axis
    'encoder/pgn_prepare.c': _EXACT,          # prepare()'s normalisation and yaw alignment
    'bank/pgn_search.c': _FAST,               # int8 coarse pass, top-m, float32 rescoring
    'bank/pgn_scan_i4.c': _FAST,              # the coarse pass over packed 4-bit codes
    'bank/pgn_dots.c': _EXACT,                # the exact vote's dot products
    'bank/pgn_project.c': _EXACT,             # the index's row-wise projection
    'bank/pgn_head.c': _STRICT,               # one query through a section's head
}
# The micro-benchmarks' library (`load_bench`): never part of the product library.
BENCH_FLAGS: dict[str, tuple[str, ...]] = {'bench/pgn_peak.c': _STRICT}
# included by the C files: part of the snapshot and the cache key
_HEADERS = ('encoder/pgn_common.h', 'encoder/pgn_geom.h', 'encoder/pgn_knn.h',
            'encoder/pgn_helper.h', 'encoder/pgn_steps.h')
_COMMON = ['-O3', '-fPIC', '-fopenmp-simd', '-std=gnu11']
ABI_VERSION = 3
_log = logging.getLogger(__name__)

_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_error: str | None = None
_bench: ctypes.CDLL | None = None


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


def _sources(files: dict[str, tuple[str, ...]]) -> dict[str, bytes]:
    """One snapshot of a library's sources: what is hashed is exactly what is compiled."""
    return {name: (_SRC_DIR / name).read_bytes() for name in (*files, *_HEADERS)}


def _key(cc: str, files: dict[str, tuple[str, ...]], sources: dict[str, bytes]) -> str | None:
    h = hashlib.sha256()
    for name in sorted(sources):
        h.update(name.encode())
        h.update(sources[name])
        h.update(' '.join(files.get(name, ())).encode())
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


def _compile(cc: str, files: dict[str, tuple[str, ...]], sources: dict[str, bytes],
             variant: str, out: Path) -> None:
    flags = _variant_flags(variant)
    with tempfile.TemporaryDirectory(prefix='pgn_build_') as tmp:
        for name, data in sources.items():  # the folders as in the package: includes resolve
            (Path(tmp) / name).parent.mkdir(parents=True, exist_ok=True)
            (Path(tmp) / name).write_bytes(data)
        objs = []
        for name, extra in files.items():
            obj = Path(tmp) / (name + '.o')
            subprocess.run([cc, *flags, *extra, '-c', str(Path(tmp) / name), '-o', str(obj)],
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
    """Where the product kernel library for these sources/compiler/CPU is (or would be)."""
    cc = _compiler()
    key = _key(cc, SOURCE_FLAGS, _sources(SOURCE_FLAGS)) if cc else None
    return None if key is None else cache_dir() / f'libpgn_{key}_{variant}.so'


def _find_or_build(stem: str, files: dict[str, tuple[str, ...]]) -> tuple[Path, str]:
    """Best cached variant of library `stem`, else build one: (path, variant).

    Raises the last build error.
    """
    cc = _compiler()
    if cc is None:
        raise OSError('no C compiler (gcc/cc) found')
    sources = _sources(files)
    key = _key(cc, files, sources)
    if key is None:
        raise OSError(f'C compiler {cc} does not run')
    dirs = [cache_dir(), Path(tempfile.gettempdir()) / f'point_gn_ros_kernels_{os.getuid()}']
    last: Exception | None = None
    # The best variant already built wins, unless a better one may still be buildable.
    for variant in _VARIANTS:
        name = f'{stem}_{key}_{variant}.so'
        hit = next((d / name for d in dirs if (d / name).exists()), None)
        if hit is not None:
            return hit, variant
        if not any((d / (name + '.failed')).exists() for d in dirs):
            break  # not built yet and not known to fail: build it below
    for variant in _VARIANTS:
        name = f'{stem}_{key}_{variant}.so'
        if any((d / (name + '.failed')).exists() for d in dirs):
            continue
        for d in dirs:  # the cache, else a temp dir when the cache is not writable
            try:
                _compile(cc, files, sources, variant, d / name)
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
    raise OSError(f'kernel build failed earlier; see {dirs[0]}/{stem}_{key}_*.failed '
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
    lib.pgn_encode_with_helper.restype = ctypes.c_int
    lib.pgn_encode_with_helper.argtypes = [p, i64, i64, i64, i64, f32, p, i64, p]
    lib.pgn_stage_variants.restype = ctypes.c_int
    lib.pgn_stage_variants.argtypes = [i64, i64, f32, p]
    lib.pgn_build_isa.restype = ctypes.c_char_p
    lib.pgn_build_isa.argtypes = []
    lib.pgn_dispatch_size.restype = ctypes.c_int
    lib.pgn_dispatch_size.argtypes = []
    cpp = ctypes.POINTER(ctypes.c_char_p)
    lib.pgn_dispatch_entry.restype = ctypes.c_int
    lib.pgn_dispatch_entry.argtypes = [ctypes.c_int, cpp, cpp, cpp]
    lib.pgn_variant_name.restype = ctypes.c_char_p
    lib.pgn_variant_name.argtypes = [ctypes.c_int]
    lib.pgn_fps.restype = None
    lib.pgn_fps.argtypes = [p, p, p, p, i64, i64, p, p]
    lib.pgn_fps_from.restype = None
    lib.pgn_fps_from.argtypes = [p, p, p, i64, i64, i64, p, p]
    lib.pgn_knn.restype = None
    lib.pgn_knn.argtypes = [p, p, p, i64, p, p, p, i64, i64, p, p, p, ctypes.c_float]
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
    """The product kernels (encoder/, bank/; built on first call), or None without them.

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
            path, variant = _find_or_build('libpgn', SOURCE_FLAGS)
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


def load_bench() -> ctypes.CDLL:
    """The micro-benchmarks (bench/pgn_peak.c: the roofline's peaks), built on first call.

    Raises RuntimeError when they cannot be built (they are for `point_gn bench` only).
    """
    global _bench
    with _lock:
        if _bench is None:
            try:
                path, _variant = _find_or_build('libpgn_bench', BENCH_FLAGS)
            except (OSError, subprocess.CalledProcessError) as exc:
                detail = getattr(exc, 'stderr', '') or ''
                raise RuntimeError(f'bench kernels unavailable: {exc} {detail}'.strip()) from exc
            lib = ctypes.CDLL(str(path))
            for name, args in (('pgn_peak_ops', [ctypes.c_int64]),
                               ('pgn_peak_exp', [ctypes.c_int64]),
                               ('pgn_peak_read', [ctypes.c_void_p, ctypes.c_int64,
                                                  ctypes.c_int64])):
                getattr(lib, name).restype = ctypes.c_double
                getattr(lib, name).argtypes = args
            _bench = lib
        return _bench


@dataclass(frozen=True)
class KernelEntry:
    """One entry of the encoder's dispatch table (encoder/pgn_dispatch.c).

    available: this build holds its function; else `reason` says which ISA is missing.
    """

    isa: str                # avx512, avx2, portable
    variant: str            # direct, separable, narrow, narrow_derived, neighbour_lanes
    needs: frozenset[str]   # CPU flags (/proc/cpuinfo names) its code uses
    available: bool
    reason: str | None


def build_isa() -> str:
    """The ISA the loaded build's stage kernels target: avx512, avx2 or portable."""
    return _require().pgn_build_isa().decode()


def dispatch_table() -> list[KernelEntry]:
    """The encoder's ISA x variant table as this machine's build holds it."""
    lib = _require()
    built, cpu = lib.pgn_build_isa().decode(), cpu_flags()
    out = []
    for i in range(lib.pgn_dispatch_size()):
        isa, variant, needs = ctypes.c_char_p(), ctypes.c_char_p(), ctypes.c_char_p()
        ok = lib.pgn_dispatch_entry(i, ctypes.byref(isa), ctypes.byref(variant),
                                    ctypes.byref(needs)) == 1
        need = frozenset(needs.value.decode().split())
        reason = None
        if not ok:
            missing = sorted(need - cpu)
            if missing:
                reason = f'this CPU lacks {" ".join(missing)}'
            elif isa.value.decode() != built:
                reason = (f"this build targets {built}: -march=native builds one ISA's "
                          'stage kernels, the widest the CPU has')
            else:
                reason = f'compiled out of this {built} build (a PGN_NO_* flag)'
        out.append(KernelEntry(isa.value.decode(), variant.value.decode(), need, ok, reason))
    return out


def stage_variants(init_dim: int, stages: int, sigma: float) -> list[str]:
    """The aggregation variant each encoder stage runs in this build: (stages,) names.

    Fixed by the stage's width and sigma, whatever the cloud (encoder/pgn_encode.c).
    """
    lib = _require()
    codes = np.empty(stages, np.int32)
    if lib.pgn_stage_variants(init_dim, stages, sigma, codes.ctypes.data):
        raise MemoryError('pgn_stage_variants')
    return [lib.pgn_variant_name(int(c)).decode() for c in codes]


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
    """(N, d) int8 codes in [-8, 7], d % 16 == 0 -> (N, d / 2) uint8 for `packed_dots_i4`.

    Byte b of each group of 16 codes holds code b (low nibble) and code 8 + b (high), + 8:
    one 8-byte load gives two 8-lane steps of pgn_dots.c in index order. (The index's coarse
    codes pair slices of 64 for integer dot products, and bank files pair neighbours:
    bank/index.py, bank/store.py.)
    """
    n, d = codes.shape
    if d % 16 or codes.dtype != np.int8:
        raise ValueError(f'nibble packing needs int8 codes, 16 a group, got {codes.dtype} x {d}')
    u = (codes.astype(np.int16) + 8).astype(np.uint8).reshape(n, d // 16, 2, 8)
    return np.ascontiguousarray((u[:, :, 0] | (u[:, :, 1] << 4)).reshape(n, d // 2))


def packed_dots_i4(packed: np.ndarray, norms: np.ndarray, query: np.ndarray) -> np.ndarray:
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
