"""Classifier CPU per query on the shipped default bank, for before/after comparisons.

Run it in each checkout in turn (`PYTHONPATH=CHECKOUT python benchmarks/classifier_ab.py
--label NAME`): 16 demo objects, whole and as simulated single-view scans, are encoded, then
classified at batch 1 and 8; process CPU time, one torch thread, min of --repeats passes.
Only the package's public pieces are used, so older checkouts run it unchanged.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--label', default='tree')
    ap.add_argument('--repeats', type=int, default=7)
    args = ap.parse_args()
    torch.set_num_threads(1)
    from point_gn_ros.clients.node_client import load_demo_objects, place_in_sensor_frame
    from point_gn_ros.recognizer import Recognizer

    rec = Recognizer.from_bank(None, threads=1)
    objects = load_demo_objects()
    rng = np.random.default_rng(3)
    for kind, single_view in (('complete', False), ('scans', True)):
        feats = rec.encode([place_in_sensor_frame(x, rng, single_view=single_view)
                            for x in objects.xyz[:16]])
        for batch in (1, 8):
            def run(b: int = batch, f: torch.Tensor = feats) -> None:
                for i in range(0, len(f), b):
                    rec.classifier.classify(f[i:i + b])

            run()
            best = float('inf')
            for _ in range(args.repeats):
                t0 = time.process_time()
                run()
                best = min(best, (time.process_time() - t0) / len(feats))
            print(f'{args.label} {kind:8s} batch {batch}: {best * 1e3:.2f} ms CPU per query',
                  flush=True)


if __name__ == '__main__':
    main()
