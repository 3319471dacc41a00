"""Live replay: publish a bag's clouds to the classifier node over DDS and collect its answers.

The bag's raw CDR bytes are published as they are (no deserialisation on the send path).
Answers on ``/<node>/classifications`` are matched to messages by header stamp (unique per
message in our bags) and to objects by ``segment_id``. An executor thread receives while the
main thread paces the sends, so receive times are not delayed by the pacing sleeps.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
import os
import sys
import threading
import time
from typing import Any

import numpy as np

from point_gn_ros.bag.errors import ReplayError
from point_gn_ros.bag.reader import BagContents, BagMessage
from point_gn_ros.bag.report import Answer, RunResult, map_class_ids

MODES = ('rate', 'lockstep', 'listen-only')
# Wait this long for the node's latched class names once it is discovered.
CLASS_NAMES_WAIT_S = 3.0
# The node publishes /diagnostics once a second: wait a little longer than that for one.
DIAG_WAIT_S = 1.5
# The node's default name (classifier_node.NODE_NAME); preferred when several nodes subscribe.
DEFAULT_NODE_FQN = '/point_gn_classifier'


def _log(text: str) -> None:
    print(f'[replay] {text}', file=sys.stderr, flush=True)


@dataclass(frozen=True)
class ReplayOptions:
    mode: str = 'rate'
    rate: float = 1.0                 # x the recorded rate (rate mode)
    node_name: str | None = None      # None: whichever node subscribes to the bag's topic
    timeout: float = 10.0             # lockstep: per message; else: idle time before giving up
    discovery_timeout: float = 60.0   # for the node to appear (listen-only: the first answer)
    reliable: bool = True             # publisher QoS; reliable also matches best-effort subs
    log: Callable[[str], None] = _log

    def check(self) -> None:
        if self.mode not in MODES:
            raise ReplayError(f'unknown replay mode {self.mode!r}')
        if not (self.rate > 0 and np.isfinite(self.rate)):
            raise ReplayError(f'--rate must be > 0 (got {self.rate})')
        if self.timeout <= 0 or self.discovery_timeout <= 0:
            raise ReplayError('--timeout and --discovery-timeout must be > 0')


def node_fqn(name: str, namespace: str = '/') -> str:
    """'classifier_node' -> '/classifier_node'; absolute names are kept."""
    if name.startswith('/'):
        return name.rstrip('/')
    return namespace.rstrip('/') + '/' + name


class _Collector:
    """Thread-safe store of answers, keyed by bag message; fed by subscription callbacks."""

    def __init__(self, contents: BagContents, pipeline_status: Callable[[], str | None]) -> None:
        self.by_stamp: dict[int, BagMessage] = {m.stamp_ns: m for m in contents.messages}
        self.cond = threading.Condition()
        self.received: dict[int, float] = {}            # message index -> monotonic receipt
        self.raw_answers: dict[tuple[int, int], tuple[int, float]] = {}
        self.unmatched = 0
        self.duplicates = 0                             # a second answer to one message
        self.topic_indices: Counter[int] = Counter()
        self.class_names: list[str] | None = None
        self.diags: list[tuple[float, dict[str, str]]] = []
        self._pipeline_status = pipeline_status

    def on_classifications(self, msg: Any) -> None:
        t = time.monotonic()
        from point_gn_ros.errors import DecodeError
        from point_gn_ros.pointcloud2 import decode_classifications

        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        m = self.by_stamp.get(stamp_ns)
        try:
            d = decode_classifications(msg)
        except DecodeError:
            d = None
        with self.cond:
            if m is not None and d is not None and m.index in self.received:
                self.duplicates += 1     # two nodes (one name) answering, or a re-publish
                return
            if m is None or d is None:
                self.unmatched += 1
                return
            self.received[m.index] = t
            for seg, cid, score, ti in zip(d['segment_id'], d['class_id'], d['score'],
                                           d['topic_index'], strict=True):
                self.raw_answers[(m.index, int(seg))] = (int(cid), float(score))
                self.topic_indices[int(ti)] += 1
            self.cond.notify_all()

    def on_class_names(self, msg: Any) -> None:
        with self.cond:
            self.class_names = msg.data.split('\n')
            self.cond.notify_all()

    def on_diagnostics(self, msg: Any) -> None:
        name = self._pipeline_status()
        if name is None:
            return
        for st in msg.status:
            if st.name == name:
                with self.cond:
                    self.diags.append((time.monotonic(), {kv.key: kv.value for kv in st.values}))
                return

    def wait(self, predicate: Callable[[], bool], timeout: float) -> bool:
        with self.cond:
            return self.cond.wait_for(predicate, timeout)


class _Graph:
    """An rclpy context, node and executor thread of our own (so tests can run several)."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        self.context = rclpy.Context()
        rclpy.init(context=self.context)   # ROS_DOMAIN_ID from the environment
        self.node = rclpy.create_node(f'point_gn_replay_{os.getpid()}', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name='replay_spin', daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 - shutting down underneath us
                if self._stop.is_set() or not self.context.ok():
                    return
                raise

    def find_classifiers(self, topic: str) -> list[str]:
        """Every node that subscribes to `topic` and publishes `<node>/classifications`.

        The default node name first, then alphabetical.
        """
        own = self.node.get_fully_qualified_name()
        found = [node_fqn(i.node_name, i.node_namespace)
                 for i in self.node.get_subscriptions_info_by_topic(topic)]
        # Endpoints can be discovered before their node's name ('_NODE_NAME_UNKNOWN_').
        found = sorted({f for f in found if f != own and '_UNKNOWN_' not in f},
                       key=lambda f: (f != DEFAULT_NODE_FQN, f))
        return [f for f in found if self.node.count_publishers(f + '/classifications') > 0]

    def find_classifier(self, topic: str) -> str | None:
        """The preferred classifier node of `topic` (see find_classifiers), or None."""
        return next(iter(self.find_classifiers(topic)), None)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


def run_replay(contents: BagContents, opts: ReplayOptions) -> RunResult:
    """Replay `contents` against the running classifier node; see ReplayOptions."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.qos import (HistoryPolicy, QoSProfile, ReliabilityPolicy)
    from sensor_msgs.msg import PointCloud2

    opts.check()
    fqn: list[str | None] = [node_fqn(opts.node_name) if opts.node_name else None]
    col = _Collector(contents, lambda: f'{fqn[0]}: pipeline' if fqn[0] else None)
    graph = _Graph()
    try:
        node = graph.node
        pub = None
        if opts.mode != 'listen-only':
            pub = node.create_publisher(PointCloud2, contents.topic, QoSProfile(
                depth=10, history=HistoryPolicy.KEEP_LAST,
                reliability=(ReliabilityPolicy.RELIABLE if opts.reliable
                             else ReliabilityPolicy.BEST_EFFORT)))
        # Diagnostics before discovery: the first snapshot is the drop-counter baseline.
        node.create_subscription(DiagnosticArray, '/diagnostics', col.on_diagnostics, 10)
        cls_sub = _discover(graph, contents.topic, pub, fqn, col, opts)
        opts.log(f'node {fqn[0]} found; classifications on {cls_sub.topic_name}')
        others = _others_answering(graph, contents.topic, fqn[0], cls_sub, opts)
        col.wait(lambda: col.class_names is not None, CLASS_NAMES_WAIT_S)
        col.wait(lambda: bool(col.diags), DIAG_WAIT_S)
        base_diag = col.diags[-1][1] if col.diags else None
        if opts.mode == 'listen-only':
            result = _listen(contents, col, opts)
        else:
            assert pub is not None
            result = _send(contents, pub, col, opts)
        if base_diag is not None:
            t_end = time.monotonic()   # a diagnostics snapshot taken after the last event
            col.wait(lambda: col.diags[-1][0] > t_end, DIAG_WAIT_S)
        result.node = fqn[0]
        result.info.update(others)
        _finish(result, col, contents, base_diag)
        return result
    finally:
        graph.close()


def _discover(graph: _Graph, topic: str, pub: Any, fqn: list[str | None], col: _Collector,
              opts: ReplayOptions) -> Any:
    """Wait until the classifier subscribes to `topic` and we hear its classifications."""
    from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import String

    node = graph.node
    end = time.monotonic() + opts.discovery_timeout
    cls_sub = None
    opts.log(f'waiting for the classifier node on {topic} '
             f'(ROS_DOMAIN_ID={os.environ.get("ROS_DOMAIN_ID", "0")})')
    while time.monotonic() < end:
        if fqn[0] is None:
            fqn[0] = graph.find_classifier(topic)
        if fqn[0] is not None and cls_sub is None:
            cls_sub = node.create_subscription(
                PointCloud2, fqn[0] + '/classifications', col.on_classifications,
                QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                           reliability=ReliabilityPolicy.RELIABLE))
            node.create_subscription(
                String, fqn[0] + '/class_names', col.on_class_names,
                QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL))
        if (cls_sub is not None and cls_sub.get_publisher_count() > 0
                and (pub is None or pub.get_subscription_count() > 0)):
            return cls_sub
        time.sleep(0.05)
    who = (f'node {fqn[0]} did not subscribe to {topic} and publish classifications'
           if fqn[0] else f'no classifier node subscribed to {topic} and published '
                          'classifications')
    raise ReplayError(f'{who} within {opts.discovery_timeout:g} s (ROS_DOMAIN_ID='
                      f'{os.environ.get("ROS_DOMAIN_ID", "0")}): is the classifier node '
                      'running on this domain' + (', with --node-name right?' if opts.node_name
                                                  else '?'))


def _others_answering(graph: _Graph, topic: str, fqn: str | None, cls_sub: Any,
                      opts: ReplayOptions) -> dict[str, Any]:
    """Warn when more than one node would answer the bag's topic (answers would double)."""
    nodes = graph.find_classifiers(topic)
    publishers = cls_sub.get_publisher_count()
    if len(nodes) > 1:
        opts.log(f'warning: {len(nodes)} classifier nodes subscribe to {topic} '
                 f'({", ".join(nodes)}); answers are read from {fqn} only')
    if publishers > 1:
        opts.log(f'warning: {publishers} publishers on {cls_sub.topic_name}: several nodes '
                 'with the same name? their answers will be counted as duplicates')
    return {'classifier_nodes': nodes, 'classification_publishers': publishers}


def _send(contents: BagContents, pub: Any, col: _Collector, opts: ReplayOptions) -> RunResult:
    """Publish the bag (paced or lockstep) and wait for the answers; Ctrl-C stops early."""
    msgs = contents.messages
    sent_at: dict[int, float] = {}
    base_ns = msgs[0].log_ns
    interrupted = False
    opts.log(f'sending {len(msgs)} message(s) ' + (
        'in lockstep' if opts.mode == 'lockstep'
        else f'at {opts.rate:g} x the recorded {contents.rate_hz:.1f} Hz'))
    t0 = time.monotonic()
    try:
        for m in msgs:
            if opts.mode == 'rate':
                delay = t0 + (m.log_ns - base_ns) / 1e9 / opts.rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            sent_at[m.index] = time.monotonic()
            pub.publish(m.raw)   # raw CDR straight from the bag
            if opts.mode == 'lockstep':
                col.wait(lambda i=m.index: i in col.received, opts.timeout)
        # Drain: stop when all are answered or nothing arrived for `timeout` seconds.
        while True:
            with col.cond:
                done = len(col.received) >= len(sent_at)
                last = max([*sent_at.values(), *col.received.values()])
            if done or time.monotonic() - last > opts.timeout:
                break
            col.wait(lambda: len(col.received) >= len(sent_at), 0.2)
    except KeyboardInterrupt:
        interrupted = True
        opts.log('interrupted: reporting what was sent so far')
    with col.cond:
        received = dict(col.received)
    answered = {i for i in received if i in sent_at}
    latency = {i: received[i] - sent_at[i] for i in answered}
    end = max(received.values(), default=time.monotonic())
    return RunResult(opts.mode, {}, answered, len(sent_at), max(end - t0, 1e-9), latency,
                     info={'rate': opts.rate if opts.mode == 'rate' else None,
                           'timeout_s': opts.timeout, 'interrupted': interrupted})


def _listen(contents: BagContents, col: _Collector, opts: ReplayOptions) -> RunResult:
    """Only listen (someone else plays the bag): stop when all are answered or idle."""
    n = len(contents.messages)
    opts.log(f'listening for answers to {n} message(s) on {contents.topic} '
             '(play the bag now, e.g. ros2 bag play)')
    interrupted = False
    try:
        if col.wait(lambda: bool(col.received), opts.discovery_timeout):
            while not col.wait(lambda: len(col.received) >= n, 0.2):
                with col.cond:
                    last = max(col.received.values())
                if time.monotonic() - last > opts.timeout:
                    break
    except KeyboardInterrupt:
        interrupted = True
    with col.cond:
        received = dict(col.received)
    times = list(received.values())
    wall = (max(times) - min(times)) if len(times) > 1 else 0.0
    return RunResult('listen-only', {}, set(received), n, wall,
                     info={'timeout_s': opts.timeout, 'interrupted': interrupted})


def _finish(result: RunResult, col: _Collector, contents: BagContents,
            base_diag: dict[str, str] | None) -> None:
    """Map the node's class ids to the bag's, and fill in drops from the diagnostics."""
    with col.cond:
        node_names = col.class_names
        raw = dict(col.raw_answers)
        final_diag = col.diags[-1][1] if col.diags else None
        result.info.update(unmatched_answers=col.unmatched, duplicate_answers=col.duplicates,
                           topic_indices=sorted(col.topic_indices))
    if node_names is None:
        node_names = contents.class_names
        result.info['class_names'] = "not received from the node; assumed the bag's"
    lut = map_class_ids(node_names, contents.class_names)
    if (lut < 0).any():   # answers in those classes count as unknown
        result.info['node_classes_not_in_bag'] = int((lut < 0).sum())
    result.answers = {key: Answer(int(lut[cid]) if 0 <= cid < len(lut) else -1, score)
                      for key, (cid, score) in raw.items() if key[0] in result.answered}
    if base_diag is not None and final_diag is not None:
        def delta(key: str) -> int:
            try:
                return int(final_diag[key]) - int(base_diag[key])
            except (KeyError, ValueError):
                return 0
        result.dropped = delta('dropped') + delta('rejected') + delta('failed')
        result.info.update(node_dropped_queue_full=delta('dropped'),
                           node_rejected=delta('rejected'), node_failed=delta('failed'),
                           node_received=delta('received'))
