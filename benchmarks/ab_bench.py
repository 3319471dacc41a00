"""`point_gn bench` of two checkouts, interleaved, reported as B / A ratios per figure.

On a shared machine two runs taken one after the other mostly measure the load change
between them. This script alternates the two checkouts round by round (A B, then B A, ...),
each run a fresh process of `point_gn bench --json` with that checkout's package first on
PYTHONPATH (so one venv may serve both), and reports every figure's median over the rounds
for A and B and their ratio B / A. Figures in msg/s or clouds/s are rates: a ratio above 1
is faster there; for times (ms) below 1 is faster.

    python benchmarks/ab_bench.py ../start-checkout . --rounds 3
    python benchmarks/ab_bench.py OLD NEW --rounds 3 --sections encoder classifier node \
        --json ab.json -- --repeats 3

Each checkout runs with CHECKOUT/.venv/bin/python unless --python-a / --python-b name
another interpreter. Arguments after `--` go to `point_gn bench`. Runs are `nice`d.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import statistics
import subprocess
import sys
import time


def _run(checkout: Path, python: str, extra: list[str], nice: int) -> dict:
    """One `point_gn bench --json` of `checkout`: its JSON (info, rows)."""
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join(
        [str(checkout), *([env['PYTHONPATH']] if env.get('PYTHONPATH') else [])])
    cmd = ['nice', '-n', str(nice), python, '-m', 'point_gn_ros.cli', 'bench', '--json', *extra]
    done = subprocess.run(cmd, cwd=checkout, env=env, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f'{checkout}: point_gn bench failed ({done.returncode}):\n'
                         f'{done.stderr[-2000:]}')
    return json.loads(done.stdout)


def _build_kernels(checkout: Path, python: str) -> None:
    """Load the checkout's kernels (built on a cache miss): no round's start-up pays one."""
    env = dict(os.environ, PYTHONPATH=str(checkout))
    subprocess.run([python, '-c', 'from point_gn_ros.core import kernels; kernels.load()'],
                   cwd=checkout, env=env, check=True)


def _key(row: dict) -> tuple[str, str, str]:
    return row['section'], row['what'].strip(), row['unit']


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    extra: list[str] = []
    if '--' in argv:
        cut = argv.index('--')
        argv, extra = argv[:cut], argv[cut + 1:]
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('a', type=Path, help='checkout A (the baseline)')
    ap.add_argument('b', type=Path, help='checkout B (the change)')
    ap.add_argument('--rounds', type=int, default=3)
    ap.add_argument('--python-a', help='interpreter for A (default A/.venv/bin/python)')
    ap.add_argument('--python-b', help='interpreter for B (default B/.venv/bin/python)')
    ap.add_argument('--sections', nargs='*', default=None,
                    help='report only these sections (default: all)')
    ap.add_argument('--nice', type=int, default=10)
    ap.add_argument('--json', type=Path, help='also write every run and the ratios here')
    args = ap.parse_args(argv)

    sides = {'A': (args.a.resolve(), args.python_a or str(args.a / '.venv/bin/python')),
             'B': (args.b.resolve(), args.python_b or str(args.b / '.venv/bin/python'))}
    for checkout, python in sides.values():
        _build_kernels(checkout, python)
    runs: dict[str, list[dict]] = {'A': [], 'B': []}
    for r in range(args.rounds):
        for side in ('A', 'B') if r % 2 == 0 else ('B', 'A'):
            checkout, python = sides[side]
            t0 = time.monotonic()
            runs[side].append(_run(checkout, python, extra, args.nice))
            load = runs[side][-1].get('info', {}).get('load_average_end')
            print(f'round {r + 1}/{args.rounds} {side} ({checkout}): '
                  f'{time.monotonic() - t0:.0f} s, load at end {load}', file=sys.stderr,
                  flush=True)

    values: dict[str, dict[tuple[str, str, str], list[float]]] = {'A': {}, 'B': {}}
    order: list[tuple[str, str, str]] = []
    for side, got in runs.items():
        for run in got:
            for row in run['rows']:
                key = _key(row)
                if args.sections and key[0] not in args.sections:
                    continue
                if key not in order:
                    order.append(key)
                values[side].setdefault(key, []).append(float(row['value']))
    table = []
    print(f'{"section":<11} {"figure":<52} {"unit":<9} {"A median":>10} {"B median":>10} '
          f'{"B / A":>7}')
    for key in order:
        a, b = values['A'].get(key), values['B'].get(key)
        if not a or not b:
            continue
        ma, mb = statistics.median(a), statistics.median(b)
        ratio = mb / ma if ma else float('nan')
        table.append(dict(section=key[0], what=key[1], unit=key[2], a=a, b=b, a_median=ma,
                          b_median=mb, ratio=ratio))
        print(f'{key[0]:<11} {key[1][:52]:<52} {key[2]:<9} {ma:>10.4g} {mb:>10.4g} '
              f'{ratio:>7.3f}')
    if args.json:
        out = dict(a=str(sides['A'][0]), b=str(sides['B'][0]), rounds=args.rounds,
                   bench_args=extra, runs=runs, figures=table)
        tmp = args.json.with_name(args.json.name + '.tmp')
        tmp.write_text(json.dumps(out, indent=1))
        os.replace(tmp, args.json)  # atomic
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
