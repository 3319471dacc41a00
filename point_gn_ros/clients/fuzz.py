"""Fuzz the classifier node over DDS: seeded valid and invalid clouds, every answer checked.

`run_fuzz()` builds a small synthetic bank (no data outside the package), starts the node as
its own process (reliable QoS, a queue deep enough that nothing is dropped), and publishes
`fuzz_messages.generate(seed, count)` at a sustainable rate: never more than `window` valid
messages unanswered. It then checks that

* every valid message is answered exactly once, with the expected segment ids;
* no invalid message is answered (each is counted as rejected);
* every `/diagnostics` report satisfies
  ``received = answered + dropped + rejected + failed + in_flight``, and the last one has
  received = sent, answered = valid, rejected = invalid, dropped = failed = in_flight = 0.

``python -m point_gn_ros.clients.fuzz --count 10000`` (``make fuzz``); exit code 0 when every
check holds. test/node/test_node_fuzz.py runs 2,000 in CI.
"""

from __future__ import annotations

import argparse
from collections import Counter
import json
from pathlib import Path
import random
import sys
import tempfile
import time
from typing import Any

import numpy as np

from point_gn_ros.clients.fuzz_messages import SEGMENT_FIELD, FuzzCase, Limits, generate

TOPIC = 'fuzz_objects'
NODE_FQN = '/point_gn_classifier'
NUM_POINTS = 128          # small encoder: the fuzz checks plumbing, not accuracy
SHAPES = ('box', 'ball', 'rod', 'plate')


def node_params(bank_path: Path, limits: Limits) -> dict[str, Any]:
    """Node parameters of the fuzz run (limits must match the generator's)."""
    return {'bank_path': str(bank_path), 'num_points': NUM_POINTS, 'input_topics': [TOPIC],
            'segment_field': SEGMENT_FIELD, 'min_points': limits.min_points,
            'max_points_per_message': limits.max_points,
            'max_objects_per_message': limits.max_objects, 'queue_size': 2000,
            'qos_reliability': 'reliable', 'qos_depth': 1000, 'max_batch': 16,
            'torch_threads': 1, 'encoder_threads': 1}


class _Shapes:
    """Synthetic dataset (Dataset contract): a few shape classes, seeded, unit-size."""

    def __init__(self, per_class: int = 6, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        self.class_names = list(SHAPES)
        self.path, self.split, self.format = 'synthetic-shapes', 'train', 'synthetic'
        self.labels = np.repeat(np.arange(len(SHAPES)), per_class)
        self._xyz = [self._make(int(c), rng) for c in self.labels]

    @staticmethod
    def _make(c: int, rng: np.random.Generator, n: int = 400) -> np.ndarray:
        if c == 0:
            xyz = rng.uniform(-0.5, 0.5, (n, 3))
        elif c == 1:
            v = rng.normal(size=(n, 3))
            xyz = v / np.linalg.norm(v, axis=1, keepdims=True)
        elif c == 2:
            xyz = np.c_[rng.normal(0, 0.05, (n, 2)), rng.uniform(-1, 1, n)]
        else:
            xyz = np.c_[rng.uniform(-1, 1, (n, 2)), rng.normal(0, 0.02, n)]
        return (xyz * rng.uniform(0.8, 1.2, 3)).astype(np.float32)

    def __len__(self) -> int:
        return len(self.labels)

    def __getitem__(self, i: int) -> tuple[np.ndarray, int]:
        return self._xyz[i], int(self.labels[i])


def synthetic_bank(path: Path) -> Path:
    """A 4-class bank of synthetic shapes at NUM_POINTS points (seconds to build)."""
    from point_gn_ros.bank.builder import build_bank
    from point_gn_ros.core.config import EncoderConfig

    bank = build_bank(_Shapes(), EncoderConfig(num_points=NUM_POINTS, k=16), folds=2,
                      progress=False, gammas=(10.0, 100.0), standardize_options=('none',))
    return bank.save(path, dtype='float32')


def _identity(d: dict[str, str]) -> int:
    """Received minus (answered + dropped + rejected + failed + in_flight) of one report."""
    return int(d['received']) - sum(int(d[k]) for k in ('answered', 'dropped', 'rejected',
                                                         'failed', 'in_flight'))


def default_domain_id() -> int:
    """ROS_DOMAIN_ID when set (whoever shares the machine chose it), else a random 150-230."""
    import os
    value = os.environ.get('ROS_DOMAIN_ID', '').strip()
    return int(value) if value.isdigit() else random.randint(150, 230)


def run_fuzz(count: int = 2000, seed: int = 0, window: int = 8, limits: Limits | None = None,
             domain_id: int | None = None, timeout_s: float = 600.0) -> dict[str, Any]:
    """Publish `count` fuzz cases to a fresh node and check every answer; returns a report.

    report['ok'] is True when every check holds; report['problems'] lists the others.
    """
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from point_gn_ros.clients.node_client import Client, NodeLauncher

    limits = limits or Limits()
    domain_id = domain_id if domain_id is not None else default_domain_id()
    work = Path(tempfile.mkdtemp(prefix='point_gn_fuzz_'))
    cases: list[FuzzCase] = list(generate(seed, count, limits))
    bank = synthetic_bank(work / 'fuzz_bank.npz')
    node = NodeLauncher(node_params(bank, limits), domain_id, log_path=work / 'node.log')
    client = Client(domain_id, TOPIC, reliable=True, name='point_gn_fuzz')
    answers: Counter[tuple[int, int]] = Counter()
    segments: dict[tuple[int, int], tuple[int, ...]] = {}
    reports: list[dict[str, str]] = []

    def on_answer(msg: Any) -> None:
        from point_gn_ros.pointcloud2 import decode_classifications
        key = (msg.header.stamp.sec, msg.header.stamp.nanosec)
        answers[key] += 1
        segments[key] = tuple(int(s) for s in decode_classifications(msg)['segment_id'])

    def on_diag(msg: Any) -> None:
        for st in msg.status:
            if st.name == f'{NODE_FQN}: pipeline':
                reports.append({kv.key: kv.value for kv in st.values})

    reliable = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    client.node.create_subscription(PointCloud2, f'{NODE_FQN}/classifications', on_answer,
                                    reliable)
    client.node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, reliable)
    problems: list[str] = []
    t0 = time.monotonic()
    try:
        if not client.wait_ready(node, 120.0):
            raise RuntimeError(f'node not ready:\n{node.log_tail()}')
        client.spin_until(lambda: bool(reports), 5.0, node)
        t_send = time.monotonic()
        outstanding: list[tuple[int, int]] = []
        sent = 0
        for case in cases:
            if case.valid:
                # Sustainable rate: at most `window` valid messages waiting for an answer.
                def room() -> bool:
                    outstanding[:] = [k for k in outstanding if not answers[k]]
                    return len(outstanding) < window
                if not client.spin_until(room, 60.0, node):
                    problems.append(f'no answer for 60 s at case {case.index}')
                    break
                outstanding.append(case.stamp)
            client.publisher.publish(case.msg)
            sent += 1
            client.executor.spin_once(timeout_sec=0)
        valid = [c for c in cases[:sent] if c.valid]
        invalid = [c for c in cases[:sent] if not c.valid]

        def settled() -> bool:
            d = reports[-1] if reports else {}
            return bool(d) and int(d['received']) >= sent and int(d['in_flight']) == 0 and \
                all(answers[c.stamp] for c in valid)
        client.spin_until(settled, min(timeout_s, 60.0), node)
        send_s = time.monotonic() - t_send
        client.spin_until(lambda: False, 1.5, node)    # one more report, late duplicates
    finally:
        client.close()
        code = node.stop()
    final = reports[-1] if reports else {}
    lost = [c for c in valid if not answers[c.stamp]]
    wrong = [c for c in valid if answers[c.stamp] and segments[c.stamp] != c.expected_segments]
    answered_invalid = [c for c in invalid if answers[c.stamp]]
    dupes = sum(n - 1 for n in answers.values() if n > 1)
    bad_reports = [d for d in reports if _identity(d) != 0]
    if lost:
        problems.append(f'{len(lost)} valid message(s) not answered, e.g. '
                        f'{[(c.index, c.kind) for c in lost[:5]]}')
    if wrong:
        problems.append(f'{len(wrong)} answer(s) with wrong segment ids, e.g. '
                        f'{[(c.index, c.kind) for c in wrong[:5]]}')
    if answered_invalid:
        problems.append(f'{len(answered_invalid)} invalid message(s) answered, e.g. '
                        f'{[(c.index, c.kind) for c in answered_invalid[:5]]}')
    if dupes:
        problems.append(f'{dupes} duplicate answer(s)')
    if bad_reports or not reports:
        problems.append(f'identity broken in {len(bad_reports)} of {len(reports)} reports')
    expect = {'received': sent, 'answered': len(valid), 'rejected': len(invalid),
              'dropped': 0, 'failed': 0, 'in_flight': 0}
    got = {k: int(final.get(k, -1)) for k in expect}
    if got != expect:
        problems.append(f'final diagnostics {got} != expected {expect}')
    if code != 0:
        problems.append(f'node exit code {code}')
    return {
        'ok': not problems, 'problems': problems, 'seed': seed, 'count': count,
        'sent': sent, 'valid': len(valid), 'invalid': len(invalid),
        'answered_valid': len(valid) - len(lost), 'lost_valid': len(lost),
        'answered_invalid': len(answered_invalid), 'duplicates': dupes,
        'wrong_segments': len(wrong), 'reports': len(reports),
        'identity_violations': len(bad_reports), 'send_s': round(send_s, 1),
        'rate_msgs_per_s': round(sent / max(send_s, 1e-9), 1),
        'wall_s': round(time.monotonic() - t0, 1), 'window': window,
        'kinds': dict(sorted(Counter(c.kind for c in cases[:sent]).items())),
        'final_diagnostics': {k: v for k, v in final.items()
                              if not k.startswith(('latency', 'input', 'processed_rate',
                                                   'objects_rate'))},
        'node_exit_code': code, 'node_log': str(node.log_path),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--count', type=int, default=10000, help='messages (default 10000)')
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--window', type=int, default=8,
                    help='most valid messages unanswered at once (default 8)')
    ap.add_argument('--json', default=None, metavar='REPORT.json')
    args = ap.parse_args(argv)
    report = run_fuzz(args.count, args.seed, args.window)
    text = json.dumps(report, indent=2)
    if args.json:
        Path(args.json).write_text(text + '\n')
    print(text)
    return 0 if report['ok'] else 1


if __name__ == '__main__':
    sys.exit(main())
