"""Per-phase CPU time of two or more kernel builds, measured in ONE process, interleaved.

On a shared machine a before/after comparison taken in two runs mostly measures the load
change between them. This script builds each variant's kernel library (instrumented with
-DPGN_PROFILE, the same per-phase timers as `point_gn bench --profile`) into a temp dir,
loads all of them side by side (ctypes keeps their symbols apart) and times them in
alternation on the same synthetic clouds: thread CPU time, one thread, minimum over
repeats. It also reports each variant's largest relative feature difference to the first.

    python benchmarks/kernel_ab.py --variant before=git:HEAD --variant after=tree \
        --variant after-nosep=tree:-DPGN_NO_SEPARABLE_AVX2 --repeats 7

A variant is NAME=tree[:FLAGS] (the working tree's kernels) or NAME=git:REV[:FLAGS] (the
kernels of a commit, read with `git show`); FLAGS are extra compiler flags, comma separated.

--threads 2 runs each variant on two threads at once instead (half the clouds each, as a
batch on both vCPUs): wall ms a cloud and process CPU ms a cloud, best of the repeats, no
per-phase split (the phase timers are shared).
"""

from __future__ import annotations

import argparse
import ast
import ctypes
from pathlib import Path
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

from point_gn_ros.commands.bench_cmd import PROFILE_SLOTS, synthetic_clouds
from point_gn_ros.core import kernels
from point_gn_ros.core.encoder import PointGNEncoder

_KDIR = 'point_gn_ros/core/kernels'


def _git(*args: str) -> bytes:
    return subprocess.run(['git', *args], check=True, capture_output=True).stdout


def _snapshot(spec: str) -> tuple[dict[str, bytes], dict[str, list[str]]]:
    """Product kernel sources (*.c, *.h; bench/ left out) of the tree or of a git revision.

    Keyed by their paths under kernels/, with each C file's flags as that revision builds it.
    """
    if spec == 'tree':
        names = [str(p.relative_to(_KDIR)) for p in Path(_KDIR).rglob('*')
                 if p.suffix in ('.c', '.h')]
        sources = {n: (Path(_KDIR) / n).read_bytes() for n in names}
        init = (Path(_KDIR) / '__init__.py').read_text()
    else:
        rev = spec.removeprefix('git:')
        names = _git('ls-tree', '-r', '--name-only', f'{rev}:{_KDIR}').decode().split()
        sources = {n: _git('show', f'{rev}:{_KDIR}/{n}') for n in names
                   if n.endswith(('.c', '.h'))}
        init = _git('show', f'{rev}:{_KDIR}/__init__.py').decode()
    sources = {n: b for n, b in sources.items() if not n.startswith('bench/')}
    return sources, _flags_of(init)


def _flags_of(init: str) -> dict[str, list[str]]:
    """Per-file flags from a revision's kernels/__init__.py.

    Its SOURCE_FLAGS (flag sets by name), or in revisions before the subsystem folders its
    literal _SOURCES dict.
    """
    tree = ast.parse(init)
    consts: dict[str, list[str]] = {}
    for node in tree.body:
        if not isinstance(node, (ast.Assign, ast.AnnAssign)):
            continue
        target = node.targets[0] if isinstance(node, ast.Assign) else node.target
        if not isinstance(target, ast.Name) or node.value is None:
            continue
        if target.id in ('SOURCE_FLAGS', '_SOURCES') and isinstance(node.value, ast.Dict):
            return {ast.literal_eval(k): (consts[v.id] if isinstance(v, ast.Name)
                                          else list(ast.literal_eval(v)))
                    for k, v in zip(node.value.keys, node.value.values, strict=True)}
        try:
            consts[target.id] = list(ast.literal_eval(node.value))
        except (ValueError, TypeError):
            pass
    raise SystemExit('no SOURCE_FLAGS or _SOURCES in kernels/__init__.py')


def _build(snapshot: tuple[dict[str, bytes], dict[str, list[str]]], extra: list[str],
           out_dir: Path) -> Path:
    """Compile like kernels._compile (native variant, per-file flags) plus PGN_PROFILE."""
    sources, per_file = snapshot
    cc = kernels._compiler()
    if cc is None:
        raise SystemExit('no C compiler')
    flags = [*kernels._COMMON, *kernels._arch_flags(), '-DPGN_PROFILE', *extra]
    for name, data in sources.items():
        (out_dir / name).parent.mkdir(parents=True, exist_ok=True)
        (out_dir / name).write_bytes(data)
    objs = []
    for name in sorted(sources):
        if not name.endswith('.c'):
            continue
        obj = out_dir / (name + '.o')
        subprocess.run([cc, *flags, *per_file[name], '-c', str(out_dir / name), '-o', str(obj)],
                       check=True)
        objs.append(str(obj))
    lib = out_dir / 'libpgn_ab.so'
    subprocess.run([cc, '-shared', '-pthread', '-o', str(lib), *objs, '-lm'], check=True)
    return lib


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--variant', action='append', required=True,
                    help='NAME=tree[:FLAGS] or NAME=git:REV[:FLAGS]')
    ap.add_argument('--clouds', type=int, default=32)
    ap.add_argument('--repeats', type=int, default=7)
    ap.add_argument('--threads', type=int, default=1, choices=(1, 2))
    args = ap.parse_args(argv)

    enc = PointGNEncoder(threads=1)
    cfg = enc.cfg
    cents = enc._centres
    clouds = np.ascontiguousarray(synthetic_clouds(args.clouds, cfg.num_points, seed=5),
                                  dtype=np.float32)
    libs = {}
    with tempfile.TemporaryDirectory(prefix='pgn_ab_') as tmp:
        for i, v in enumerate(args.variant):
            name, spec = v.split('=', 1)
            parts = spec.split(':')
            nsrc = 1 if parts[0] == 'tree' else 2
            src, fl = ':'.join(parts[:nsrc]), ':'.join(parts[nsrc:])
            d = Path(tmp) / str(i)
            d.mkdir()
            lib = ctypes.CDLL(str(_build(_snapshot(src), [f for f in fl.split(',') if f], d)))
            lib.pgn_encode.restype = ctypes.c_int
            p, i64, f32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float
            lib.pgn_encode.argtypes = [p, i64, i64, i64, i64, i64, f32, p, i64, p]
            width = lib.pgn_simd_width() if hasattr(lib, 'pgn_simd_width') else -1
            libs[name] = (lib, (ctypes.c_double * 16).in_dll(lib, 'pgn_prof'), width)
        outs = {n: np.zeros((len(clouds), cfg.feature_dim), np.float32) for n in libs}
        if args.threads == 2:
            return _two_threads(libs, clouds, cfg, cents, outs, args.repeats)
        best = {n: None for n in libs}
        for _ in range(args.repeats):
            for n, (lib, prof, _w) in libs.items():
                for s in range(16):
                    prof[s] = 0.0
                t0 = time.thread_time()
                rc = lib.pgn_encode(clouds.ctypes.data, len(clouds), cfg.num_points,
                                    cfg.init_dim, cfg.stages, cfg.k, cfg.sigma,
                                    cents.ctypes.data, cfg.feature_dim, outs[n].ctypes.data)
                total = time.thread_time() - t0
                if rc:
                    raise MemoryError(n)
                got = np.array([total] + [prof[s] for s in range(16)]) / len(clouds)
                best[n] = got if best[n] is None else np.minimum(best[n], got)
    names = list(libs)
    print(f'phase (CPU ms per cloud, 1 thread, min of {args.repeats})'
          + ''.join(f' | {n} (w{libs[n][2]})' for n in names))
    for slot, phase in PROFILE_SLOTS.items():
        print(f'{phase:45s}' + ''.join(f' | {best[n][slot + 1] * 1e3:8.3f}' for n in names))
    print(f'{"encoder, one cloud, all phases":45s}'
          + ''.join(f' | {best[n][0] * 1e3:8.3f}' for n in names))
    _print_agreement(outs, names)
    return 0


def _print_agreement(outs: dict, names: list) -> None:
    """Each variant's largest feature difference to the first."""
    ref = outs[names[0]]
    scale = np.maximum(np.abs(ref), 1e-6)
    for n in names[1:]:
        rel = np.abs(outs[n] - ref) / scale
        norm = np.linalg.norm(outs[n] - ref, axis=1) / np.linalg.norm(ref, axis=1)
        print(f'{n} vs {names[0]}: max elementwise relative difference {rel.max():.2e}, '
              f'max per-cloud relative L2 difference {norm.max():.2e}')


def _two_threads(libs: dict, clouds: np.ndarray, cfg, cents: np.ndarray, outs: dict,
                 repeats: int) -> int:
    """Each variant on two threads at once, alternating: best wall and CPU a cloud."""
    half = len(clouds) // 2
    best = {n: (float('inf'), float('inf')) for n in libs}
    for _ in range(repeats):
        for n, (lib, _prof, _w) in libs.items():
            def run(a: int, b: int, lib=lib, out=outs[n]) -> None:
                lib.pgn_encode(clouds[a:].ctypes.data, b - a, cfg.num_points, cfg.init_dim,
                               cfg.stages, cfg.k, cfg.sigma, cents.ctypes.data,
                               cfg.feature_dim, out[a:].ctypes.data)
            threads = [threading.Thread(target=run, args=(0, half)),
                       threading.Thread(target=run, args=(half, len(clouds)))]
            t0, c0 = time.perf_counter(), time.process_time()
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            wall = (time.perf_counter() - t0) / len(clouds)
            cpu = (time.process_time() - c0) / len(clouds)
            best[n] = (min(best[n][0], wall), min(best[n][1], cpu))
    print(f'two threads at once, {len(clouds)} clouds, best of {repeats}')
    for n, (wall, cpu) in best.items():
        print(f'{n:12s} wall {wall * 1e3:.3f} ms a cloud ({1 / wall:.0f} clouds/s), '
              f'process CPU {cpu * 1e3:.3f} ms a cloud')
    _print_agreement(outs, list(libs))
    return 0


if __name__ == '__main__':
    sys.exit(main())
