#!/usr/bin/env python3
"""The taught block's lead (bank/taught.py LEAD_SLOPE, LEAD_MARGIN) and the unknown rule's scope.

Two sets, no test object read:

  tabletop     the restaurant Kinect-sim tree (metres): 5 views of each of the 20 classes
               taught into the shipped bank (`bank add`'s policy, measured sizes), the other
               views queried
  lidar proxy  ModelNet40 TRAIN car, person, plant and lamp objects (100 a class at most) as
               car, pedestrian, bush and pole: one sparse single-view scan each (camera 0-15
               degrees above the horizon, 3-12 radii away, 30-85 % dropout, <= 400 points,
               the lowest 5 % of the height cut as ground), scaled to real sizes (the size
               prior; lamps thinned to 0.3 and stretched to 2.5-5 m as poles). A harsh
               stand-in for real lidar clusters: the built classes hold these very objects.

For each draw (class `draw * 7 mod C` held out for the open set) and each (slope, margin):
mean class accuracy, the share answered with a built class, the unknown rule's AUROC and
reject rates (unseen / taught) for the fit to every class and to the taught classes only.
And the cost to the built classes: the tabletop classes of draw 0 taught, ModelNet40 train
scans (size_knob_study.sized_train_scans) classified without sizes (`point_gn eval`'s way)
and with their plausible sizes: accuracy before - after, in points.

usage: experiments/lead_study.py [--cache DIR] [--draws 3] [--write-proxy DIR]
  --write-proxy DIR  also write the lidar proxy as a class-per-folder tree of .npy clouds
                     (for `point_gn fewshot DIR/all --bank default`)
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.bank.enroll import BankFile, add_examples
from point_gn_ros.bank.refit import RefitPolicy
from point_gn_ros.bank.taught import plausible_scale
from point_gn_ros.core.size import size_descriptors
from point_gn_ros.core.views import ViewConfig, simulate_view
from point_gn_ros.datasets import open_dataset
from point_gn_ros.evaluation.openset import auroc
from point_gn_ros.evaluation.teach import mean_class_accuracy
from point_gn_ros.recognizer import encode_clouds, make_encoder
from size_knob_study import sized_train_scans

SHARED = Path(__file__).resolve().parents[2] / 'shared' / 'datasets'
POLICY = RefitPolicy(lda_prior='typical', lda_debias=2.0, lda_steal_budget=0.001)
GRID = ((20.0, 0.0), (10.0, 0.1), (10.0, 0.2), (5.0, 0.2), (10.0, 0.3), (10.0, 0.5))
PROXY = {'car': 'car', 'person': 'pedestrian', 'plant': 'bush', 'lamp': 'pole'}
LIDAR_VIEW = ViewConfig(elevation_deg=(0.0, 15.0), distance=(3.0, 12.0), noise=(0.005, 0.015),
                        dropout=(0.3, 0.85), min_points=24)


def lidar_proxy() -> tuple[list[np.ndarray], np.ndarray, list[str]]:
    """The proxy of the module docstring -> clouds (metres, z up), labels, class names."""
    ds = open_dataset(SHARED / 'modelnet40_1024', split='train')
    y = np.asarray(ds.labels)
    rng = np.random.default_rng(7)
    clouds, labels = [], []
    for k, name in enumerate(PROXY):
        for i in np.flatnonzero(y == ds.class_names.index(name))[:100]:
            full = ds[int(i)][0].astype(np.float64)
            if name == 'lamp':
                scale = rng.uniform(2.5, 5.0) / np.ptp(full[:, 2])
                full = full * np.array([0.3, 0.3, 1.0])
            else:
                scale = plausible_scale(full, name) * rng.uniform(0.85, 1.15)
            view = simulate_view(full.astype(np.float32), rng, LIDAR_VIEW).points * scale
            view = view[view[:, 2] > view[:, 2].min() + 0.05 * np.ptp(view[:, 2])]
            if len(view) > 400:
                view = view[rng.choice(len(view), rng.integers(80, 400), replace=False)]
            clouds.append(view.astype(np.float32))
            labels.append(k)
    return clouds, np.asarray(labels), list(PROXY.values())


def taught(base: BankFile, feats: torch.Tensor, sizes: np.ndarray, y: np.ndarray,
           names: list[str], draw: int, skip: int | None = None) -> tuple[Classifier, np.ndarray]:
    """5 scans a class (but `skip`) taught into `base` -> its classifier, the support ids."""
    r = np.random.default_rng(draw)
    sup = np.concatenate([r.permutation(np.flatnonzero(y == c))[:5] for c in range(len(names))])
    bf = base
    for c in range(len(names)):
        if c != skip:
            idx = sup[y[sup] == c]
            bf = add_examples(bf, feats[idx], names[c], 'lead study', POLICY,
                              sizes=sizes[idx]).file
    return Classifier(bf.bank, fit_threshold=0.0), sup


def head_outputs(clf: Classifier, feats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The head's probabilities and the transformed rows: the same for every grid point."""
    return clf.evaluate(feats)[0], clf.transform(feats)


def layer_outputs(clf: Classifier, head: tuple[torch.Tensor, torch.Tensor],
                  sizes: np.ndarray | None, slope: float, margin: float):
    layer = replace(clf.taught, lead_slope=slope, lead_margin=margin)
    out, fit, misfit = layer.apply(*head, sizes)
    return out.argmax(1).numpy(), fit, misfit, layer


def study(base: BankFile, feats: torch.Tensor, sizes: np.ndarray, y: np.ndarray,
          names: list[str], draws: int) -> dict:
    rows: dict = {}
    for draw in range(draws):
        clf, sup = taught(base, feats, sizes, y, names, draw)
        held = draw * 7 % len(names)
        clf_open, _ = taught(base, feats, sizes, y, names, draw, held)
        q = np.setdiff1d(np.arange(len(y)), sup)
        to_ds = {clf.bank.class_names.index(n): i for i, n in enumerate(names)}
        unseen = np.flatnonzero(y == held)
        known = q[y[q] != held]
        both = np.r_[known, unseen]
        is_unseen = np.r_[np.zeros(len(known), bool), np.ones(len(unseen), bool)]
        head_q, head_open = head_outputs(clf, feats[q]), head_outputs(clf_open, feats[both])
        z_open = head_open[1].double().numpy()
        for slope, margin in GRID:
            top, *_ = layer_outputs(clf, head_q, sizes[q], slope, margin)
            top = np.array([to_ds.get(int(p), -1) for p in top])
            _, fit, misfit, layer = layer_outputs(clf_open, head_open, sizes[both], slope,
                                                  margin)
            fit_all = layer.fit(z_open, layer.plausibility(sizes[both]))
            out = [mean_class_accuracy(top, y[q]), (top < 0).mean()]
            for score in (fit_all, fit):
                rejected = (score < 0) | (misfit > 1)
                out += [auroc(-score[is_unseen], -score[~is_unseen]),
                        rejected[is_unseen].mean(), rejected[~is_unseen].mean()]
            rows.setdefault((slope, margin), []).append(out)
    return {k: np.mean(v, axis=0) for k, v in rows.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--cache', default='cache')
    ap.add_argument('--draws', type=int, default=3)
    ap.add_argument('--write-proxy', default=None)
    args = ap.parse_args()
    torch.set_num_threads(2)
    base = BankFile.load(None)
    enc = make_encoder(base.bank.config, 'cpu')
    clouds, y, names = lidar_proxy()
    if args.write_proxy:
        for i, (cloud, label) in enumerate(zip(clouds, y, strict=True)):
            folder = Path(args.write_proxy) / 'all' / names[label]
            folder.mkdir(parents=True, exist_ok=True)
            np.save(folder / f'{names[label]}_{i:04d}.npy', cloud)
    tt = open_dataset(SHARED / 'restaurant_kinectsim' / 'all', split='train')
    tt_clouds = [tt[i][0] for i in range(len(tt))]
    sets = {'tabletop': (tt_clouds, np.asarray(tt.labels), list(tt.class_names)),
            'lidar proxy': (clouds, y, names)}
    head = ('| set | slope, margin | accuracy | built share | AUROC, reject unseen / taught: '
            'fit to every class | fit to the taught classes |')
    print(head + '\n|---|---|---|---|---|---|')
    for name, (cl, labels, cls) in sets.items():
        feats, sizes = encode_clouds(cl, enc), size_descriptors(cl)
        res = study(base, feats, sizes, labels, cls, args.draws)
        for (slope, margin), m in res.items():
            print(f'| {name} | {slope:g}, {margin:g} | {100 * m[0]:.1f} % | {100 * m[1]:.1f} % '
                  f'| {m[2]:.3f}, {100 * m[3]:.1f} / {100 * m[4]:.1f} % '
                  f'| {m[5]:.3f}, {100 * m[6]:.1f} / {100 * m[7]:.1f} % |', flush=True)
    # the cost to the built classes
    feats, my, msizes, _ = sized_train_scans(Path(args.cache), enc)
    clf, _ = taught(base, encode_clouds(tt_clouds, enc), size_descriptors(tt_clouds),
                    np.asarray(tt.labels), list(tt.class_names), 0)
    shipped = Classifier(base.bank)
    before = {s is None: (shipped.classify(feats, 1, sizes=s).topk_ids[:, 0] == my).mean()
              for s in (None, msizes)}
    head = head_outputs(clf, feats)
    print('\n| slope, margin | ModelNet40 train scans, drop without sizes | with sizes |\n'
          '|---|---|---|')
    for slope, margin in GRID:
        cells = []
        for s in (None, msizes):
            after = (layer_outputs(clf, head, s, slope, margin)[0] == my).mean()
            cells.append(f'{100 * (before[s is None] - after):.1f}')
        print(f'| {slope:g}, {margin:g} | ' + ' | '.join(cells) + ' |', flush=True)


if __name__ == '__main__':
    main()
