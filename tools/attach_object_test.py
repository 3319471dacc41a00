"""Fit the object test of taught classes (bank/objects.py) into a built two-section bank.

What `point_gn bank build --sections` now fits itself (bank/sections.py), for a bank built
before it: the bank build's scans are encoded again (or read from its feature cache), the
test is fitted on the scan section's standardised rows, and the bank is written back with
every other array bit for bit as it was (checked before the file is replaced).

Run: python tools/attach_object_test.py [--bank BANK] [--cache DIR] [-o OUT]
(the shipped bank by default; 7 minutes of encoding without the cache)
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
import sys

import numpy as np
import torch

from point_gn_ros.bank.builder import encode_dataset
from point_gn_ros.bank.discriminant import fit_object_test
from point_gn_ros.bank.store import OBJECTS_PREFIX
from point_gn_ros.bank.store import FeatureBank, default_bank_path
from point_gn_ros.core.views import VIEW_PROTOCOLS
from point_gn_ros.datasets import open_dataset
from point_gn_ros.datasets.views import ViewsDataset
from point_gn_ros.recognizer import make_encoder

MODELNET = Path(__file__).resolve().parents[2] / 'shared' / 'datasets' / 'modelnet40_1024'


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--bank', default=str(default_bank_path()))
    p.add_argument('--dataset', default=str(MODELNET))
    p.add_argument('--cache')
    p.add_argument('-o', '--output', help='default: the bank itself')
    args = p.parse_args(argv)
    torch.set_num_threads(2)
    bank = FeatureBank.load(args.bank)
    vm = bank.meta.get('views')
    if bank.views is None or not vm:
        raise SystemExit(f'{args.bank}: not a two-section bank with its views recorded')
    train = open_dataset(args.dataset, split=vm['source_split'])
    cfgs = VIEW_PROTOCOLS[vm['protocol']]               # as `point_gn bank build --views`
    ds = ViewsDataset(train, int(vm['views_per_object']), int(vm['seed']),
                      cfgs if len(cfgs) > 1 else cfgs[0], include_full=True, random_yaw=True)
    feats = encode_dataset(ds, make_encoder(bank.config), cache_dir=args.cache)
    scan = np.asarray(ds.view_index) >= 0
    if int(scan.sum()) != len(bank.views) or not np.array_equal(
            np.asarray(ds.labels)[scan], bank.views.labels.numpy()):
        raise SystemExit("the re-made scans do not match the bank's scan section")
    objects = fit_object_test(bank.views.transform.standardized(feats[torch.from_numpy(scan)]),
                             np.asarray(ds.groups)[scan], bank.views.labels.numpy(),
                             bank.class_names)
    out = Path(args.output or args.bank)
    tmp = out.with_name(out.name + '.new.npz')
    meta = {**bank.meta, 'object_test': objects.describe()}
    replace(bank, meta=meta, objects=objects).save(tmp, dtype=bank.meta['stored_dtype'])
    with np.load(args.bank) as old, np.load(tmp) as new:
        changed = [k for k in old.files if k not in ('meta', 'views_meta')
                   and not np.array_equal(old[k], new[k])]
        added = sorted(set(new.files) - set(old.files))
    if changed or any(not k.startswith(OBJECTS_PREFIX) for k in added):
        tmp.unlink()
        raise SystemExit(f'arrays changed: {changed}, added: {added}')
    tmp.replace(out)
    print(f'{out}: object test of {len(objects.means)} objects, rank {objects.rank} '
          f'({out.stat().st_size / 1e6:.1f} MB)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
