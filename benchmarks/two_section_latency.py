"""Lone queries on the shipped two-section bank: helper-thread paths against one thread.

`--case both` (default): the demo objects placed in a sensor frame (the node bench's input)
whose gate needs both sections; with and without the helper thread that evaluates the scan
section (bank/classifier.py). `--case scans`: simulated single-view scans the gate sends to
the scan section alone; with and without the coarse pass split over the helper thread
(bank/index.py, `SPLIT_MIN_ROWS`). `--compare bits` instead compares the scan section's
index at 4-bit and 8-bit coarse codes (bank/index.py `COARSE_BITS`), both with the
helper thread. `--case complete --compare nibbles`: complete objects the gate sends to the
complete section alone, its exact scan from 4-bit nibbles (kernels.packed_dots_i4) against
its int8 codes. `--gap-ms G` idles G ms before each query, as between a sensor's objects.
Interleaved passes, wall and process CPU time, one torch thread, and whether the answers
are identical.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--case', choices=('both', 'scans', 'complete'), default='both')
    ap.add_argument('--passes', type=int, default=30)
    ap.add_argument('--compare', choices=('helper', 'bits', 'nibbles'), default='helper')
    ap.add_argument('--gap-ms', type=float, default=0.0)
    args = ap.parse_args()
    torch.set_num_threads(1)
    import point_gn_ros.bank.classifier as clf_mod
    import point_gn_ros.bank.index as search_mod
    from point_gn_ros.bank.index import IndexedSearch
    from point_gn_ros.bank.vote import CompiledHead
    from point_gn_ros.clients.node_client import load_demo_objects, place_in_sensor_frame
    from point_gn_ros.recognizer import Recognizer

    rec = Recognizer.from_bank(None, threads=1)
    rng = np.random.default_rng(0)
    scans = args.case == 'scans'
    feats = rec.encode([place_in_sensor_frame(x, rng, single_view=scans)
                        for x in load_demo_objects().xyz])
    p = rec.classifier.gate.scan_probability(feats)
    skip = clf_mod.GATE_SKIP
    queries = (feats[p >= 1 - skip] if scans else feats[p <= skip] if args.case == 'complete'
               else feats[(p > skip) & (p < 1 - skip)])
    print(f'{len(queries)} of {len(feats)} objects in this case')
    helper, split = clf_mod.helper_thread, search_mod.SPLIT_MIN_ROWS
    views = rec.classifier.views
    if args.compare == 'bits':
        modes = ('4-bit codes', '8-bit codes')
        searches = {}
        for mode, bits in zip(modes, (4, 8), strict=True):
            views.search = IndexedSearch(views.features, views.labels, views.bank.num_classes,
                                         code_bits=bits)
            searches[mode] = (views.search, CompiledHead.build(
                views.transform, views.head, views.bank.num_classes, views.search))
    elif args.compare == 'nibbles':
        modes = ('nibbles', 'int8 codes')
        search = rec.classifier.search
        packed = search._packed
    else:
        modes = ('helper thread', 'one thread')
    times: dict[str, list[float]] = {m: [] for m in modes}
    cpu = dict.fromkeys(modes, 0.0)
    answers: dict[tuple[str, int], np.ndarray] = {}
    for _ in range(args.passes):
        for mode in modes:
            if args.compare == 'bits':
                views.search, views.compiled_head = searches[mode]
            elif args.compare == 'nibbles':
                search._packed = packed if mode == 'nibbles' else None
            else:
                on = mode == 'helper thread'
                clf_mod.helper_thread = helper if on else (lambda: None)
                search_mod.SPLIT_MIN_ROWS = split if on else 1 << 62
            c0 = time.process_time()
            for i in range(len(queries)):
                if args.gap_ms:
                    time.sleep(args.gap_ms / 1e3)
                t0 = time.perf_counter()
                out = rec.classifier.classify(queries[i:i + 1])
                times[mode].append(time.perf_counter() - t0)
                answers.setdefault((mode, i), out.probability)
            cpu[mode] += time.process_time() - c0
    for mode, t in times.items():
        print(f'{mode}: wall p50 {np.percentile(t, 50) * 1e3:.2f} ms, '
              f'p90 {np.percentile(t, 90) * 1e3:.2f} ms; process CPU '
              f'{cpu[mode] / len(t) * 1e3:.2f} ms per query')
    same = all(np.array_equal(answers[(modes[0], i)], answers[(modes[1], i)])
               for i in range(len(queries)))
    print('identical answers:', same)
    if args.compare == 'bits':      # other codes may pick other candidates: how far apart
        a, b = (np.stack([answers[(m, i)] for i in range(len(queries))]) for m in modes)
        print(f'labels differing: {int((a.argmax(1) != b.argmax(1)).sum())} of {len(a)}, '
              f'max probability difference {float(np.abs(a - b).max()):.2g}')


if __name__ == '__main__':
    main()
