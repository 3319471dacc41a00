"""rclpy executor CPU per received PointCloud2, against the entities of the receiving node.

A publisher node sends a 1,024-point cloud every ~2 ms for 5 s to a node spun by a
SingleThreadedExecutor on its own thread, whose subscription callback only counts; prints
that thread's CPU time per received message (issue 13: the classifier node's executor
thread takes ~1.2 ms a message, benchmarks/log/2026-12-02.md).

Run: python benchmarks/executor_cost.py [--services N] [--parameter-services] [--raw]
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time

import numpy as np
import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from point_gn_ros.pointcloud2 import xyz_to_pointcloud2


def thread_cpu_s(tid: int) -> float:
    """User + system CPU seconds of one thread of this process (Linux /proc)."""
    with open(f'/proc/self/task/{tid}/stat') as f:
        fields = f.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    p.add_argument('--services', type=int, default=0, help='extra Trigger services')
    p.add_argument('--parameter-services', action='store_true')
    p.add_argument('--raw', action='store_true',
                   help='take the serialized bytes (raw=True): no deserialization')
    args = p.parse_args()
    rclpy.init()
    sender = Node('executor_cost_sender', start_parameter_services=False)
    receiver = Node('executor_cost_receiver',
                    start_parameter_services=args.parameter_services)
    count = [0]
    qos = QoSProfile(depth=5, history=HistoryPolicy.KEEP_LAST,
                     reliability=ReliabilityPolicy.RELIABLE)
    receiver.create_subscription(PointCloud2, 'executor_cost_objects',
                                 lambda msg: count.__setitem__(0, count[0] + 1), qos,
                                 raw=args.raw)
    for i in range(args.services):
        receiver.create_service(Trigger, f'~/service_{i}', lambda req, resp: resp)
    receiver.create_timer(1.0, lambda: None)
    executor = SingleThreadedExecutor()
    executor.add_node(receiver)

    def spin() -> None:
        try:
            executor.spin()
        except ExternalShutdownException:
            pass                          # rclpy.shutdown() below

    spinner = threading.Thread(target=spin, daemon=True)
    spinner.start()
    pub = sender.create_publisher(PointCloud2, 'executor_cost_objects', qos)
    msg = xyz_to_pointcloud2(Header(frame_id='sensor'),
                             np.random.default_rng(0).random((1024, 3), dtype=np.float32))
    time.sleep(1.0)                      # discovery
    cpu0, got0, t0, sent = thread_cpu_s(spinner.native_id), count[0], time.monotonic(), 0
    while time.monotonic() - t0 < 5.0:
        pub.publish(msg)
        sent += 1
        time.sleep(0.002)
    time.sleep(0.5)
    got = count[0] - got0
    per = (thread_cpu_s(spinner.native_id) - cpu0) / max(got, 1)
    print(f'{args.services} extra services, parameter services '
          f'{"on" if args.parameter_services else "off"}{", raw" if args.raw else ""}: '
          f'{got}/{sent} received, executor '
          f'CPU {per * 1e3:.3f} ms per message', flush=True)
    rclpy.shutdown()                     # ends the spinning thread's spin()
    spinner.join(timeout=5.0)
    return 0


if __name__ == '__main__':
    sys.exit(main())
