"""How many large object clouds reach the node at each input reliability (docs/NODE.md, QoS).

For each reliability, the node runs as deployed (shipped bank) with that `qos_reliability`;
a client with the matching publisher QoS (best effort = the sensor-data profile, as a driver
would; reliable otherwise) sends `--count` clouds of each size, 0.3 s apart, and counts the
answers. Clouds are a held-out demo object resampled with jitter to the size (x, y, z, rgb:
16 bytes a point). Localhost Fast DDS, this machine's load.

    python benchmarks/qos_fragmentation.py --sizes-kb 64 640 4900 --count 6
"""

from __future__ import annotations

import argparse
import random

import numpy as np

from point_gn_ros.clients.node_client import (DEMO_OBJECTS, Client, NodeLauncher,
                                              load_demo_objects, place_in_sensor_frame)

TOPIC = 'qos_objects'


def measure(reliability: str, sizes_kb: list[int], count: int, domain_id: int) -> list[dict]:
    rng = np.random.default_rng(0)
    base = place_in_sensor_frame(load_demo_objects(DEMO_OBJECTS).xyz[0], rng)
    rows = []
    with NodeLauncher({'input_topics': [TOPIC], 'qos_reliability': reliability,
                       'queue_size': 2 * count}, domain_id) as node:
        client = Client(domain_id, TOPIC, reliable=reliability == 'reliable',
                        name='qos_fragmentation')
        try:
            if not client.wait_ready(node, 120.0):
                raise RuntimeError(f'node did not start:\n{node.log_tail()}')
            client.spin_until(lambda: False, 0.5)
            for kb in sizes_kb:
                n = kb * 1024 // 16
                keys = []
                for _ in range(count):
                    xyz = base[rng.integers(0, len(base), n)] + rng.normal(
                        0, 0.002, (n, 3)).astype(np.float32)
                    key, _ = client.send(xyz.astype(np.float32), 'sensor',
                                         {'rgb': rng.random(n, dtype=np.float32)})
                    keys.append(key)
                    client.spin_until(lambda: False, 0.3)
                client.spin_until(lambda k=keys: all(x in client.answers for x in k), 30.0, node)
                rows.append({'reliability': reliability, 'size_kb': kb, 'sent': count,
                             'answered': sum(k in client.answers for k in keys)})
                print(rows[-1], flush=True)
        finally:
            client.close()
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--sizes-kb', type=int, nargs='+', default=[64, 640, 4900])
    ap.add_argument('--count', type=int, default=6)
    ap.add_argument('--domain-id', type=int, default=random.randint(150, 230))
    args = ap.parse_args()
    rows = [r for rel in ('best_effort', 'reliable')
            for r in measure(rel, args.sizes_kb, args.count, args.domain_id)]
    print('| input QoS | object size | answered |\n|---|---|---|')
    for r in rows:
        print(f"| {r['reliability']} | {r['size_kb']} KB | {r['answered']}/{r['sent']} |")


if __name__ == '__main__':
    main()
