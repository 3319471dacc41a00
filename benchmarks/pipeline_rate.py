"""The node's worker loop without DDS: answers a second and CPU when messages come too fast.

`Pipeline.serve` (node/pipeline.py, as the node's worker thread runs it) takes from a
`WorkQueue` that a feeder thread fills at --rate with the demo objects' PointCloud2
messages, drop-oldest as the node's intake does; every answer's `~/classifications` message
is built. After --warmup s, it reports answers a second, cores busy (this process's CPU
over the wall time) and CPU an answer over --seconds. Node parameters as NAME=VALUE, e.g.
queue_size=16. What `node_bench`'s burst measures, without the middleware and the client.

Run: python benchmarks/pipeline_rate.py [--rate 1000] [--seconds 6] [queue_size=16 ...]
"""

from __future__ import annotations

import argparse
import threading
import time

import numpy as np
from node_path_time import classifications_of, worker_pipeline  # benchmarks/, beside this one

from point_gn_ros.clients.node_client import load_demo_objects, place_in_sensor_frame
from point_gn_ros.node.params import PARAMETERS
from point_gn_ros.node.pipeline import Answer
from point_gn_ros.node.work_queue import WorkQueue
from point_gn_ros.pointcloud2 import xyz_to_pointcloud2

def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--rate', type=float, default=1000.0, help='messages a second offered')
    p.add_argument('--seconds', type=float, default=6.0)
    p.add_argument('--warmup', type=float, default=2.0)
    p.add_argument('params', nargs='*', help='node parameters, NAME=VALUE')
    args = p.parse_args()
    from std_msgs.msg import Header

    overrides = {}
    for item in args.params:
        name, value = item.split('=', 1)
        overrides[name] = type(PARAMETERS[name][0])(value)
    stop = threading.Event()
    s, _, pipe = worker_pipeline(overrides, stop)
    rng = np.random.default_rng(0)
    msgs = [xyz_to_pointcloud2(Header(frame_id='sensor'), place_in_sensor_frame(x, rng))
            for x in load_demo_objects().xyz]
    queue: WorkQueue = WorkQueue(1, s.queue_size)
    answered = [0]

    def publish(a: Answer) -> None:
        classifications_of(a)
        answered[0] += 1

    def feed() -> None:
        """5 messages a wake-up, as the node benchmark's client sends a burst."""
        i, next_t = 0, time.monotonic()
        while not stop.is_set():
            for _ in range(5):
                queue.put(0, msgs[i % len(msgs)])
                i += 1
            next_t += 5 / args.rate
            time.sleep(max(0.0, next_t - time.monotonic()))

    worker = threading.Thread(target=pipe.serve, args=(queue, publish), daemon=True)
    feeder = threading.Thread(target=feed, daemon=True)
    worker.start()
    feeder.start()
    time.sleep(args.warmup)
    a0, c0, t0 = answered[0], time.process_time(), time.monotonic()
    time.sleep(args.seconds)
    a1, c1, t1 = answered[0], time.process_time(), time.monotonic()
    stop.set()
    queue.close()
    feeder.join()
    worker.join()   # out of the encoder's C code before the interpreter ends
    n = max(a1 - a0, 1)
    print(f'{(a1 - a0) / (t1 - t0):.1f} answers/s, {(c1 - c0) / (t1 - t0):.2f} cores busy, '
          f'{(c1 - c0) / n * 1e3:.2f} ms CPU an answer; {" ".join(args.params) or "defaults"}')


if __name__ == '__main__':
    main()
