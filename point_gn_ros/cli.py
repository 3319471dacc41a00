"""`point_gn` command line: bank, eval, fewshot, classify, bench, bag, replay.

Each sub-command lives in its own module exposing `register(subparsers)`; the
module is imported only when listed here, and its heavy imports happen inside
its command function so `point_gn --help` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

# Modules that register sub-commands, in the order they appear in --help.
COMMAND_MODULES = (
    'point_gn_ros.commands.bank_cmd',
    'point_gn_ros.commands.enroll_cmd',      # bank add|remove: after bank_cmd
    'point_gn_ros.commands.eval_cmd',
    'point_gn_ros.commands.classify_cmd',
    'point_gn_ros.commands.bench_cmd',
    'point_gn_ros.commands.bag_cmd',
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='point_gn',
        description='Point-GN training-free point-cloud classification: banks, evaluation, '
                    'benchmarks and rosbag tools.')
    sub = parser.add_subparsers(dest='command', required=True, metavar='COMMAND')
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:
                raise
            continue  # a command module not written yet
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # The reader went away (`point_gn ... | head`): no traceback, and none at exit when
        # Python flushes stdout again (the recipe of Python's signal docs).
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except Exception as exc:  # noqa: BLE001 - one clear line for users, not a traceback
        from point_gn_ros.errors import PointGNError
        if isinstance(exc, PointGNError):
            print(f'point_gn: error: {exc}', file=sys.stderr)
            return 2
        raise


if __name__ == '__main__':
    sys.exit(main())
