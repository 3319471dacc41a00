"""Yaw handling of single-view scans when the camera position is known, by grouped CV on train.

Issue 9: a scan's canonical yaw (PCA of its x-y spread, signs by third moments) often differs
from its object's, and a robot knows where its sensor is. Variants of the frame a scan is
encoded in (camera = the simulator's, turned with the scan by its random yaw):

- a   canonical_yaw of the scan (today's `prepare(..., yaw_align=True)`);
- b   view-aligned: turned about z so the camera, seen from the scan's centroid, lies on -x;
- c2  PCA major axis on x, turned by 180 degrees when needed to put the camera at y < 0;
- c4  PCA major axis on x, both signs (reflections, as canonical_yaw) by the camera: x, y < 0;
- c4h PCA major axis on x, x's sign by the third moment (as canonical_yaw), y's by the camera
      (y < 0): a scan's camera is mostly across its major axis, where its y is a clear sign;
- c4v b snapped to the scan's principal axes: the axis more across the view on x, the camera
      at y < 0, x's sign by the third moment;
- a+X the sum of the a and X heads' probabilities (the query encoded in both frames).

Bank = the 4 (`--views`) HPR scans of every `--subset`-th train object, each at a random yaw,
exactly as `ViewsDataset(train, K, 0, include_full=True, random_yaw=True)` draws them; 5 folds
grouped by source object; held-out objects' scans are the queries. Scan-section head as in
experiments/gated_study.py (standardise, PCA 320, whitened vote + LDA), fixed knobs. Features are
cached per variant under `--cache` (rotation_study_<key>.npy). Never reads the test split.

    python experiments/rotation_study.py ../shared/datasets/modelnet40_1024 --cache DIR
"""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path
import time

import numpy as np
import torch

from point_gn_ros.bank.discriminant import fit_head
from point_gn_ros.bank.selection import stratified_folds
from point_gn_ros.bank.model import FeatureTransform
from point_gn_ros.core.config import ENCODER_VERSION, EncoderConfig
from point_gn_ros.core.sampling import canonical_yaw, normalize, resample, rotate_z
from point_gn_ros.core.views import DEFAULT_VIEW_CONFIG, SIMULATOR_VERSION, simulate_views
from point_gn_ros.datasets import open_dataset
from point_gn_ros.datasets.views import hash_seed
from point_gn_ros.recognizer import make_encoder
from point_gn_ros.bank.vote import ExactSearch, reference_head

VARIANTS = ('a', 'b', 'c2', 'c4', 'c4h', 'c4v')
# (dims, gamma, whitening shrinkage, LDA shrinkage, LDA weight): gated_study's scan expert, and
# the shipped scan section's CV-chosen knobs.
KNOBS = {'gated': (320, 40.0, 0.1, 0.02, 0.3), 'shipped': (320, 20.0, 0.1, 0.01, 0.2),
         # narrower scan sections: what 8 scans per object at the 25 MB cap would allow
         'gated224': (224, 40.0, 0.1, 0.02, 0.3), 'gated192': (192, 40.0, 0.1, 0.02, 0.3)}
STUDY_VERSION = 1   # bump when a variant's frame changes (cached features re-key)


def turn(xyz: np.ndarray, cam: np.ndarray, angle: float) -> tuple[np.ndarray, np.ndarray]:
    """Rotate a cloud (N, 3) and its camera (3,) about z by angle radians."""
    return rotate_z(xyz, angle), rotate_z(cam[None], angle)[0].astype(np.float64)


def pca_major(xyz: np.ndarray, cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Turn so the x-y spread's major axis lies on x (sign arbitrary): cloud and camera."""
    xy = xyz[:, :2].astype(np.float64)
    _, vecs = np.linalg.eigh(np.cov(xy.T))
    c, s = vecs[:, 1]
    return turn(xyz, cam, -float(np.arctan2(s, c)))


def frame(xyz: np.ndarray, cam: np.ndarray, variant: str) -> np.ndarray:
    """A prepared (centred, unit) cloud (N, 3) and its camera (3,), same frame -> (N, 3)."""
    if variant == 'a':
        return canonical_yaw(xyz)
    if variant == 'b':     # camera azimuth from the centroid (the origin) -> pi
        return turn(xyz, cam, np.pi - float(np.arctan2(cam[1], cam[0])))[0]
    out, c = pca_major(xyz, cam)
    if variant == 'c2':    # rotation only: camera in the y < 0 half-plane
        return rotate_z(out, np.pi) if c[1] > 0 else out
    if variant == 'c4':    # reflections allowed: camera in the x < 0, y < 0 quadrant
        signs = np.where(c[:2] > 0, -1.0, 1.0)
        out = out.copy()
        out[:, :2] *= signs.astype(np.float32)
        return out
    if variant == 'c4v':
        if abs(c[0]) > abs(c[1]):   # looking along the major axis: the minor one goes on x
            out, c = turn(out, c, np.pi / 2)
        variant = 'c4h'
    if variant == 'c4h':
        out = out.copy()
        if np.mean(out[:, 0].astype(np.float64) ** 3) < 0:
            out[:, 0] *= -1.0
        if c[1] > 0:
            out[:, 1] *= -1.0
        return out
    raise ValueError(f'unknown variant {variant!r}')


def prepare_with_camera(xyz: np.ndarray, cam: np.ndarray, n: int = 1024
                        ) -> tuple[np.ndarray, np.ndarray]:
    """`sampling.prepare` without yaw, the camera carried along: (n, 3) float32, (3,)."""
    pts = resample(xyz, n)
    mean = pts.astype(np.float64).mean(axis=0)
    radius = float(np.sqrt(((pts - mean) ** 2).sum(axis=1).max())) or 1.0
    return normalize(pts), (cam - mean) / radius


def simulate(train, sources: np.ndarray, k: int) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """ViewsDataset's scans (seed 0, full object first, random yaw): (source, points, camera)."""
    out = []
    for s in sources:
        s = int(s)
        xyz = train[s][0]
        views = simulate_views(xyz, k, hash_seed(0, s), DEFAULT_VIEW_CONFIG)
        yaws = np.random.default_rng([0, s, 0xA11]).uniform(0, 2 * np.pi, k + 1)[1:]
        out += [(s, *turn(v.points, v.camera, float(a))) for v, a in zip(views, yaws, strict=True)]
    return out


def cached_scans(train, sources: np.ndarray, k: int, key: str, cache: Path) -> list:
    """`simulate`, cached (the hidden point removal costs ~30 ms a scan)."""
    path = cache / f'rotation_study_scans_{hashlib.sha1(key.encode()).hexdigest()[:16]}.npz'
    if path.is_file():
        z = np.load(path, allow_pickle=False)
        pts = np.split(z['points'], z['offsets'][1:-1])
        return list(zip(z['sources'].tolist(), pts, z['cameras'], strict=True))
    t0 = time.process_time()
    scans = simulate(train, sources, k)
    print(f'simulated {len(scans)} scans, {time.process_time() - t0:.0f} s CPU', flush=True)
    offsets = np.cumsum([0] + [len(p) for _, p, _ in scans])
    np.savez(path, sources=np.array([s for s, _, _ in scans]), offsets=offsets,
             points=np.concatenate([p for _, p, _ in scans]),
             cameras=np.stack([c for _, _, c in scans]))
    return scans


def features(scans: list, variant: str, key: str, cache: Path, enc) -> np.ndarray:  # noqa: ANN001
    """Encoder features (M, 1620) float32 of every scan in `variant`'s frame, cached."""
    digest = hashlib.sha1(f'{key},{variant}'.encode()).hexdigest()[:16]
    path = cache / f'rotation_study_{digest}.npy'
    if path.is_file():
        return np.load(path, allow_pickle=False)
    t0, rows, batch = time.process_time(), [], []
    for _, pts, cam in scans:
        batch.append(frame(*prepare_with_camera(pts, cam), variant))
        if len(batch) == 64:
            rows.append(enc.encode(torch.from_numpy(np.stack(batch))).numpy())
            batch.clear()
    if batch:
        rows.append(enc.encode(torch.from_numpy(np.stack(batch))).numpy())
    feats = np.concatenate(rows).astype(np.float32)
    np.save(path, feats)
    print(f'encoded {variant}: {len(feats)} scans, {time.process_time() - t0:.0f} s CPU',
          flush=True)
    return feats


def cv_probs(feats: np.ndarray, labels: np.ndarray, parts: list, c: int, knobs: tuple
             ) -> np.ndarray:
    """Held-out class probabilities (M, C) of every scan, each from its fold's head."""
    dims, gamma, alpha, lda_alpha, w = knobs
    f = torch.from_numpy(feats)
    probs = np.zeros((len(labels), c), dtype=np.float32)
    for va in parts:
        tr = np.setdiff1d(np.arange(len(labels)), va)
        tf = FeatureTransform.fit(f[tr], 'standardize', dims)
        z = tf(f[tr])
        lab = torch.from_numpy(labels[tr])
        head = fit_head(z, lab, c, gamma, alpha, lda_alpha, w, 1.0)
        probs[va] = reference_head(head, tf(f[va]),
                                   ExactSearch(head.vote_space(z), lab, c))[0].numpy()
    return probs


def summary(right: np.ndarray, base: np.ndarray, groups: np.ndarray, parts: list) -> dict:
    """CV accuracy, its spread over folds, and the paired difference to `base`.

    The difference's 95 % interval: bootstrap over source objects, 2,000 draws.
    """
    per_fold = [float(right[va].mean()) for va in parts]
    uniq, inv = np.unique(groups, return_inverse=True)
    diff = np.bincount(inv, right.astype(float) - base.astype(float)) / np.bincount(inv)
    rng = np.random.default_rng(0)
    boots = diff[rng.integers(0, len(uniq), (2000, len(uniq)))].mean(axis=1)
    return {'cv': float(right.mean()), 'fold_mean': float(np.mean(per_fold)),
            'fold_sd': float(np.std(per_fold, ddof=1)), 'fold_min': min(per_fold),
            'fold_max': max(per_fold), 'vs_a': float(diff.mean()),
            'vs_a_95': [float(np.quantile(boots, 0.025)), float(np.quantile(boots, 0.975))],
            'won_lost_vs_a': [int((right & ~base).sum()), int((base & ~right).sum())]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('dataset')
    p.add_argument('--cache', required=True)
    p.add_argument('--subset', type=int, default=3, help='every n-th train object')
    p.add_argument('--base-subset', type=int, default=None,
                   help='simulate/encode every n-th object (n divides --subset; default: '
                        "--subset), so a sparser study reuses a denser one's cache")
    p.add_argument('--views', type=int, default=4, help='scans per object (bank and queries)')
    p.add_argument('--variants', nargs='+', default=list(VARIANTS), choices=VARIANTS)
    p.add_argument('--knobs', nargs='+', default=list(KNOBS), choices=list(KNOBS))
    p.add_argument('--threads', type=int, default=1, help='encoder threads')
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    train = open_dataset(args.dataset, split='train')
    c = len(train.class_names)
    base = args.base_subset or args.subset
    if args.subset % base:
        raise SystemExit('--base-subset must divide --subset')
    sources = np.arange(0, len(train), base)
    enc_cfg = EncoderConfig(yaw_align=False)
    key = repr((str(Path(train.path).resolve()), 'train', base, len(train), args.views,
                SIMULATOR_VERSION, sorted(DEFAULT_VIEW_CONFIG.to_dict().items()),
                ENCODER_VERSION, enc_cfg.to_dict(), STUDY_VERSION))
    scans = cached_scans(train, sources, args.views, key, Path(args.cache))
    groups = np.array([s for s, _, _ in scans])
    keep = groups % args.subset == 0
    labels = np.asarray(train.labels)[groups].astype(np.int64)
    enc = make_encoder(enc_cfg, threads=args.threads)
    variants = ['a'] + [v for v in args.variants if v != 'a']
    feats = {v: features(scans, v, key, Path(args.cache), enc)[keep] for v in variants}
    groups, labels = groups[keep], labels[keep]
    parts = stratified_folds(labels, 5, 0, groups)
    res: dict = {'scans': len(labels), 'objects': len(np.unique(groups))}
    for kn in args.knobs:
        probs = {v: cv_probs(feats[v], labels, parts, c, KNOBS[kn]) for v in variants}
        for v in variants[1:]:      # the query encoded twice: both heads' probabilities
            probs[f'a+{v}'] = probs['a'] + probs[v]
        right = {v: pr.argmax(1) == labels for v, pr in probs.items()}
        res[kn] = {v: summary(r, right['a'], groups, parts) for v, r in right.items()}
        for v, s in res[kn].items():
            print(f"{kn:8s} {v:4s} CV {100 * s['cv']:.2f} % (folds {100 * s['fold_min']:.2f}-"
                  f"{100 * s['fold_max']:.2f}, sd {100 * s['fold_sd']:.2f}); vs a "
                  f"{100 * s['vs_a']:+.2f} [{100 * s['vs_a_95'][0]:+.2f}, "
                  f"{100 * s['vs_a_95'][1]:+.2f}] won/lost {s['won_lost_vs_a']}", flush=True)
    print(json.dumps(res))


if __name__ == '__main__':
    main()
