"""CPU time of each step of one live enrollment, single thread, without ROS.

Replays what the node's committer does for `--examples` scans of a new object (the clouds
benchmarks/enroll_latency.py enrolls): encode them, add them to each section of the bank
(add_examples; the refit and the near-duplicate check inside it reported apart), build the
next version's model (Recognizer; with the previous one to derive from where the code
supports it). Thread CPU time (time.thread_time), median over `--repeats` enrollments of
new classes in a row, torch and the encoder on one thread. The node's swap itself
(replace_recognizer: a reference swap and the class-name parameter) is not in here.

Run: python benchmarks/enroll_profile.py [--bank PATH] [--examples 20] [--repeats 5]
"""

from __future__ import annotations

import argparse
from collections import defaultdict
import json
from pathlib import Path
import sys
import time
from typing import Any

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / 'test'))


def _timed(module: Any, name: str, times: dict[str, list[float]], key: Any) -> None:
    """Wrap module.name so each call's thread CPU time is added under key(args)."""
    fn = getattr(module, name)

    def wrapper(*args: Any, **kwargs: Any) -> Any:
        t = time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            times[key(*args)].append(time.thread_time() - t)
    setattr(module, name, wrapper)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--bank', default=None, help='bank (default: the shipped default bank)')
    p.add_argument('--examples', type=int, default=20)
    p.add_argument('--repeats', type=int, default=5)
    p.add_argument('--json', default=None)
    args = p.parse_args(argv)
    torch.set_num_threads(1)

    from conftest import load_modelnet_split
    import point_gn_ros.bank.enroll as enroll
    import point_gn_ros.bank.live as live_mod
    from point_gn_ros.bank.live import LiveBank
    from point_gn_ros.core.views import simulate_views
    from point_gn_ros.recognizer import Recognizer, make_encoder

    bf = enroll.BankFile.load(args.bank)
    encoder = make_encoder(bf.bank.config, threads=1)
    times: dict[str, list[float]] = defaultdict(list)
    # sections told apart by their vote-space width (the shipped bank: 512 and 320)
    width = {bf.bank.features.shape[1]: 'main'}
    if bf.views is not None:
        width.setdefault(bf.views.bank.features.shape[1], 'scan')

    def sec(bank: Any) -> str:
        return width.get(bank.features.shape[1], 'section')

    _timed(enroll, 'add_examples', times, lambda bfile, *a: f'add_examples {sec(bfile.bank)}')
    _timed(live_mod, 'add_examples', times, lambda *a: 'add_examples')     # LiveBank.add's
    _timed(enroll, 'refit', times, lambda bank, *a: f'  refit {sec(bank)}')
    _timed(enroll, 'near_duplicates', times, lambda new, bank, *a: f'  near_duplicates '
                                                                  f'{sec(bank)}')
    try:
        live = LiveBank(bf, lambda b: Recognizer(b, encoder=encoder),
                        derive=lambda b, prev: Recognizer(b, encoder=encoder, previous=prev))
        derives = True
    except TypeError:       # a tree without incremental models
        live, derives = LiveBank(bf, lambda b: Recognizer(b, encoder=encoder)), False
    xyz, labels, names = load_modelnet_split('test')
    obj = xyz[np.flatnonzero(labels == names.index('sofa'))[0]]
    views = [v.points * 0.8 + np.float32(3.0) for v in simulate_views(obj, 40, seed=3)]
    clouds = views[:args.examples]
    live.current().model.encode(clouds[:2])                          # warm-up
    rows = []
    for r in range(args.repeats):
        times.clear()
        t = time.thread_time()
        feats = live.current().model.encode(clouds)
        t_enc = time.thread_time() - t
        t = time.thread_time()
        live.add(feats, f'new_{r}', 'profile')
        t_all = time.thread_time() - t
        t_add = sum(times['add_examples'])
        row = {'encode': t_enc, **{k: sum(v) for k, v in times.items()},
               'model build': t_all - t_add, 'commit total': t_all}
        search = getattr(live.current().model.classifier.views or
                         live.current().model.classifier, 'search', None)
        row['derived'] = bool(getattr(search, 'derived', False))
        rows.append(row)
    keys = [k for k in rows[0] if k != 'derived']
    med = {k: float(np.median([r.get(k, np.nan) for r in rows])) for k in keys}
    print(f'bank {args.bank or "default"}: {len(bf.bank)} entries'
          + (f' + scan section {len(bf.views.bank)}' if bf.views else '')
          + f'; {args.examples} examples; median of {args.repeats}; derive supported: '
          f'{derives}, derived: {[r["derived"] for r in rows]}')
    for k in keys:
        print(f'  {k:<28} {1000 * med[k]:7.1f} ms CPU')
    if args.json:
        Path(args.json).write_text(json.dumps({'median_s': med, 'runs': rows}, indent=2) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
