"""`point_gn bench`: encoder, resampling and classifier timings on this machine.

Every figure is the median of several repeats (the development machines are
shared, so single runs are noisy). The naive oracle is timed in the same run so
the fast encoder's speed-up is measured, not remembered.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
import json
import statistics
import sys
import time
from typing import Any

# The roofline family (--profile) and the synthetic inputs live beside this module.
from point_gn_ros.commands.bench_inputs import synthetic_bank, synthetic_clouds
from point_gn_ros.commands.bench_roofline import PROFILE_SLOTS, Row, profile_rows


__all__ = ['PROFILE_SLOTS', 'Row', 'TABLE_HEADER', 'classifier_rows', 'encoder_rows',
           'format_rows', 'node_rows', 'profile_rows', 'register', 'resample_rows',
           'synthetic_bank', 'synthetic_clouds']


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser('bench', help='time the encoder, resampling and classifier')
    p.add_argument('--quick', action='store_true',
                   help='smoke run: fewer clouds and repeats, small inputs only (~20 s)')
    p.add_argument('--json', action='store_true', help='print the rows as JSON')
    p.add_argument('--device', default='cpu', help='torch device for the encoder (default cpu)')
    p.add_argument('--threads', type=int, default=None,
                   help='encoder worker threads and torch threads (default: usable CPUs)')
    p.add_argument('--repeats', type=int, default=None,
                   help='repeats per figure (default 5, 2 with --quick)')
    p.add_argument('--profile', action='store_true',
                   help='also time each kernel phase (builds an instrumented kernel copy)')
    p.set_defaults(func=_bench)


def _median_time(fn: Callable[[], object], repeats: int) -> float:
    """Median wall seconds of fn() over repeats calls."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def encoder_rows(quick: bool, repeats: int, device: str, threads: int | None) -> list[Row]:
    """Fast encoder at batch 1, 16, 64 against the naive oracle, plus warm-up cost."""
    import torch

    from point_gn_ros.core import kernels
    from point_gn_ros.core.config import EncoderConfig
    from point_gn_ros.core.encoder import PointGNEncoder
    from point_gn_ros.core.encoder_naive import NaiveEncoder

    cfg = EncoderConfig()
    rows: list[Row] = []
    path = kernels.library_path()
    cached = path is not None and path.exists()
    t0 = time.perf_counter()
    enc = PointGNEncoder(cfg, device=device, threads=threads)
    warm = enc.warmup()
    start = time.perf_counter() - t0
    note = (f'backend {enc.backend}, {enc.threads} threads; kernel '
            + ('loaded from cache' if cached else 'built now') if enc.backend == 'kernel'
            else f'backend {enc.backend}')
    rows.append(dict(section='encoder', what='start-up: construct + warmup()', value=start * 1e3,
                     unit='ms', note=note))
    rows.append(dict(section='encoder', what='  of which warmup()', value=warm * 1e3, unit='ms',
                     note='first encode: thread start, page faults'))

    clouds = torch.from_numpy(synthetic_clouds(64, cfg.num_points))
    n_naive = 1 if quick else 3
    naive = NaiveEncoder(cfg)
    # The oracle at 1 torch thread and at the bench's thread count; ratios use the faster
    # (on 2 shared cores 1 thread wins by far: its large ops wake OpenMP threads that spin).
    naive_rate = 0.0
    saved = torch.get_num_threads()
    for n_threads in sorted({1, saved}):
        torch.set_num_threads(n_threads)
        naive.encode(clouds[:1])  # first-call costs out of the timing
        t_naive = _median_time(lambda: naive.encode(clouds[:n_naive]), max(1, repeats // 2))
        rate = n_naive / t_naive
        rows.append(dict(section='encoder', what=f'naive oracle, {n_threads} torch thread(s)',
                         value=rate, unit='clouds/s', note=f'{n_naive} clouds'))
        naive_rate = max(naive_rate, rate)
    torch.set_num_threads(saved)
    for batch in (1, 16, 64):
        total = batch if batch > 1 else (8 if quick else 32)  # batch 1: several calls

        def run(batch: int = batch, total: int = total) -> None:
            for i in range(0, total, batch):
                enc.encode(clouds[i % 64:i % 64 + batch])

        cpu0 = time.process_time()
        rate = total / _median_time(run, repeats)
        cpu = (time.process_time() - cpu0) / (total * repeats)
        rows.append(dict(section='encoder', what=f'fast encoder, batch {batch}', value=rate,
                         unit='clouds/s', note=f'{rate / naive_rate:.0f}x naive; '
                                               f'{1e3 / rate:.2f} ms per cloud; process CPU '
                                               f'{cpu * 1e3:.2f} ms per cloud'))
    enc.close()
    # A lone cloud on 1 and on 2 threads (the automatic choice picks 2 only while the load
    # average leaves a CPU spare); wall time is what changes, CPU time shows the overhead.
    total = 8 if quick else 32
    for lone in (1, 2):
        one = PointGNEncoder(cfg, device=device, threads=threads, lone_threads=lone)

        def run_lone(one: PointGNEncoder = one) -> None:
            for i in range(total):
                one.encode(clouds[i % 64:i % 64 + 1])

        run_lone()
        cpu0 = time.process_time()
        t = _median_time(run_lone, repeats) / total
        cpu = (time.process_time() - cpu0) / (total * repeats)
        rows.append(dict(section='encoder', what=f'one cloud, lone_threads={lone}',
                         value=t * 1e3, unit='ms', note=f'process CPU {cpu * 1e3:.2f} ms; '
                                                        f'load average {_load():.1f}'))
        # As a sensor's clouds come (30/s): caches and the other CPU idle in between.
        times = []
        for i in range(total):
            time.sleep(1 / 30)
            t0 = time.perf_counter()
            one.encode(clouds[i % 64:i % 64 + 1])
            times.append(time.perf_counter() - t0)
        rows.append(dict(section='encoder', what=f'one cloud at 30/s, lone_threads={lone}',
                         value=statistics.median(times) * 1e3, unit='ms',
                         note=f'median of {total}, 33 ms idle before each'))
    return rows


def _load() -> float:
    import os
    try:
        return os.getloadavg()[0]
    except OSError:
        return float('nan')


def resample_rows(quick: bool, repeats: int) -> list[Row]:
    """sampling.prepare on inputs of 1k to 1M points (FPS) and on a 340-point scan (filled up)."""
    import numpy as np

    from point_gn_ros.core.sampling import prepare

    rows: list[Row] = []
    rng = np.random.default_rng(1)
    sizes = (1_000, 10_000) if quick else (1_000, 10_000, 100_000, 1_000_000)
    for n in sizes:
        xyz = rng.normal(0, 1, (n, 3)).astype(np.float32)
        prepare(xyz)
        t = _median_time(lambda xyz=xyz: prepare(xyz), repeats)
        rows.append(dict(section='resample', what=f'prepare() {n:,} points -> 1024',
                         value=t * 1e3, unit='ms', note='method fps'))
    # a single-view scan's typical size (core/views.py's default protocol), filled up to 1024
    scan = rng.normal(0, 1, (340, 3)).astype(np.float32)
    for upsample in ('repeat', 'midpoint'):
        prepare(scan, upsample=upsample)   # warm: first-call costs stay out of the timing
        t = _median_time(lambda u=upsample: prepare(scan, upsample=u), repeats)
        rows.append(dict(section='resample', what='prepare() 340 points -> 1024',
                         value=t * 1e3, unit='ms', note=f'upsample {upsample}'))
    return rows


def classifier_rows(quick: bool, repeats: int, device: str) -> list[Row]:
    """Classification time per query against random banks of 1k, 10k, 100k entries."""
    try:
        from point_gn_ros.bank.store import FeatureBank
        from point_gn_ros.bank.classifier import Classifier
        from point_gn_ros.bank.model import FeatureTransform
    except ImportError as exc:  # HOOK: classifier not available in this checkout
        return [dict(section='classifier', what='classifier', value=float('nan'), unit='ms',
                     note=f'skipped: {exc}')]
    import torch

    from point_gn_ros.core.config import EncoderConfig

    cfg = EncoderConfig()
    rows: list[Row] = []
    gen = torch.Generator().manual_seed(2)
    sizes = (1_000, 10_000) if quick else (1_000, 10_000, 100_000)
    # 1,620 = raw feature width; 512 = the stored width of the shipped bank (PCA by CV).
    for dims in (cfg.feature_dim, 512):
        for n in sizes:
            feats = torch.nn.functional.normalize(torch.randn(n, dims, generator=gen), dim=1)
            tf = FeatureTransform(torch.zeros(cfg.feature_dim), torch.ones(cfg.feature_dim),
                                  None if dims == cfg.feature_dim else
                                  torch.randn(cfg.feature_dim, dims, generator=gen))
            bank = FeatureBank(features=feats, labels=torch.randint(0, 40, (n,), generator=gen),
                               class_names=[f'c{i}' for i in range(40)], config=cfg,
                               transform=tf, gamma=100.0)
            # exact: every entry; indexed (what 'auto' picks from 20,000 entries): the
            # two-stage search, here on isotropic random rows, its worst case (the coarse
            # pass keeps ~90 % of the width)
            for search in ('exact', 'indexed') if n >= 100_000 else ('exact',):
                clf = Classifier(bank, device=device, search=search)
                for batch in (1, 16, 64):
                    q = torch.randn(batch, cfg.feature_dim, generator=gen)
                    clf.classify(q)
                    t = _median_time(lambda clf=clf, q=q: clf.classify(q), repeats)
                    rows.append(dict(section='classifier',
                                     what=f'bank {n:,} x {dims} dims, batch {batch}'
                                          + (f' ({search})' if search != 'exact' else ''),
                                     value=t / batch * 1e3, unit='ms/query', note=''))
            del bank, clf, feats
    return rows + default_bank_rows(repeats, device)


def default_bank_rows(repeats: int, device: str) -> list[Row]:
    """The shipped default bank's classifier per query: demo objects whole and as scans.

    Complete objects go to the exact complete section (int4 codes), scans to the indexed
    scan section (the gate routes them); lone queries are what a node at low rates sees.
    One torch thread, as the node runs its classifier (`torch_threads`).
    """
    import torch

    saved = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _default_bank_rows(repeats, device)
    finally:
        torch.set_num_threads(saved)


def _default_bank_rows(repeats: int, device: str) -> list[Row]:
    import numpy as np

    from point_gn_ros.clients.node_client import load_demo_objects, place_in_sensor_frame
    from point_gn_ros.recognizer import Recognizer

    rec = Recognizer.from_bank(None, device=device)
    objects = load_demo_objects()
    rng = np.random.default_rng(3)
    rows: list[Row] = []
    for kind, single_view in (('complete objects', False), ('single-view scans', True)):
        feats = rec.encode([place_in_sensor_frame(x, rng, single_view=single_view)
                            for x in objects.xyz[:16]])
        for batch in (1, 8):
            def run(b: int = batch, feats: Any = feats) -> None:
                for i in range(0, 16, b):
                    rec.classifier.classify(feats[i:i + b])

            run()
            cpu0 = time.process_time()
            t = _median_time(run, repeats) / 16
            cpu = (time.process_time() - cpu0) / (16 * repeats)
            rows.append(dict(section='classifier', what=f'default bank, {kind}, batch {batch}',
                             value=t * 1e3, unit='ms/query',
                             note=f'process CPU {cpu * 1e3:.2f} ms per query'))
    return rows


def node_rows(quick: bool, repeats: int) -> list[Row]:
    """End-to-end node rows through real DDS: throughput, latency, peak RSS."""
    del repeats  # each input rate runs for a fixed duration instead
    from point_gn_ros.clients.node_bench import bench_rows
    return bench_rows(quick)


TABLE_HEADER = f'{"section":<11} {"what":<38} {"value":>11} {"unit":<10} note'


def format_rows(rows: list[Row]) -> str:
    """Table lines (no header) for rows."""
    lines = []
    for r in rows:
        value = r['value']
        text = f'{value:11.2f}' if value == value else f'{"-":>11}'  # NaN: skipped
        lines.append(f'{r["section"]:<11} {r["what"]:<38} {text} {r["unit"]:<10} {r["note"]}')
    return '\n'.join(lines)


def _bench(args: argparse.Namespace) -> int:
    import platform

    import torch

    from point_gn_ros.core.encoder import default_threads

    if args.profile:
        import os
        os.environ['POINT_GN_KERNEL_PROFILE'] = '1'  # read when the kernels first load
    threads = args.threads or default_threads()
    torch.set_num_threads(threads)
    repeats = args.repeats or (2 if args.quick else 5)
    rows: list[Row] = []
    sections = [
        lambda: encoder_rows(args.quick, repeats, args.device, threads),
        lambda: resample_rows(args.quick, repeats),
        lambda: classifier_rows(args.quick, repeats, args.device),
        lambda: node_rows(args.quick, repeats),
    ]
    if args.profile:
        sections.append(lambda: profile_rows(args.quick, repeats))
    if not args.json:
        print(f'# {platform.processor() or platform.machine()}, {threads} threads, load average '
              f'{_load():.1f} at start', flush=True)
        print(TABLE_HEADER, flush=True)
    for section in sections:
        got = section()
        rows += got
        if not args.json and got:
            print(format_rows(got), flush=True)  # as each section finishes
    if args.json:
        info = dict(machine=platform.processor() or platform.machine(), threads=threads,
                    torch=torch.__version__, repeats=repeats, quick=args.quick,
                    load_average_end=_load())
        json.dump(dict(info=info, rows=rows), sys.stdout, indent=1)
        print()
    return 0
