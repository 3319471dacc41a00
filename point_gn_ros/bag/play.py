"""`point_gn bag play`: publish a bag's topics at the recorded rate (no `ros2 bag` needed).

Raw CDR is published as recorded (no deserialisation), one publisher per topic of a type this
Python can import; a topic recorded as transient local (latched) is offered so again.
"""

from __future__ import annotations

from collections.abc import Callable
import os
from pathlib import Path
import time
from typing import Any

import numpy as np

from point_gn_ros.bag.errors import BagError, MissingTopicError
from point_gn_ros.bag.reader import _open


def _latched(conn: Any) -> bool:
    profiles = getattr(conn.ext, 'offered_qos_profiles', None) or []
    return any('TRANSIENT_LOCAL' in str(getattr(q, 'durability', '')).upper() or
               'transient_local' in str(q) for q in profiles)


def play(path: str | os.PathLike[str], topics: list[str] | None = None, rate: float = 1.0,
         loop: bool = False, log: Callable[[str], None] = print,
         discovery_s: float = 1.0, wait_subscribers_s: float = 0.0) -> int:
    """Publish the bag (rate x recorded); returns messages published. Ctrl-C stops.

    discovery_s: pause before the first message, so that subscribers can match;
    wait_subscribers_s > 0: also wait (at most that long) until every topic has one.
    """
    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rosidl_runtime_py.utilities import get_message

    if not (rate > 0 and np.isfinite(rate)):
        raise BagError(f'--rate must be > 0 (got {rate})')
    path = Path(path)
    reader = _open(path)
    try:
        info = reader.topics
        chosen = list(dict.fromkeys(topics)) if topics else sorted(info)
        missing = [t for t in chosen if t not in info]
        if missing:
            raise MissingTopicError(f'{path}: no topic {", ".join(missing)} in the bag '
                                    f'(topics: {", ".join(sorted(info))})')
        conns = [c for c in reader.connections if c.topic in chosen]
        rows = [(log_ns, conn.topic, bytes(raw)) for conn, log_ns, raw in reader.messages(conns)]
        latched = {c.topic for c in conns if _latched(c)}
    finally:
        reader.close()
    if not rows:
        raise BagError(f'{path}: no messages on {", ".join(chosen)}')
    context = rclpy.Context()
    rclpy.init(context=context)          # ROS_DOMAIN_ID from the environment
    node = rclpy.create_node(f'point_gn_bag_play_{os.getpid()}', context=context)
    sent = 0
    try:
        pubs = {}
        for topic in chosen:
            try:
                msg_type = get_message(info[topic].msgtype)
            except (AttributeError, ModuleNotFoundError, ValueError):
                log(f'{topic}: type {info[topic].msgtype} is not installed here; skipped')
                continue
            pubs[topic] = node.create_publisher(msg_type, topic, QoSProfile(
                depth=100 if topic not in latched else 1,
                reliability=ReliabilityPolicy.RELIABLE,
                durability=(DurabilityPolicy.TRANSIENT_LOCAL if topic in latched
                            else DurabilityPolicy.VOLATILE)))
        log(f'playing {len(rows)} message(s) on {", ".join(pubs)} at {rate:g} x'
            + (' (looping)' if loop else ''))
        time.sleep(discovery_s)          # let subscribers match before the first message
        end = time.monotonic() + wait_subscribers_s
        while (time.monotonic() < end
               and not all(p.get_subscription_count() for p in pubs.values())):
            time.sleep(0.05)
        base = rows[0][0]
        while True:
            t0 = time.monotonic()
            for log_ns, topic, raw in rows:
                pub = pubs.get(topic)
                if pub is None:
                    continue
                delay = t0 + (log_ns - base) / 1e9 / rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                pub.publish(raw)
                sent += 1
            if not loop:
                break
        time.sleep(0.2)                  # reliable writers: let the last samples go out
    except KeyboardInterrupt:
        log(f'interrupted after {sent} message(s)')
    finally:
        node.destroy_node()
        context.try_shutdown()
    return sent
