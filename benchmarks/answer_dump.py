"""Dump the shipped default bank's answers on ModelNet40 test, to compare two checkouts.

Run it in each checkout (`PYTHONPATH=CHECKOUT python benchmarks/answer_dump.py --out DIR`):
the complete objects and one single-view scan each (hpr, random yaw, seed 0, as `point_gn
eval --single-view`) are encoded once (features cached in --cache, shared by the runs, so
both checkouts classify the same features), then classified in batches of 64 and one by
one (the lone path). Writes DIR/{protocol}_{batch|lone}_{labels,probability}.npy. Compare
with --compare OTHER_DIR: labels that differ and the largest probability change.
Only public pieces that the start commit has are used.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

DATA = Path(__file__).resolve().parents[1] / '..' / 'shared' / 'datasets' / 'modelnet40_1024'


def dump(out: Path, cache: Path, data: Path) -> None:
    from point_gn_ros.bank.builder import encode_dataset
    from point_gn_ros.bank.classifier import Classifier
    from point_gn_ros.bank.store import FeatureBank
    from point_gn_ros.core.views import VIEW_PROTOCOLS
    from point_gn_ros.datasets import open_dataset
    from point_gn_ros.datasets.views import ViewsDataset
    from point_gn_ros.recognizer import make_encoder

    bank = FeatureBank.load(None)
    ds = open_dataset(data, split='test')
    enc = make_encoder(bank.config, 'cpu')
    clf = Classifier(bank)
    out.mkdir(parents=True, exist_ok=True)
    sources = {'complete': ds,
               'single_view': ViewsDataset(ds, 1, 0, VIEW_PROTOCOLS['hpr'][0],
                                           include_full=False, random_yaw=True)}
    for name, source in sources.items():
        feats = torch.as_tensor(encode_dataset(source, enc, 64, progress=False,
                                               cache_dir=cache))
        for mode, step in (('batch', 64), ('lone', 1)):
            res = [clf.classify(feats[i:i + step], top_k=1) for i in range(0, len(feats), step)]
            np.save(out / f'{name}_{mode}_labels.npy', np.concatenate([r.labels for r in res]))
            np.save(out / f'{name}_{mode}_probability.npy',
                    np.concatenate([r.probability for r in res]))
            print(f'{name} {mode}: {len(feats)} answers', flush=True)


def compare(a: Path, b: Path) -> int:
    bad = 0
    for f in sorted(a.glob('*_labels.npy')):
        la, lb = np.load(f), np.load(b / f.name)
        pa = np.load(f.with_name(f.name.replace('labels', 'probability')))
        pb = np.load(b / f.name.replace('labels', 'probability'))
        differ, moved = int((la != lb).sum()), float(np.abs(pa - pb).max())
        print(f'{f.name[:-11]}: {differ} of {len(la)} labels differ, largest probability '
              f'change {moved:.2e}')
        bad += differ > 0 or moved > 1e-5
    return int(bad > 0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--out', type=Path, required=True)
    ap.add_argument('--cache', type=Path, default=Path('/tmp/pgn_answer_dump_cache'))
    ap.add_argument('--data', type=Path, default=DATA)
    ap.add_argument('--compare', type=Path, help='another --out folder: compare, do not run')
    args = ap.parse_args()
    if args.compare is not None:
        return compare(args.out, args.compare)
    torch.set_num_threads(2)
    dump(args.out, args.cache, args.data)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
