"""Soak and lifecycle cycles of the node under load: nothing lost, no thread or memory creep.

Starts the node (shipped bank unless --bank; --enrollment turns enrollment on), then
1. soak: queries (single-view scans of the demo objects) at --rate per second for --seconds;
   every one must be answered (reliable QoS);
2. cycles: --cycles lifecycle cycles (deactivate, cleanup, configure, activate) while queries
   keep coming at --cycle-rate per second (those sent while inactive are not answered).
Prints answered / lost, latency, the node's RSS and thread count before and after each part.

Run: python benchmarks/node_soak.py [--seconds 120] [--rate 30] [--cycles 50] [--enrollment]
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
                                              load_demo_objects, percentiles_ms,
                                              place_in_sensor_frame)


def _status(pid: int) -> tuple[float, int]:
    """(RSS MB, threads) of a process."""
    rss, threads = float('nan'), -1
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        if line.startswith('VmRSS:'):
            rss = int(line.split()[1]) / 1024
        elif line.startswith('Threads:'):
            threads = int(line.split()[1])
    return rss, threads


def _send_for(client: Client, node: NodeLauncher, objects, rng, rate: float,  # noqa: ANN001
              seconds: float, between=None) -> dict:  # noqa: ANN001
    """Queries at `rate` for `seconds` (calling between() when idle) -> key -> send time."""
    sent = {}
    t0 = time.monotonic()
    next_t = t0
    while time.monotonic() < t0 + seconds and node.alive():
        if time.monotonic() >= next_t:
            i = int(rng.integers(len(objects.labels)))
            key, t = client.send(place_in_sensor_frame(objects.xyz[i], rng, single_view=True),
                                 'sensor')
            sent[key] = t
            next_t += 1.0 / rate
        elif between is not None and between():
            pass
        else:
            client.executor.spin_once(timeout_sec=0.002)
    return sent


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--bank', default='')
    p.add_argument('--num-points', type=int, default=1024)
    p.add_argument('--seconds', type=float, default=120.0, help='soak duration')
    p.add_argument('--rate', type=float, default=30.0, help='soak queries per second')
    p.add_argument('--cycles', type=int, default=50, help='lifecycle cycles')
    p.add_argument('--cycle-rate', type=float, default=10.0, help='queries/s while cycling')
    p.add_argument('--enrollment', action='store_true', help='enable_enrollment:=true')
    args = p.parse_args()
    domain = int(os.environ.get('ROS_DOMAIN_ID') or random.randint(150, 230))
    objects = load_demo_objects()
    rng = np.random.default_rng(0)
    node = NodeLauncher({'bank_path': args.bank, 'num_points': args.num_points,
                         'input_topics': ['objects'], 'qos_reliability': 'reliable',
                         'enable_enrollment': args.enrollment}, domain)
    client = None
    ok = True
    try:
        from lifecycle_msgs.msg import Transition
        from lifecycle_msgs.srv import ChangeState
        client = Client(domain, 'objects', name='node_soak')
        if not client.wait_ready(node, 180):
            print(f'node did not come up:\n{node.log_tail()}', file=sys.stderr)
            return 1
        time.sleep(2.0)
        rss0, th0 = _status(node.pid)
        sent = _send_for(client, node, objects, rng, args.rate, args.seconds)
        client.spin_until(lambda: all(k in client.answers for k in sent), 30.0, node)
        lat = [client.answers[k].received - t for k, t in sent.items() if k in client.answers]
        lost = len(sent) - len(lat)
        p50, p99 = percentiles_ms(lat)
        rss1, th1 = _status(node.pid)
        print(f'soak {args.seconds:g} s at {args.rate:g}/s: {len(sent)} sent, {len(lat)} '
              f'answered, {lost} lost; latency p50 {p50:.1f} ms, p99 {p99:.1f} ms; RSS '
              f'{rss0:.0f} -> {rss1:.0f} MB; threads {th0} -> {th1}', flush=True)
        ok = lost == 0
        change = client.node.create_client(ChangeState, f'{NODE_FQN}/change_state')
        steps = (Transition.TRANSITION_DEACTIVATE, Transition.TRANSITION_CLEANUP,
                 Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE)
        state = {'cycle': 0, 'step': 0, 'future': None, 'failed': 0}

        def between() -> bool:
            fut = state['future']
            if fut is not None and not fut.done():
                return False
            if fut is not None and not fut.result().success:
                state['failed'] += 1
            if state['cycle'] >= args.cycles:
                return False
            state['future'] = change.call_async(ChangeState.Request(
                transition=Transition(id=steps[state['step']])))
            state['step'] = (state['step'] + 1) % len(steps)
            state['cycle'] += state['step'] == 0
            return True
        if not change.wait_for_service(timeout_sec=30):
            print('no change_state service', file=sys.stderr)
            return 1
        t0 = time.monotonic()
        sent = {}
        while (state['cycle'] < args.cycles or (state['future'] is not None
                                                and not state['future'].done())) \
                and node.alive() and time.monotonic() - t0 < 900:
            sent |= _send_for(client, node, objects, rng, args.cycle_rate, 1.0, between)
        took = time.monotonic() - t0
        sent |= _send_for(client, node, objects, rng, args.cycle_rate, 3.0)
        client.spin_until(lambda: all(k in client.answers for k in sent), 10.0, node)
        answered = sum(k in client.answers for k in sent)
        time.sleep(2.0)
        rss2, th2 = _status(node.pid)
        print(f'{state["cycle"]} lifecycle cycles in {took:.0f} s at {args.cycle_rate:g} '
              f'queries/s: {state["failed"]} transitions failed; {len(sent)} sent, {answered} '
              f'answered (none while inactive); RSS {rss1:.0f} -> {rss2:.0f} MB; threads '
              f'{th1} -> {th2}; node alive: {node.alive()}', flush=True)
        ok = ok and state['failed'] == 0 and node.alive() and th2 == th1
        return 0 if ok else 1
    finally:
        if client is not None:
            client.close()
        print(f'node stopped (exit code {node.stop()})')


if __name__ == '__main__':
    sys.exit(main())
