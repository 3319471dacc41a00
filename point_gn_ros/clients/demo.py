"""`make demo`: the classifier node with the shipped bank, fed held-out ModelNet40 objects.

Starts the node as its own process (default bank unless --bank), publishes the test
objects shipped in point_gn_ros/data/demo_objects.npz (one per class) one at a time in a
sensor frame (metres, translated, turned by a random yaw, a little noise): each object whole,
then as a single-view scan (only the side facing the sensor, noisy and sparser, simulated by
core/views.py), prints each answer (true label, prediction, score, end-to-end latency) and a
summary for both kinds, then stops the node with Ctrl-C semantics (SIGINT). Needs nothing
outside the package: no ../shared, no network.

With --enrollment the node is started with `enable_enrollment:=true` (off by default: with
it on, any peer on the ROS domain can change the bank) and, after the run, the demo teaches
it one new class live: 5 scans of the first object published on ~/enroll_cloud under the
name `my_<class>`, then 3 other scans of it are classified again.
"""

from __future__ import annotations

import argparse
import os
import random
import sys
import time

import numpy as np

from point_gn_ros.clients.node_client import (DEMO_OBJECTS, Client, NodeLauncher,
                                              load_demo_objects, percentiles_ms,
                                              place_in_sensor_frame)

TOPIC = 'demo_objects'
FRAME = 'demo_sensor'
KINDS = ('complete', 'scan')


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='python -m point_gn_ros.clients.demo',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('--bank', default='', help="feature bank .npz ('' = the shipped default)")
    p.add_argument('--objects', default=str(DEMO_OBJECTS), help='demo objects .npz')
    p.add_argument('--count', type=int, default=0, help='objects to send (0 = all)')
    p.add_argument('--num-points', type=int, default=0,
                   help='node num_points (0 = read it from the bank)')
    p.add_argument('--domain-id', type=int, default=None,
                   help='ROS domain (default: $ROS_DOMAIN_ID, else a random private one)')
    p.add_argument('--timeout', type=float, default=120.0,
                   help='seconds to wait for the node to start, and for each answer')
    p.add_argument('--seed', type=int, default=0, help='sensor-frame placement seed')
    p.add_argument('--node-log', action='store_true', help="show the node's log as it runs")
    p.add_argument('--no-random-yaw', dest='random_yaw', action='store_false',
                   help='keep the dataset heading (default: each object turned by a random yaw; '
                        'the shipped bank is yaw-aligned)')
    p.add_argument('--kinds', nargs='+', choices=KINDS, default=list(KINDS),
                   help='what to send of each object: the complete cloud, a single-view scan, '
                        'or both (default both)')
    p.add_argument('--enrollment', action='store_true',
                   help='start the node with enable_enrollment:=true and teach it one new '
                        'class live after the run (docs/NODE.md "Enrollment")')
    return p


TAUGHT = 'my_object'


def _teach(client: Client, node: NodeLauncher, objects, rng: np.random.Generator,  # noqa: ANN001
           timeout: float) -> bool:
    """Teach the first demo object as a new class over ~/enroll_cloud; show the answers."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from point_gn_ros.clients.node_client import NODE_FQN
    from point_gn_ros.pointcloud2 import decode_classifications
    true = objects.class_names[int(objects.labels[0])]
    pub = client.node.create_publisher(PointCloud2, f'{NODE_FQN}/enroll_cloud',
                                       QoSProfile(depth=100,
                                                  reliability=ReliabilityPolicy.RELIABLE))
    if not client.spin_until(lambda: pub.get_subscription_count() > 0, timeout, node):
        print('error: the node offers no ~/enroll_cloud (enable_enrollment)', file=sys.stderr)
        return False
    print(f'\nteaching: 5 scans of object #1 (a {true}) on {NODE_FQN}/enroll_cloud as '
          f'{TAUGHT!r} (parameter enroll_class)')
    from builtin_interfaces.msg import Time
    from std_msgs.msg import Header

    from point_gn_ros.pointcloud2 import xyz_to_pointcloud2
    for i in range(5):
        xyz = place_in_sensor_frame(objects.xyz[0], rng, yaw=float(rng.uniform(0, 6.28)),
                                    single_view=True)
        pub.publish(xyz_to_pointcloud2(Header(frame_id=FRAME, stamp=Time(sec=1, nanosec=i)),
                                       xyz))
    if not client.spin_until(lambda: TAUGHT in (client.class_names or []), timeout, node):
        print(f'error: {TAUGHT!r} did not appear in ~/class_names', file=sys.stderr)
        return False
    names = client.class_names
    print(f'{TAUGHT!r} is class {names.index(TAUGHT)} of {len(names)}; 3 other scans of it:')
    for _ in range(3):
        xyz = place_in_sensor_frame(objects.xyz[0], rng, yaw=float(rng.uniform(0, 6.28)),
                                    single_view=True)
        key, _ = client.send(xyz, FRAME)
        if not client.spin_until(lambda k=key: k in client.answers, timeout, node):
            print('  (no answer)')
            return False
        res = decode_classifications(client.answers[key].msg)
        cid = int(res['class_id'][0])
        print(f'  predicted {names[cid] if 0 <= cid < len(names) else "unknown"} '
              f'{float(res["score"][0]):.2f}')
    return True


def _bank_num_points(bank: str) -> int:
    """The bank's encoder num_points, read from its metadata only (no features loaded)."""
    import json
    from pathlib import Path

    from point_gn_ros.bank.store import default_bank_path
    path = Path(bank) if bank else default_bank_path()
    try:
        with np.load(path, allow_pickle=False) as z:
            return int(json.loads(z['meta'].tobytes().decode())['encoder_config']['num_points'])
    except Exception:  # noqa: BLE001 - the node itself reports a bad bank clearly
        return 1024


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    objects = load_demo_objects(args.objects)
    count = len(objects.labels) if args.count <= 0 else min(args.count, len(objects.labels))
    domain = args.domain_id
    if domain is None:
        env = os.environ.get('ROS_DOMAIN_ID')
        domain = int(env) if env else random.randint(150, 230)
    num_points = args.num_points or _bank_num_points(args.bank)

    print(f'starting the classifier node (ROS domain {domain}, bank '
          f"{args.bank or 'shipped default'}) ...", flush=True)
    params = {'bank_path': args.bank, 'num_points': num_points, 'input_topics': [TOPIC],
              'qos_reliability': 'reliable'}
    if args.enrollment:        # off by default: any peer on the domain could teach the node
        params |= {'enable_enrollment': True, 'enroll_class': TAUGHT}
    node = NodeLauncher(params, domain, passthrough=args.node_log)
    client = None
    try:
        client = Client(domain, TOPIC, reliable=True, name='point_gn_demo')
        t0 = time.monotonic()
        if not client.wait_ready(node, args.timeout):
            print(f'error: the node did not come up (exit code {node.proc.poll()}):\n'
                  f'{node.log_tail()}', file=sys.stderr)
            return 1
        print(f'node ready in {time.monotonic() - t0:.1f} s; '
              f'{len(client.class_names or [])} classes; sending {count} held-out ModelNet40 '
              f'test objects on /{TOPIC} (frame {FRAME})\n', flush=True)
        names = client.class_names or []
        rng = np.random.default_rng(args.seed)
        correct = dict.fromkeys(args.kinds, 0)
        sent_n = dict.fromkeys(args.kinds, 0)
        latencies, missing = [], 0
        print(f'{"#":>4}  {"kind":<8} {"points":>6}  {"true":<12} {"predicted":<12} {"score":>5}'
              f'  {"latency":>10}')
        for i, kind in ((i, k) for i in range(count) for k in args.kinds):
            yaw = float(rng.uniform(0, 2 * np.pi)) if args.random_yaw else 0.0
            true = objects.class_names[int(objects.labels[i])]
            xyz = place_in_sensor_frame(objects.xyz[i], rng, yaw=yaw,
                                        single_view=kind == 'scan', class_name=true)
            key, sent = client.send(xyz, FRAME)
            if not client.spin_until(lambda k=key: k in client.answers, args.timeout, node):
                missing += 1
                print(f'{i + 1:>4}  {kind:<8} {len(xyz):>6}  {true:<12} '
                      f'(no answer within {args.timeout:g} s)')
                if not node.alive():
                    break
                continue
            from point_gn_ros.pointcloud2 import decode_classifications
            ans = client.answers[key]
            res = decode_classifications(ans.msg)
            cid, score = int(res['class_id'][0]), float(res['score'][0])
            pred = names[cid] if 0 <= cid < len(names) else 'unknown'
            latency = ans.received - sent
            latencies.append(latency)
            correct[kind] += pred == true
            sent_n[kind] += 1
            print(f'{i + 1:>4}  {kind:<8} {len(xyz):>6}  {true:<12} {pred:<12} {score:5.2f}  '
                  f"{latency * 1e3:7.1f} ms  {'ok' if pred == true else 'WRONG'}", flush=True)
        p50, p99 = percentiles_ms(latencies)
        print()
        for kind in args.kinds:
            print(f'accuracy ({kind}) {correct[kind]}/{sent_n[kind]} = '
                  f'{100.0 * correct[kind] / max(sent_n[kind], 1):.1f} %')
        print(f'latency p50 {p50:.1f} ms, p99 {p99:.1f} ms'
              + (f', {missing} unanswered' if missing else ''))
        ok = missing == 0 and node.alive()
        if args.enrollment:
            ok = _teach(client, node, objects, rng, args.timeout) and ok
    except KeyboardInterrupt:
        print('\ninterrupted')
        ok = False
    finally:
        if client is not None:
            client.close()
        code = node.stop()
    print(f'node stopped (exit code {code})')
    return 0 if ok and code == 0 else 1


if __name__ == '__main__':
    sys.exit(main())
