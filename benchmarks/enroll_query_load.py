"""Query latency while enrollment teaches many new classes (docs/NODE.md "Enrollment").

Starts the node (shipped bank unless --bank) with enable_enrollment, sends queries (single-view
scans of the demo objects) at --rate per second for the whole run, and after --warmup seconds
teaches --classes new classes, one every --every seconds: set `enroll_class`, publish
--examples scans on ~/enroll_cloud. Prints the query latency (publish -> answer received)
before and while teaching, the time until every class is listed, the node's RSS and its
enrollment counters.

Run: python benchmarks/enroll_query_load.py [--classes 100] [--rate 10] [--examples 5]
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import random
import sys
import time

import numpy as np

from point_gn_ros.clients.node_client import (NODE_FQN, Client, NodeLauncher,
                                              load_demo_objects, place_in_sensor_frame)


def _rss_mb(pid: int) -> float:
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        if line.startswith('VmRSS:'):
            return int(line.split()[1]) / 1024
    return float('nan')


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--bank', default='', help="bank .npz ('' = the shipped default)")
    p.add_argument('--num-points', type=int, default=1024)
    p.add_argument('--classes', type=int, default=100)
    p.add_argument('--examples', type=int, default=5, help='examples per new class')
    p.add_argument('--rate', type=float, default=10.0, help='queries per second')
    p.add_argument('--every', type=float, default=0.5, help='seconds between two classes')
    p.add_argument('--warmup', type=float, default=10.0, help='seconds of queries first')
    p.add_argument('--tail', type=float, default=10.0, help='seconds of queries after')
    p.add_argument('--seed', type=int, default=0)
    args = p.parse_args()
    domain = int(os.environ.get('ROS_DOMAIN_ID') or random.randint(150, 230))
    objects = load_demo_objects()
    rng = np.random.default_rng(args.seed)
    node = NodeLauncher({'bank_path': args.bank, 'num_points': args.num_points,
                         'input_topics': ['objects'], 'qos_reliability': 'reliable',
                         'enable_enrollment': True, 'enroll_class': 'new_0'}, domain)
    client = None
    try:
        from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
        from rcl_interfaces.srv import SetParameters
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2
        from std_msgs.msg import Header
        from builtin_interfaces.msg import Time

        from point_gn_ros.pointcloud2 import xyz_to_pointcloud2
        client = Client(domain, 'objects', name='enroll_query_load')
        enroll = client.node.create_publisher(PointCloud2, f'{NODE_FQN}/enroll_cloud',
                                              QoSProfile(depth=100,
                                                         reliability=ReliabilityPolicy.RELIABLE))
        params = client.node.create_client(SetParameters, f'{NODE_FQN}/set_parameters')
        if not client.wait_ready(node, 180) or not client.spin_until(
                lambda: enroll.get_subscription_count() > 0, 60, node):
            print(f'node did not come up:\n{node.log_tail()}', file=sys.stderr)
            return 1
        built = len(client.class_names)
        rss0 = _rss_mb(node.pid)
        sent: dict[tuple[int, int], tuple[float, str]] = {}
        t0 = time.monotonic()
        teach_start = t0 + args.warmup
        teach_end = teach_start + args.classes * args.every
        end = teach_end + args.tail
        next_query, next_class, taught = t0, teach_start, 0
        all_listed = None
        while time.monotonic() < end:
            now = time.monotonic()
            if now >= next_query:
                i = int(rng.integers(len(objects.labels)))
                xyz = place_in_sensor_frame(objects.xyz[i], rng, single_view=True)
                phase = 'before' if now < teach_start else (
                    'teaching' if now < teach_end else 'after')
                key, t_sent = client.send(xyz, 'sensor')
                sent[key] = (t_sent, phase)
                next_query += 1.0 / args.rate
            elif taught < args.classes and now >= next_class:
                name = f'new_{taught}'
                req = SetParameters.Request(parameters=[Parameter(
                    name='enroll_class', value=ParameterValue(
                        type=ParameterType.PARAMETER_STRING, string_value=name))])
                fut = params.call_async(req)
                client.spin_until(fut.done, 5.0)
                obj = objects.xyz[taught % len(objects.labels)]
                for j in range(args.examples):
                    xyz = place_in_sensor_frame(obj * float(rng.uniform(0.8, 1.2)), rng,
                                                single_view=True)
                    enroll.publish(xyz_to_pointcloud2(
                        Header(frame_id='sensor', stamp=Time(sec=10_000 + taught,
                                                             nanosec=j)), xyz))
                taught += 1
                next_class += args.every
            else:
                client.executor.spin_once(timeout_sec=0.002)
            if all_listed is None and taught == args.classes and \
                    len(client.class_names or []) >= built + args.classes:
                all_listed = time.monotonic() - teach_start
        client.spin_until(lambda: all(k in client.answers for k in sent), 30.0)
        if all_listed is None and client.spin_until(
                lambda: len(client.class_names or []) >= built + args.classes, 120.0):
            all_listed = time.monotonic() - teach_start
        rss1 = _rss_mb(node.pid)
        lat: dict[str, list[float]] = {'before': [], 'teaching': [], 'after': []}
        lost = 0
        for key, (t_sent, phase) in sent.items():
            ans = client.answers.get(key)
            if ans is None:
                lost += 1
            else:
                lat[phase].append((ans.received - t_sent) * 1e3)
        print(f'node: bank {args.bank or "shipped default"}, {built} built classes; '
              f'queries at {args.rate:g}/s; {args.classes} new classes x {args.examples} '
              f'examples, one every {args.every:g} s')
        for phase, values in lat.items():
            if values:
                p50, p99, mx = np.percentile(values, [50, 99, 100])
                print(f'  queries {phase:<9} n={len(values):4d}  p50 {p50:6.1f} ms  '
                      f'p99 {p99:6.1f} ms  max {mx:6.1f} ms')
        print(f'  unanswered queries: {lost}')
        when = 'NOT all listed' if all_listed is None else \
            f'all listed {all_listed:.1f} s after the first was sent'
        print(f'  classes: {len(client.class_names or [])} ({args.classes} new: {when})')
        print(f'  node RSS {rss0:.0f} -> {rss1:.0f} MB')
        client.spin_until(lambda: False, 2.0)      # a fresh /diagnostics report
        print(f'  pipeline counters: dropped {client.counters.get("dropped")}, errors '
              f'{client.counters.get("errors")}')
        return 0 if lost == 0 else 1
    finally:
        if client is not None:
            client.close()
        print(f'node stopped (exit code {node.stop()})')


if __name__ == '__main__':
    sys.exit(main())
