"""Every bad bank of the reliability campaign (issue 10) is refused with one clear reason.

Each case rewrites a valid bank file; loading must raise one BankError naming the file and
the reason, `point_gn bank info` must exit 2 with one `point_gn: error:` line, and the node
must print one FATAL line and exit 1 (a few cases, over a real process).
"""

from __future__ import annotations

import json
from pathlib import Path
import time

import numpy as np
import pytest
import torch

from node_testing import NodeProcess

from point_gn_ros.bank.store import FeatureBank
from point_gn_ros.bank.model import FeatureTransform
from point_gn_ros.bank.store import META_MAX_BYTES, META_MAX_DEPTH, parse_meta
from point_gn_ros.cli import main as cli_main
from point_gn_ros.core.config import EncoderConfig
from point_gn_ros.errors import BankError

CFG = EncoderConfig(num_points=64, k=16)


def _good(path: Path) -> Path:
    raw = torch.randn(12, CFG.feature_dim)
    tf = FeatureTransform.fit(raw, 'none', None)
    bank = FeatureBank(features=tf(raw), labels=torch.arange(12) % 3,
                       class_names=['a', 'b', 'c'], config=CFG, transform=tf, gamma=20.0,
                       meta={'unknown_calibration': {'threshold': 0.5}})
    return bank.save(path, dtype='float32')


def _rewrite(path: Path, meta_bytes: bytes | None = None, **changes) -> Path:
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays['meta'].tobytes())
    for key, value in changes.items():
        if key.startswith('cfg_'):
            meta['encoder_config'][key[4:]] = value
        elif key.startswith('meta_'):
            meta[key[5:]] = value
        else:
            arrays[key] = value
    raw = meta_bytes if meta_bytes is not None else json.dumps(meta).encode()
    arrays['meta'] = np.frombuffer(raw, np.uint8)
    np.savez(path, **arrays)
    return path


def _nested(depth: int) -> bytes:
    good = json.dumps({'format_version': 1}).encode()[:-1]
    return good + b', "x": ' + b'[' * depth + b']' * depth + b'}'


# name -> (rewrite kwargs, reason in the error)
BAD_BANKS: dict[str, tuple[dict, str]] = {
    'sigma 1e-30': ({'cfg_sigma': 1e-30}, r'sigma=1e-30 is out of range'),
    'sigma inf': ({'cfg_sigma': 'inf'}, r'sigma must be a number'),
    'k > num_points': ({'cfg_k': 65}, r'k=65 neighbours is more than num_points=64'),
    'k zero': ({'cfg_k': 0}, r'k=0 is out of range'),
    'k float': ({'cfg_k': 16.5}, r'k must be an integer'),
    'num_points huge': ({'cfg_num_points': 2**24}, r'num_points=16777216 is out of range'),
    'stages 40': ({'cfg_stages': 40}, r'stages=40 is out of range'),
    'init_dim bool': ({'cfg_init_dim': True}, r'init_dim must be a number'),
    'yaw_align string': ({'cfg_yaw_align': 'yes'}, r'yaw_align must be true or false'),
    'extra sigma zero': ({'cfg_extra_sigmas': [0.0]}, r'extra_sigmas=0.0 is out of range'),
    'extra sigmas a string': ({'cfg_extra_sigmas': '0.25'},
                              r'extra_sigmas must be a list of at most 3 numbers'),
    'too many extra sigmas': ({'cfg_extra_sigmas': [0.3] * 4},
                              r'extra_sigmas must be a list of at most 3'),
    'upsample unknown': ({'cfg_upsample': 'cubic'},
                         r"upsample must be one of \['repeat', 'midpoint'\], got 'cubic'"),
    'class_names a string': ({'meta_class_names': 'x' * 3},
                             r'class_names must be a list of strings, got str'),
    'class_names numbers': ({'meta_class_names': [1, 2, 3]}, r'a list with int'),
    'class name with a newline': ({'meta_class_names': ['a', 'b\nc', 'd']},
                                  r'single lines'),
    'duplicate class names': ({'meta_class_names': ['a', 'b', 'a']}, r'not unique: a'),
    'empty class': ({'labels': (np.arange(12) % 2).astype(np.int32)},
                    r'1 class\(es\) have no entries: c'),
    'gamma nan': ({'meta_gamma': float('nan')}, r'gamma must be a finite number'),
    'threshold string': ({'meta_unknown_calibration': {'threshold': 'high'}},
                         r'unknown threshold must be a finite number'),
    'zero feature row': ({'features': np.zeros((12, CFG.feature_dim), np.float32)},
                         r'12 feature row\(s\) are all zero'),
    'non-finite features': ({'features': np.full((12, CFG.feature_dim), np.inf, np.float32)},
                            r'features holds non-finite values'),
    'deeply nested metadata': ({'meta_bytes': _nested(100_000)},
                               rf'nests 100001 levels deep, more than the limit of '
                               rf'{META_MAX_DEPTH}'),
    'huge metadata': ({'meta_bytes': b'{"pad": "' + b'x' * META_MAX_BYTES + b'"}'},
                      r'bytes, more than the limit'),
}


@pytest.mark.parametrize('name', list(BAD_BANKS))
def test_bad_bank_is_refused_with_its_reason(tmp_path: Path, name: str,
                                             capsys: pytest.CaptureFixture) -> None:
    changes, reason = BAD_BANKS[name]
    path = _rewrite(_good(tmp_path / 'bank.npz'), **changes)
    with pytest.raises(BankError, match=reason) as err:
        FeatureBank.load(path)
    assert str(err.value).startswith(f'{path}: ') and '\n' not in str(err.value)
    assert cli_main(['bank', 'info', str(path)]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('point_gn: error: ')


def test_good_bank_passes_and_limits_are_not_hit_by_the_shipped_bank(tmp_path: Path) -> None:
    assert FeatureBank.load(_good(tmp_path / 'ok.npz')).num_classes == 3
    shipped = FeatureBank.load(None)     # the shipped default bank is well inside every limit
    assert shipped.num_classes == 40


def test_depth_scan_ignores_brackets_inside_strings() -> None:
    text = json.dumps({'a': '[[[[' * 100 + '\\"{{{{', 'b': [[1]]}).encode()
    assert parse_meta(np.frombuffer(text, np.uint8))['b'] == [[1]]


def test_node_refuses_bad_banks_with_one_fatal_line(tmp_path: Path) -> None:
    names = ('sigma 1e-30', 'class_names a string', 'deeply nested metadata', 'empty class')
    procs = {}
    for i, name in enumerate(names):
        changes, _ = BAD_BANKS[name]
        path = _rewrite(_good(tmp_path / f'bank{i}.npz'), **changes)
        procs[name] = NodeProcess({'bank_path': str(path), 'num_points': CFG.num_points},
                                  tmp_path / f'node{i}.log')
    t0 = time.monotonic()
    try:
        for name, proc in procs.items():
            rc = proc.wait(60.0)
            log = proc.log()
            fatal = [ln for ln in log.splitlines() if '[FATAL]' in ln]
            assert rc == 1 and len(fatal) == 1, f'{name}: exit {rc}\n{log}'
            assert 'cannot start' in fatal[0] and 'Traceback' not in log, log
    finally:
        for proc in procs.values():
            proc.stop(timeout=5)
    assert time.monotonic() - t0 < 60.0
