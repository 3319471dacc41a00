"""How fast a live enrollment takes effect, and whether any answer is lost meanwhile.

The node (its own process, real Fast DDS) classifies a steady stream of objects (default
30 objects/s, one object per message, reliable QoS); 1 s in, another process publishes the
enrollment examples of a NEW class (default 20, on ~/enroll_cloud under `enroll_class`). The
stream is scans of that same object, so once the class exists the answers name it.

Figures: effect time = from publishing the enrollment examples to receiving the first answer
that names the new class (publish -> answer through DDS, both ends in this process);
class listed = to receiving the node's new ~/class_names (the version is swapped in), and
how many answers came after it before one named the class (scans it calls something else);
answered / answered twice = stream messages answered (each must be exactly once); dropped /
errors from the node's diagnostics.

Run: python benchmarks/enroll_latency.py [--bank PATH] [--rate 30] [--examples 20] [--seconds 6]
     [--search auto|exact|indexed] [--augment d4] [--lda-prior balanced]
     [--lda-debias F] [--steal-budget RHO]
(needs the shared ModelNet40 data; ROS_DOMAIN_ID honoured via test/node_testing.py).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import sys
import tempfile
import time

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / 'test'))

from node_testing import (NODE_FQN, Harness, NodeProcess, cloud_msg, latest_diagnostics,  # noqa: E402
                          latched_qos, pick, reliable_qos, stamp, stamp_key)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--bank', default='', help="bank (default '': the shipped default bank)")
    p.add_argument('--rate', type=float, default=30.0, help='stream objects per second')
    p.add_argument('--examples', type=int, default=20, help='enrollment examples')
    p.add_argument('--seconds', type=float, default=6.0, help='stream duration')
    p.add_argument('--search', default='auto', choices=('auto', 'exact', 'indexed'),
                   help="the node's bank search parameter")
    p.add_argument('--augment', default='none', choices=('none', 'mirror', 'rot4', 'd4'),
                   help='node parameter enroll_augment (frames stored per example)')
    p.add_argument('--lda-prior', default='entries', choices=('entries', 'balanced', 'typical'),
                   help='node parameter enroll_lda_prior')
    p.add_argument('--lda-debias', type=float, default=0.0,
                   help='node parameter enroll_lda_debias (wide-LDA banks)')
    p.add_argument('--steal-budget', type=float, default=0.0,
                   help='node parameter enroll_steal_budget (bank/discriminant.py)')
    p.add_argument('--json', default=None)
    args = p.parse_args(argv)

    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import String

    from point_gn_ros.core.views import simulate_views
    from point_gn_ros.pointcloud2 import decode_classifications

    xyz, _ = pick('test', ('sofa',), 1)
    views = [v.points * 0.8 + np.float32(3.0) for v in simulate_views(xyz[0], 40, seed=3)]
    examples, stream = views[:args.examples], views[args.examples:]
    log = Path(tempfile.mkdtemp(prefix='enroll_latency_')) / 'node.log'
    node = NodeProcess({'bank_path': args.bank, 'input_topics': ['objects'],
                        'qos_reliability': 'reliable', 'qos_depth': 200, 'queue_size': 400,
                        'enable_enrollment': True, 'enroll_class': 'my_sofa',
                        'search': args.search,
                        'enroll_augment': args.augment,
                        'enroll_lda_prior': args.lda_prior,
                        'enroll_lda_debias': float(args.lda_debias),
                        'enroll_steal_budget': float(args.steal_budget)}, log)
    h = Harness('enroll_latency')
    try:
        pub = h.node.create_publisher(PointCloud2, 'objects', reliable_qos(400))
        pub_enroll = h.node.create_publisher(PointCloud2, f'{NODE_FQN}/enroll_cloud',
                                             reliable_qos(100))
        answers: list = []                               # (arrival time, message)
        h.node.create_subscription(PointCloud2, f'{NODE_FQN}/classifications',
                                   lambda m: answers.append((time.monotonic(), m)),
                                   reliable_qos(1000))
        names = h.collect(String, f'{NODE_FQN}/class_names', latched_qos())
        names_at: list[tuple[float, str]] = []            # (arrival time, class list)
        h.node.create_subscription(String, f'{NODE_FQN}/class_names',
                                   lambda m: names_at.append((time.monotonic(), m.data)),
                                   latched_qos())
        diags = h.collect(DiagnosticArray, '/diagnostics', reliable_qos(50))
        h.wait_for_subscribers([pub, pub_enroll], node, timeout=120.0)
        h.spin_for(1.0)
        n = int(args.rate * args.seconds)
        sent: dict[tuple[int, int], float] = {}
        t0 = time.monotonic()
        t_enroll = None
        for i in range(n):
            while time.monotonic() < t0 + i / args.rate:
                h.executor.spin_once(timeout_sec=0.001)
            key = (10_000 + i, 0)
            pub.publish(cloud_msg(stream[i % len(stream)], 'base_link', stamp(*key)))
            sent[key] = time.monotonic()
            if t_enroll is None and time.monotonic() - t0 >= 1.0:
                t_enroll = time.monotonic()
                for ex in examples:
                    pub_enroll.publish(cloud_msg(ex, 'base_link', stamp(1, 0)))
        h.spin_until(lambda: {stamp_key(m.header) for _, m in answers} >= set(sent), 60.0)
        h.spin_for(1.5)                                  # one more diagnostics period
        got: dict = {}
        for t, m in answers:
            got.setdefault(stamp_key(m.header), []).append((t, m))
        cls = names[-1].data.split('\n') if names else []
        new_id = cls.index('my_sofa') if 'my_sofa' in cls else -2
        named = sorted(ms[0][0] for k, ms in got.items() if k in sent
                       and int(decode_classifications(ms[0][1])['class_id'][0]) == new_id)
        listed = [t for t, data in names_at if 'my_sofa' in data.split('\n')]
        # answers after the new class list: how many before one names the class (a scan of
        # the enrolled object is not always called it)
        after = sorted(ms[0] for k, ms in got.items() if k in sent and listed
                       and ms[0][0] >= listed[0])
        misses = next((i for i, (_, m) in enumerate(after)
                       if int(decode_classifications(m)['class_id'][0]) == new_id), None)
        pipe = latest_diagnostics(diags, ': pipeline')
        enr = latest_diagnostics(diags, ': enrollment')
        out = {
            'bank': args.bank or 'default', 'rate_hz': args.rate, 'examples': args.examples,
            'stream_messages': n, 'answered': sum(1 for k in sent if k in got),
            'answered_twice': sum(1 for k in sent if len(got.get(k, [])) > 1),
            'effect_s': (named[0] - t_enroll) if named and t_enroll else None,
            'class_listed_s': (listed[0] - t_enroll) if listed and t_enroll else None,
            'answers_after_listing_before_named': misses,
            'node_enroll_latency_s': enr.get('enroll_last_latency_s'),
            'dropped': pipe.get('dropped'), 'errors': pipe.get('errors'),
            'latency_receipt_p99_ms': pipe.get('latency_receipt_p99_ms'),
            'bank_version': enr.get('bank_version'),
        }
        print(json.dumps(out, indent=2))
        if args.json:
            Path(args.json).write_text(json.dumps(out, indent=2) + '\n')
    finally:
        h.close()
        node.stop()
    return 0


if __name__ == '__main__':
    sys.exit(main())
