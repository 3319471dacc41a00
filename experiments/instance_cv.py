"""Choose the enrolled classes' LDA debias share and steal budget by CV on the TRAIN split only.

Pseudo-enrollment on the default bank's own objects (no test object is read):
- each round takes, per ModelNet10 category, one train object as a pseudo "new instance" and
  `--others` further random train objects as existing-class queries; all of them are taken
  out of both sections of the bank (their complete entry and their HPR scans: 4 or 8);
- the pseudo-instances go through experiments/enroll_study.py's protocol on TRAIN objects: 5 HPR
  scans each (evenly spread azimuths) enrolled as new classes '<category>_object_<i>' through
  `add_examples` with the study's refit policy, `--query-views` other scans queried (other
  seeds: other azimuths, noise, dropout);
- existing classes: the other objects' complete entries and scans (raw features from the bank
  build's feature cache, `make default-bank CACHE=...`: the bank's own scans of each; or, with
  `--other-scans random`, one new scan from a random viewpoint as enroll_study's existing-class
  scans), classified before and after the enrollment; the drop counts right-before-wrong-after
  minus the reverse.
The grid's first axis was the vote prior's exponent beta; CV chose 0 and the vote prior was
removed (CHANGELOG), so beta is 0 throughout. The rule picks the largest instance accuracy whose
existing-class drop stays <= --max-drop points on complete objects AND scans.
Both sections' LDA is refitted without the held-out objects before anything is measured (as
an enrollment refits it), with the build's entry-share priors; the enrollments refit with
`--lda-prior`, so a prior that moves the built classes' answers counts in the drop (as in
enroll_study.py's test protocol; before 2026-12-02's fifth session the 'before' bank had the
tested prior too). The gate and the other knobs keep their build values.
With `--new-categories K` the new classes are new CATEGORIES instead (a user's own kind of
object): each round draws K of the 40 categories, takes every train object of them out of the
bank and their classes with them (`remove_class`), and enrolls one object of each.

Run: python experiments/instance_cv.py --cache DIR [--rounds 4] [--json OUT]
"""

from __future__ import annotations

import argparse
import hashlib
from dataclasses import replace
import json
from pathlib import Path
import sys

import numpy as np
import torch

from point_gn_ros.bank.discriminant import fit_ridge
from point_gn_ros.bank.builder import feature_cache_path
from point_gn_ros.bank.classifier import Classifier
from point_gn_ros.bank.discriminant import fit_object_test
from point_gn_ros.bank.enroll import BankFile, add_examples, remove_class
from point_gn_ros.bank.refit import RefitPolicy, refit
from point_gn_ros.bank.refit import enrolled_debias
from point_gn_ros.core.config import ENCODER_VERSION
from point_gn_ros.core.fusion import fused_examples
from point_gn_ros.core.views import (SIMULATOR_VERSION, VIEW_PROTOCOLS, simulate_view,
                                     simulate_views)
from point_gn_ros.datasets import open_dataset
from point_gn_ros.datasets.views import ViewsDataset
from point_gn_ros.recognizer import encode_clouds, make_encoder

from enroll_study import misregistered  # noqa: I001 - experiments/ is on sys.path when run

MODELNET = Path(__file__).resolve().parents[2] / 'shared' / 'datasets' / 'modelnet40_1024'
MODELNET10 = ('bathtub', 'bed', 'chair', 'desk', 'dresser', 'monitor', 'night_stand', 'sofa',
              'table', 'toilet')
BETAS = (0.0,)


def subset(bf: BankFile, keep_obj: np.ndarray, raw: np.ndarray) -> BankFile:
    """The bank without some train objects: keep_obj (S,) bool over the source objects.

    raw: the build's cached features (S * per, D), complete then scans per object: a wide
    LDA's class means lose the removed rows (its covariance is kept, as an enrollment does);
    the object test, if any, is fitted again without the removed objects.
    """
    per = len(raw) // len(keep_obj)
    vk = np.repeat(keep_obj, per - 1)
    gone = np.flatnonzero(~keep_obj)
    b, v = bf.bank, bf.views.bank
    scan_rows = (per * gone[:, None] + np.arange(1, per)).ravel()
    views = replace(v, features=v.features[torch.from_numpy(vk)],
                    labels=v.labels[torch.from_numpy(vk)],
                    head=without_rows(v, raw[scan_rows], v.labels[torch.from_numpy(~vk)]))
    head = without_rows(b, raw[per * gone], b.labels[torch.from_numpy(~keep_obj)])
    keep = torch.from_numpy(keep_obj)
    if head is not None and head.ridge_coef is not None:   # refitted without them, in full
        head = replace(head, ridge_coef=fit_ridge(b.features[keep], b.labels[keep],
                                                  b.num_classes, head.ridge_gamma,
                                                  head.ridge_lambda))
    objects = b.objects
    if objects is not None:     # ObjectTest, refitted on the kept objects' scans alone
        rows = (per * np.flatnonzero(keep_obj)[:, None] + np.arange(1, per)).ravel()
        objects = fit_object_test(v.transform.standardized(torch.from_numpy(raw[rows])),
                                 np.repeat(np.flatnonzero(keep_obj), per - 1),
                                 views.labels.numpy(), b.class_names, objects.rank,
                                 objects.alpha, objects.lam, objects.theta)
    main = replace(b, features=b.features[keep], labels=b.labels[keep], views=views, head=head,
                   objects=objects)
    return BankFile(main, bf.stored[keep_obj], views=BankFile(views, bf.views.stored[vk]))


def without_rows(bank, raw_rows: np.ndarray, labels: torch.Tensor):  # noqa: ANN001, ANN201
    """The section's head with a wide LDA's class means less the rows raw_rows (m, D)."""
    head = bank.head
    if head is None or not head.lda_wide:
        return head
    x = bank.transform.standardized(torch.from_numpy(np.asarray(raw_rows))).double()
    n = torch.bincount(bank.labels, minlength=bank.num_classes).double()
    m = torch.bincount(labels, minlength=bank.num_classes).double()
    sums = head.lda_means.double() * n[:, None]
    sums.index_add_(0, labels, -x)
    return replace(head, lda_means=(sums / (n - m).clamp_min(1)[:, None]).float())


def refitted(bf: BankFile, policy: RefitPolicy) -> BankFile:
    """Both sections refitted as an enrollment would (the LDA without the removed objects).

    The clean 'before': the built LDA still holds the held-out objects' own rows.
    """
    v, moved_v = refit(bf.views.bank, policy)
    m, moved_m = refit(bf.bank, policy)
    assert not (moved_v or moved_m), 'kept knobs never move the stored rows'
    return BankFile(replace(m, views=v), bf.stored, views=BankFile(v, bf.views.stored)
                    ).with_stats()


def with_beta(bf: BankFile, beta: float, names: list[str], scope: str) -> BankFile:
    """The bank as it is: the vote prior (beta > 0) no longer exists."""
    if beta:
        raise SystemExit('the vote prior was removed: beta must be 0')
    return bf


def with_debias(bf: BankFile, f: float, budget: float = 0.0) -> BankFile:
    """Both sections with the enrolled classes' wide-LDA mean-noise correction.

    As RefitPolicy(lda_debias=f, lda_steal_budget=budget) gives it (bank/refit.py
    `enrolled_debias`; enrolled = not in the build's provenance), on banks refitted without.
    """
    policy = RefitPolicy(lda_debias=f, lda_steal_budget=budget)

    def put(bank):  # noqa: ANN001, ANN202
        head = bank.head
        if f == 0 or head is None or not head.lda_wide:
            return bank
        n = torch.bincount(bank.labels, minlength=bank.num_classes)
        head, _ = enrolled_debias(head, n, np.arange(bank.num_classes), bank, bank.meta, policy)
        return replace(bank, head=head)
    views = put(bf.bank.views)
    return BankFile(replace(put(bf.bank), views=views), bf.stored,
                    views=BankFile(views, bf.views.stored))


def key(g: tuple[float, float, float]) -> str:
    """Table key of (beta, debias, budget): 'b=1.2', 'b=1.2,f=0.5' or 'b=1.2,f=1.5,rho=0.002'."""
    return f'b={g[0]:g}' + (f',f={g[1]:g}' if g[1] else '') + (f',rho={g[2]:g}' if g[2] else '')


def predict(bf: BankFile, feats: torch.Tensor) -> np.ndarray:
    return Classifier(bf.bank, search='exact').classify(feats).labels


def scans(train, inst: list[int], query_views: int, cache: str, encoder  # noqa: ANN001
          ) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Encoded 5 enrollment scans and `query_views` query scans of each train object in inst.

    Seeds as experiments/enroll_study.py's (object i: enrollment seed i, queries seed 1000 + i).
    """
    key = hashlib.sha1(repr((encoder.cfg.to_dict(), ENCODER_VERSION, SIMULATOR_VERSION, inst,
                             query_views)).encode()).hexdigest()[:16]
    path = Path(cache) / f'instance_cv_{key}.npz'
    if path.is_file():
        with np.load(path) as z:
            return ([torch.from_numpy(z[f'e{o}']) for o in inst],
                    [torch.from_numpy(z[f'q{o}']) for o in inst])
    enroll, query = [], []
    for o in inst:
        obj = train[o][0]
        enroll.append(encode_clouds([v.points for v in simulate_views(obj, 5, seed=o)], encoder))
        query.append(encode_clouds([v.points for v in simulate_views(
            obj, query_views, seed=1000 + o)], encoder))
    np.savez(path, **{f'e{o}': e.numpy() for o, e in zip(inst, enroll, strict=True)},
             **{f'q{o}': q.numpy() for o, q in zip(inst, query, strict=True)})
    return enroll, query


def random_scans(train, objs: np.ndarray, cache: str, encoder) -> torch.Tensor:  # noqa: ANN001
    """One scan of each object from a random viewpoint, seeded as enroll_study's (seed [7, i])."""
    key = hashlib.sha1(repr((encoder.cfg.to_dict(), ENCODER_VERSION, SIMULATOR_VERSION,
                             'random', [int(o) for o in objs])).encode()).hexdigest()[:16]
    path = Path(cache) / f'instance_cv_{key}.npy'
    if path.is_file():
        return torch.from_numpy(np.load(path))
    cfg = VIEW_PROTOCOLS['hpr'][0]
    feats = encode_clouds([simulate_view(train[int(o)][0], np.random.default_rng([7, int(o)]),
                                         cfg).points for o in objs], encoder)
    np.save(path, feats.numpy())
    return feats


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--cache', required=True)
    p.add_argument('--data', default=str(MODELNET))
    p.add_argument('--rounds', type=int, default=4)
    p.add_argument('--query-views', type=int, default=10)
    p.add_argument('--others', type=int, default=150)
    p.add_argument('--max-drop', type=float, default=1.0)
    p.add_argument('--lda-prior', choices=('entries', 'balanced', 'typical'), default='entries')
    p.add_argument('--scope', choices=('enrolled', 'all'), default='enrolled')
    p.add_argument('--betas', type=float, nargs='+', default=list(BETAS))
    p.add_argument('--debias', type=float, nargs='+', default=[0.0],
                   help='fractions f of the wide LDA mean-noise correction of enrolled classes '
                        '(bank/discriminant.py lda_noise_trace), each crossed with every beta')
    p.add_argument('--budgets', type=float, nargs='+', default=[0.0],
                   help='steal budgets rho (RefitPolicy.lda_steal_budget, bank/discriminant; 0 = '
                        'the uniform share), each crossed with every debias share (the cap)')
    p.add_argument('--other-scans', choices=('bank', 'random'), default='bank',
                   help="existing-class scans: the bank's own scans of each held-out object, "
                        "or one scan from a random viewpoint (enroll_study's existing-class "
                        'protocol, seed [7, object])')
    p.add_argument('--fuse-views', action='store_true',
                   help="also enroll core/fusion.py's examples from each pseudo-instance's 5 "
                        "scans fused (enroll_study.py --fuse-views, same registration error)")
    p.add_argument('--pose-noise', type=float, default=1.0, metavar='S',
                   help='registration error scale of --fuse-views (enroll_study.py)')
    p.add_argument('--new-categories', type=int, default=0, metavar='K',
                   help='enroll one object of each of K categories taken out of the bank '
                        'whole (new kinds of object), instead of one instance per ModelNet10 '
                        'category')
    p.add_argument('--json', default=None)
    p.add_argument('--bank', default=None, help='bank (default: the shipped default bank)')
    args = p.parse_args(argv)

    bf = BankFile.load(args.bank)
    train = open_dataset(args.data, split='train')
    labels = np.asarray(train.labels)
    n_obj = len(labels)
    views = len(bf.views.bank) // n_obj                 # scans per object in the bank
    # The bank build's cached raw features (complete, then its scans, per train object).
    built = ViewsDataset(train, views, 0, VIEW_PROTOCOLS['hpr'][0], include_full=True,
                         random_yaw=True)
    raw = np.load(feature_cache_path(built, bf.bank.config, args.cache), mmap_mode='r')
    per = views + 1                                     # rows per object: (per S, D)
    assert raw.shape[0] == per * n_obj and np.array_equal(
        bf.views.bank.labels.numpy(), np.repeat(labels, views)), 'feature cache / bank mismatch'
    policy = RefitPolicy(gamma='auto', lda_prior=args.lda_prior)
    built = RefitPolicy(gamma='auto')
    encoder = make_encoder(bf.bank.config)
    grid = [(b, f, rho) for rho in args.budgets for f in args.debias for b in args.betas
            if not (rho and not f)]
    res = {g: {'inst': [], 'complete': [], 'scan': []} for g in grid}
    for r in range(args.rounds):
        rng = np.random.default_rng(100 + r)
        cats = MODELNET10 if not args.new_categories else tuple(
            str(c) for c in rng.choice(train.class_names, args.new_categories, replace=False))
        inst = [int(rng.choice(np.flatnonzero(labels == train.class_names.index(c))))
                for c in cats]
        gone = np.isin(labels, [train.class_names.index(c) for c in cats]) \
            if args.new_categories else np.zeros(n_obj, dtype=bool)
        others = rng.choice(np.setdiff1d(np.flatnonzero(~gone), inst), args.others,
                            replace=False)
        keep = ~gone
        keep[inst] = keep[others] = False
        cur = subset(bf, keep, raw)
        for c in cats if args.new_categories else ():      # now classes without entries
            cur = remove_class(cur, c, source='instance_cv', policy=built).file
        # 'before' is the bank as built (entry-share priors), as enroll_study's test protocol
        # has it; the enrollments below refit with the policy under test.
        cur = refitted(cur, built)
        if args.new_categories:     # the removals left the ridge term pending: the 'before'
            cur = cur      # state is the one the robot keeps
        # dataset class id -> the bank's (removing classes shifts the ids after them)
        bank_id = np.array([cur.bank.class_names.index(n) if n in cur.bank.class_names else -1
                            for n in train.class_names])
        q_full = torch.from_numpy(np.asarray(raw[per * others]))
        if args.other_scans == 'bank':
            q_scan = torch.from_numpy(np.concatenate([raw[per * o + 1:per * o + per]
                                                      for o in others]))
            t_scan = np.repeat(bank_id[labels[others]], views)
        else:
            q_scan = random_scans(train, others, args.cache, encoder)
            t_scan = bank_id[labels[others]]
        t_full = bank_id[labels[others]]
        right0 = {'complete': predict(cur, q_full) == t_full,
                  'scan': predict(cur, q_scan) == t_scan}
        enroll, query = scans(train, inst, args.query_views, args.cache, encoder)
        names, q_ids = [], []
        for c, o, f in zip(cats, inst, enroll, strict=True):
            name = f'{c}_object_{o}'
            if args.fuse_views:     # the same 5 scans (seed o), fused after a pose error
                obj = train[o][0]
                seen = misregistered([v.points for v in simulate_views(obj, 5, seed=o)], obj,
                                     args.pose_noise, o)
                f = torch.cat([f, encode_clouds(fused_examples(seen, seed=o), encoder)])
            cur = add_examples(cur, f, name, source='instance_cv', policy=policy).file
            names.append(name)
            q_ids += [cur.bank.class_names.index(name)] * args.query_views
        # A kernel ridge term is refitted in full after the enrollments, as the node's
        # background refit does (bank/live.py): the state the robot keeps.
        cur = cur
        q_inst, q_ids = torch.cat(query), np.asarray(q_ids)
        for b, fd, rho in grid:
            bb = with_beta(with_debias(cur, fd, rho), b, names, args.scope)
            res[b, fd, rho]['inst'].append(float((predict(bb, q_inst) == q_ids).mean()))
            for kind, q, t in (('complete', q_full, t_full), ('scan', q_scan, t_scan)):
                now = predict(bb, q) == t
                res[b, fd, rho][kind].append(100 * float((right0[kind] & ~now).mean()
                                                    - (~right0[kind] & now).mean()))
        print(f'round {r}: ' + ', '.join(
            f'{key(g)} inst {res[g]["inst"][-1]:.3f} drop {res[g]["complete"][-1]:.2f}/'
            f'{res[g]["scan"][-1]:.2f}' for g in grid), file=sys.stderr)
    table = {key(g): {'instance_accuracy': float(np.mean(v['inst'])),
                      'drop_complete_points': float(np.mean(v['complete'])),
                      'drop_scan_points': float(np.mean(v['scan'])),
                      # the rounds' spread: how far one draw of 10 objects may land
                      'round_std': {k: float(np.std(v[k], ddof=1)) if len(v[k]) > 1 else 0.0
                                    for k in ('inst', 'complete', 'scan')}}
             for g, v in res.items()}
    ok = [g for g in grid if table[key(g)]['drop_complete_points'] <= args.max_drop
          and table[key(g)]['drop_scan_points'] <= args.max_drop]
    chosen = max(ok, key=lambda g: (table[key(g)]['instance_accuracy'], -g[0], -g[1], g[2])) \
        if ok else (0.0, 0.0, 0.0)
    out = {'rounds': args.rounds, 'others': args.others, 'scope': args.scope,
           'new_categories': args.new_categories,
           'fuse_views': args.fuse_views, 'pose_noise': args.pose_noise,
           'other_scans': args.other_scans,
           'lda_prior': args.lda_prior, 'max_drop': args.max_drop, 'table': table,
           'chosen_beta': chosen[0], 'chosen_debias': chosen[1], 'chosen_budget': chosen[2]}
    print(json.dumps(out, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2) + '\n')
    return 0


if __name__ == '__main__':
    sys.exit(main())
