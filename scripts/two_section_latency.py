"""Lone queries needing both sections of a two-section bank: with and without the helper.

Wall time with and without the helper thread (bank/classifier.py), interleaved, and
whether the answers are identical.

`python scripts/two_section_latency.py [--passes 30]`: the shipped default bank, the demo
objects placed in a sensor frame (the node bench's input), one torch thread.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--passes', type=int, default=30)
    args = ap.parse_args()
    torch.set_num_threads(1)
    import point_gn_ros.bank.classifier as clf_mod
    from point_gn_ros.clients.node_client import load_demo_objects, place_in_sensor_frame
    from point_gn_ros.recognizer import Recognizer

    rec = Recognizer.from_bank(None, threads=1)
    rng = np.random.default_rng(0)
    feats = rec.encode([place_in_sensor_frame(x, rng) for x in load_demo_objects().xyz])
    p = rec.classifier.gate.scan_probability(feats)
    both = feats[(p > clf_mod.GATE_SKIP) & (p < 1 - clf_mod.GATE_SKIP)]
    print(f'{len(both)} of {len(feats)} objects need both sections')
    helper = clf_mod._section_helper
    times: dict[str, list[float]] = {'helper thread': [], 'one thread': []}
    answers: dict[tuple[str, int], np.ndarray] = {}
    for _ in range(args.passes):
        for mode in times:
            clf_mod._section_helper = helper if mode == 'helper thread' else (lambda: None)
            for i in range(len(both)):
                t0 = time.perf_counter()
                out = rec.classifier.classify(both[i:i + 1])
                times[mode].append(time.perf_counter() - t0)
                answers.setdefault((mode, i), out.probability)
    for mode, t in times.items():
        print(f'{mode}: wall p50 {np.percentile(t, 50) * 1e3:.2f} ms, '
              f'p90 {np.percentile(t, 90) * 1e3:.2f} ms')
    same = all(np.array_equal(answers[('helper thread', i)], answers[('one thread', i)])
               for i in range(len(both)))
    print('identical answers:', same)


if __name__ == '__main__':
    main()
