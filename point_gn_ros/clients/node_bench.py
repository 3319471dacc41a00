"""End-to-end benchmark of the classifier node through DDS.

`bench_node()` starts the node as its own process (as deployed: default QoS, queue and
threads unless overridden), publishes held-out test objects at fixed input rates and then
as fast as possible, and measures what comes back: throughput, latency (publish ->
answer received, both on this machine's monotonic clock), unanswered (dropped) messages,
and the node's peak RSS. Called by `point_gn bench`; needs no data outside the package.
"""

from __future__ import annotations

from collections.abc import Sequence
import os
import random
import time
from typing import Any

import numpy as np

from point_gn_ros.clients.node_client import (DEMO_OBJECTS, Client, NodeLauncher,
                                              load_demo_objects, percentiles_ms,
                                              place_in_sensor_frame)

TOPIC = 'bench_objects'
FRAME = 'bench_sensor'
BURST_HZ = 1000.0        # "as fast as possible": far above any CPU encoder's rate
SLOT_HZ = 200.0          # the publisher's wake-ups a second at most


def _run_phase(client: Client, node: NodeLauncher, clouds: Sequence[np.ndarray], rate_hz: float,
               duration_s: float, drain_s: float) -> dict[str, Any]:
    """Publish at rate_hz for duration_s, then wait up to drain_s for the last answers."""
    period = 1.0 / rate_hz
    sent: dict[tuple[int, int], float] = {}
    taken0 = int(client.fresh_counters().get('received', -1))
    cpu0, own0 = node.cpu_s(), time.process_time()
    start = time.monotonic()
    next_t = start
    i = 0
    # The answers come in on the client's intake thread: this one only sends, and sleeps
    # until the next send slot. Above SLOT_HZ a slot holds several messages, sent back to
    # back: each sleep costs a wake-up, and 1,000 a second took a tenth of a CPU here.
    per_slot = max(1, round(rate_hz / SLOT_HZ))
    while time.monotonic() - start < duration_s and node.alive():
        for _ in range(per_slot):
            key, t = client.send(clouds[i % len(clouds)], FRAME)
            sent[key] = t
            i += 1
        next_t += per_slot * period
        remaining = next_t - time.monotonic()
        if remaining > 0:
            time.sleep(remaining)
    end_send, own1 = time.monotonic(), time.process_time()

    def all_in() -> bool:
        return all(k in client.answers for k in sent)

    # Drain: stop once everything is answered or no new answer came for a while.
    last_count, last_change = -1, time.monotonic()
    while time.monotonic() - end_send < drain_s and not all_in() and node.alive():
        time.sleep(0.02)
        n = sum(k in client.answers for k in sent)
        if n != last_count:
            last_count, last_change = n, time.monotonic()
        elif time.monotonic() - last_change > 2.0:
            break
    got = [(client.answers[k].received, client.answers[k].received - t)
           for k, t in sent.items() if k in client.answers]
    latencies = [lat for _, lat in got]
    p50, p99 = percentiles_ms(latencies)
    finished = max((r for r, _ in got), default=end_send)
    elapsed = max(finished - start, 1e-9)
    cpu1 = node.cpu_s()
    taken1 = int(client.fresh_counters().get('received', -1))
    return {
        'duration_s': round(end_send - start, 3),
        'sent': len(sent),
        'answered': len(got),
        'dropped': len(sent) - len(got),
        'input_hz': round(len(sent) / max(end_send - start, 1e-9), 2),
        'throughput_hz': round(len(got) / elapsed, 2),
        'latency_p50_ms': round(p50, 2),
        'latency_p99_ms': round(p99, 2),
        # Node CPU per answered message: what the node costs, whatever else the box runs.
        'node_cpu_ms_per_answer': round(1e3 * (cpu1 - cpu0) / max(len(got), 1), 2),
        # This process (publisher and answer intake) while sending, in CPUs: what the
        # measurement itself takes from the machine the node runs on.
        'client_cpus': round((own1 - own0) / max(end_send - start, 1e-9), 3),
        # What the node took off DDS (its 'received' counter; -1: no /diagnostics report).
        # sent - taken were lost before the node saw them (a full reader history);
        # taken - answered the node dropped from its queue, and counted.
        'node_taken': taken1 - taken0 if min(taken0, taken1) >= 0 else -1,
    }


def bench_node(rates: Sequence[float] = (10, 30, 100), duration_s: float = 10.0,
               burst: bool = True, bank_path: str = '', num_points: int = 0,
               params: dict[str, Any] | None = None, domain_id: int | None = None,
               objects_path: str | os.PathLike[str] = DEMO_OBJECTS,
               start_timeout_s: float = 180.0, drain_s: float = 30.0,
               verbose: bool = False) -> list[dict[str, Any]]:
    """Measure the node end to end at each input rate, then (burst=True) at maximum rate.

    Returns one dict per phase: mode ('rate' | 'burst'), target_hz, input_hz (achieved),
    duration_s, sent, answered, dropped (sent - answered: dropped by the node's queues or
    lost), node_taken (messages the node took off DDS, by its /diagnostics counters; -1
    without a report), throughput_hz (answers per second from first send to last answer),
    latency_p50_ms / latency_p99_ms (publish -> answer received), node_cpu_ms_per_answer
    (node process CPU time over the phase / answers), node_peak_rss_mb (VmHWM of the node
    process after that phase; cumulative), plus node_startup_s and the node parameters
    used. Raises RuntimeError if the node does not start.
    """
    from point_gn_ros.clients.demo import _bank_num_points

    objects = load_demo_objects(objects_path)
    rng = np.random.default_rng(0)
    clouds = [place_in_sensor_frame(x, rng) for x in objects.xyz]
    if domain_id is None:
        domain_id = random.randint(150, 230)
    node_params: dict[str, Any] = {
        'bank_path': bank_path, 'num_points': num_points or _bank_num_points(bank_path),
        'input_topics': [TOPIC], **(params or {})}
    t0 = time.monotonic()
    node = NodeLauncher(node_params, domain_id, passthrough=verbose)
    client = None
    rows: list[dict[str, Any]] = []
    try:
        # Reliable: what the node subscribes with by default (qos_reliability).
        client = Client(domain_id, TOPIC, reliable=True, name='point_gn_bench')
        if not client.wait_ready(node, start_timeout_s):
            raise RuntimeError(f'classifier node did not start (exit code {node.proc.poll()}):'
                               f'\n{node.log_tail()}')
        startup = time.monotonic() - t0
        client.spin_until(lambda: False, 0.5)   # let the answer side match as well
        # Warm: one object end to end before measuring.
        key, _ = client.send(clouds[0], FRAME)
        client.spin_until(lambda: key in client.answers, drain_s, node)
        phases = [('rate', float(r)) for r in rates] + ([('burst', BURST_HZ)] if burst else [])
        for mode, hz in phases:
            row = {'mode': mode, 'target_hz': hz}
            row.update(_run_phase(client, node, clouds, hz, duration_s, drain_s))
            row['node_peak_rss_mb'] = round(node.peak_rss_mb(), 1)
            row['node_startup_s'] = round(startup, 2)
            row['node_params'] = {k: v for k, v in node_params.items() if k != 'input_topics'}
            rows.append(row)
            if verbose:
                print(row, flush=True)
            client.spin_until(lambda: False, 1.0)   # let queues empty between phases
    finally:
        if client is not None:
            client.close()
        node.stop()
    return rows


def format_rows(rows: Sequence[dict[str, Any]]) -> str:
    """A plain-text table of bench_node() results."""
    head = (f'{"mode":<6} {"target":>7} {"input":>7} {"sent":>5} {"answered":>8} '
            f'{"dropped":>7} {"taken":>6} {"thru/s":>7} {"p50 ms":>8} {"p99 ms":>8} {"CPU ms":>7} '
            f'{"RSS MB":>7} {"client":>6}')
    lines = [head]
    for r in rows:
        lines.append(f'{r["mode"]:<6} {r["target_hz"]:>7g} {r["input_hz"]:>7.1f} '
                     f'{r["sent"]:>5} {r["answered"]:>8} {r["dropped"]:>7} '
                     f'{r["node_taken"]:>6} '
                     f'{r["throughput_hz"]:>7.1f} {r["latency_p50_ms"]:>8.1f} '
                     f'{r["latency_p99_ms"]:>8.1f} {r["node_cpu_ms_per_answer"]:>7.2f} '
                     f'{r["node_peak_rss_mb"]:>7.0f} {r["client_cpus"]:>6.2f}')
    return '\n'.join(lines)


def bench_rows(quick: bool = False, **kwargs: Any) -> list[dict[str, Any]]:
    """bench_node() as `point_gn bench` rows: dicts of section, what, value, unit, note.

    quick: rates 10 and 30 Hz for 3 s each (plus the burst); else 10, 30, 100 Hz for 10 s.
    A node that cannot start gives one row with value NaN and the reason in the note.
    """
    rates, duration = ((10, 30), 3.0) if quick else ((10, 30, 100), 10.0)
    try:
        results = bench_node(rates=kwargs.pop('rates', rates),
                             duration_s=kwargs.pop('duration_s', duration), **kwargs)
    except (RuntimeError, OSError) as exc:
        return [dict(section='node', what='classifier node end to end', value=float('nan'),
                     unit='', note=str(exc).splitlines()[0])]
    rows: list[dict[str, Any]] = []
    for r in results:
        label = f'node {r["target_hz"]:g} Hz in' if r['mode'] == 'rate' else 'node burst'
        note = (f'{r["answered"]}/{r["sent"]} answered, {r["node_taken"]} taken by the node, '
                f'{r["dropped"]} dropped, input '
                f'{r["input_hz"]:.0f}/s, reliable, DDS, 1 process; the publishing client '
                f'{r["client_cpus"]:.2f} CPU')
        rows += [dict(section='node', what=f'{label}: answered', value=r['throughput_hz'],
                      unit='msg/s', note=note),
                 dict(section='node', what=f'{label}: latency p50', value=r['latency_p50_ms'],
                      unit='ms', note='publish -> answer received'),
                 dict(section='node', what=f'{label}: latency p99', value=r['latency_p99_ms'],
                      unit='ms', note=''),
                 dict(section='node', what=f'{label}: node CPU per answer',
                      value=r['node_cpu_ms_per_answer'], unit='ms',
                      note='node process user+system CPU over the phase / answers')]
    if results:
        params = results[-1]['node_params']
        rows.append(dict(section='node', what='node peak RSS', value=results[-1][
            'node_peak_rss_mb'], unit='MB', note=f'VmHWM; startup {results[-1]["node_startup_s"]}'
                                                 f' s; params {params}'))
    return rows


if __name__ == '__main__':
    import argparse

    parser = argparse.ArgumentParser(description='End-to-end classifier node benchmark.')
    parser.add_argument('--rates', type=float, nargs='*', default=[10, 30, 100])
    parser.add_argument('--duration', type=float, default=10.0)
    parser.add_argument('--bank', default='')
    parser.add_argument('--no-burst', action='store_true')
    parser.add_argument('-p', '--param', action='append', default=[],
                        help='extra node parameter name=value (repeatable)')
    a = parser.parse_args()
    extra = dict(kv.split('=', 1) for kv in a.param)
    print(format_rows(bench_node(a.rates, a.duration, not a.no_burst, a.bank, params=extra)))
