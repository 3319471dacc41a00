"""ROS 2 node: classify segmented object point clouds with Point-GN.

Subscribes to one or more sensor_msgs/PointCloud2 topics (each message one object,
or several objects split by an integer segment field) and publishes

* ``~/classifications`` (sensor_msgs/PointCloud2): one point per object, at its
  centroid in the input frame, with class_id, score, top-k ids/scores,
  segment_id and topic_index; same header as the input message;
* ``~/markers`` (visualization_msgs/MarkerArray): a "label score" text and a
  bounding box per object;
* ``~/class_names`` (std_msgs/String, latched): one class name per line,
  line index = class_id;
* ``/diagnostics`` (diagnostic_msgs/DiagnosticArray) once a second.

Threading: subscription callbacks only enqueue (bounded per topic, dropping the
oldest); one worker thread decodes, resamples, encodes and classifies in
micro-batches across topics, so the executor stays responsive however slow the
encoder is.
"""

from __future__ import annotations

import point_gn_ros.node._quiet_interrupt  # noqa: F401 - first: before the slow imports

from collections.abc import Sequence
from dataclasses import dataclass
import math
import re
import signal
import sys
import threading
import time
from typing import Any

import numpy as np
import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
import rclpy.logging
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType)
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String
from visualization_msgs.msg import MarkerArray

from point_gn_ros.errors import BankError, DecodeError, PointGNError
from point_gn_ros.node.markers import MarkerTracker, object_box
from point_gn_ros.node.stats import NodeStats
from point_gn_ros.node.rate_limited_log import RateLimitedLogger
from point_gn_ros.node.work_queue import QueueItem, WorkQueue

NODE_NAME = 'point_gn_classifier'
REJECT_TOO_FEW = 'too few points'
# Seconds between two warnings for the same topic (the rest are counted, then summarised).
WARN_PERIOD_S = 5.0
# How long shutdown waits for the worker to finish the batch it is classifying.
WORKER_JOIN_TIMEOUT_S = 10.0


class NodeConfigError(PointGNError):
    """A parameter value the node cannot run with."""


@dataclass(frozen=True)
class Settings:
    """Validated parameter values (all fixed at start)."""

    bank_path: str
    input_topics: tuple[str, ...]
    segment_field: str
    min_points: int
    num_points: int
    resample: str
    device: str
    top_k: int
    unknown_threshold: float
    max_batch: int
    queue_size: int
    qos_reliability: str
    qos_depth: int
    torch_threads: int


def _int_range(lo: int, hi: int) -> list[IntegerRange]:
    return [IntegerRange(from_value=lo, to_value=hi, step=1)]


# name -> (default, description, extra ParameterDescriptor kwargs). Every one is read-only:
# the pipeline (bank, encoder, queues, subscriptions) is built once at start.
PARAMETERS: dict[str, tuple[Any, str, dict[str, Any]]] = {
    'bank_path': ('', "Feature bank (.npz); '' = the ModelNet40 bank shipped with the package.",
                  {}),
    'input_topics': (['segmented_objects'],
                     'sensor_msgs/PointCloud2 topics to classify (all share one worker).', {}),
    'segment_field': ('', "'' = each message is one object; else the integer point field that "
                          'splits a message into objects (negative ids are ignored).', {}),
    'min_points': (16, 'Objects (or segments) with fewer finite points are rejected.',
                   {'integer_range': _int_range(1, 1_000_000)}),
    'num_points': (1024, "Points per object after resampling; must equal the bank's encoder "
                         'configuration.', {'integer_range': _int_range(16, 65536)}),
    'resample': ('fps', "Resampling to num_points: 'fps' (farthest point) or 'random'.",
                 {'additional_constraints': "one of 'fps', 'random'"}),
    'device': ('cpu', "Torch device: 'cpu' or 'cuda'.",
               {'additional_constraints': "one of 'cpu', 'cuda'"}),
    'top_k': (5, 'How many best classes (ids and scores) each object carries.',
              {'integer_range': _int_range(1, 100)}),
    'unknown_threshold': (0.0, 'Top-1 scores below it are labelled unknown (class_id -1); '
                               "0 = off, < 0 = the bank's calibrated threshold.",
                          {'floating_point_range': [FloatingPointRange(
                              from_value=-1.0, to_value=1.0, step=0.0)]}),
    'max_batch': (32, 'Most objects encoded in one micro-batch (across topics).',
                  {'integer_range': _int_range(1, 1024)}),
    'queue_size': (8, 'Messages waiting per input topic; when full the oldest is dropped.',
                   {'integer_range': _int_range(1, 10_000)}),
    'qos_reliability': ('best_effort', "Input QoS: 'best_effort' (sensor data profile) or "
                                       "'reliable'.",
                        {'additional_constraints': "one of 'best_effort', 'reliable'"}),
    'qos_depth': (5, 'Input (and output) QoS history depth.',
                  {'integer_range': _int_range(1, 1000)}),
    'torch_threads': (2, 'Torch intra-op threads and fast-encoder worker threads; bounded on '
                         'purpose so that they do not starve the executor and DDS threads.',
                      {'integer_range': _int_range(1, 256)}),
}

_CHOICES = {'resample': ('fps', 'random'), 'device': ('cpu', 'cuda'),
            'qos_reliability': ('best_effort', 'reliable')}


@dataclass
class _Job:
    """One dequeued message on its way through the pipeline."""

    item: QueueItem[PointCloud2]
    segment_ids: list[int]
    clouds: list[np.ndarray]


class ClassifierNode(Node):
    """Point-GN classifier node; see the module docstring for topics and threading."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self.settings = self._declare_parameters()
        s = self.settings
        self._configure_torch()

        t0 = time.perf_counter()
        self.recognizer = self._make_recognizer()
        bank = self.recognizer.bank
        if bank.config.num_points != s.num_points:
            raise BankError(f'{bank.path}: bank was built for num_points='
                            f'{bank.config.num_points}, node parameter num_points='
                            f'{s.num_points}')
        self.class_names = list(self.recognizer.class_names)
        # Read-only and taken from the bank: an override on the command line is ignored.
        self.declare_parameter(
            'class_names', self.class_names,
            ParameterDescriptor(type=ParameterType.PARAMETER_STRING_ARRAY, read_only=True,
                                description='Class names of the bank (index = class_id).'),
            ignore_override=True)
        self.get_logger().info(f'bank {bank.path}: {bank.summary()} '
                               f'(loaded in {time.perf_counter() - t0:.1f} s)')
        # Pay compile / first-call costs before any message can arrive.
        warm_s = self.recognizer.warmup()
        self.get_logger().info(f'warm-up done in {warm_s:.1f} s: {self.recognizer.encoder!r}, '
                               f'device {s.device}, {s.torch_threads} thread(s)')

        out_qos = QoSProfile(depth=max(10, s.qos_depth), reliability=ReliabilityPolicy.RELIABLE,
                             history=HistoryPolicy.KEEP_LAST)
        self._pub_cls = self.create_publisher(PointCloud2, '~/classifications', out_qos)
        self._pub_markers = self.create_publisher(MarkerArray, '~/markers', out_qos)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self._pub_names = self.create_publisher(String, '~/class_names', latched)
        self._pub_names.publish(String(data='\n'.join(self.class_names)))
        self._pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)

        self._queue: WorkQueue[PointCloud2] = WorkQueue(len(s.input_topics), s.queue_size)
        self._stats = NodeStats(len(s.input_topics))
        self._markers = MarkerTracker(s.input_topics)
        self._warn = RateLimitedLogger(self.get_logger().warning, WARN_PERIOD_S)
        self._last_diag: tuple[int, int, int] = (0, 0, 0)   # drops, rejects, errors
        self._stop = threading.Event()
        self._worker = threading.Thread(target=self._work, name='point_gn_worker', daemon=True)
        self._worker.start()

        in_qos = QoSProfile(
            depth=s.qos_depth, history=HistoryPolicy.KEEP_LAST,
            reliability=(ReliabilityPolicy.BEST_EFFORT if s.qos_reliability == 'best_effort'
                         else ReliabilityPolicy.RELIABLE),
            durability=DurabilityPolicy.VOLATILE)
        self._subs = [
            self.create_subscription(PointCloud2, topic,
                                     lambda msg, i=i: self._on_cloud(i, msg), in_qos)
            for i, topic in enumerate(s.input_topics)]
        self._diag_timer = self.create_timer(1.0, self._publish_diagnostics)
        resolved = ', '.join(sub.topic_name for sub in self._subs)
        self.get_logger().info(
            f'classifying {resolved} ({s.qos_reliability}, depth {s.qos_depth}, segment field '
            f"{s.segment_field or 'none'}) -> {self._pub_cls.topic_name}, "
            f'{self._pub_markers.topic_name}')

    # ------------------------------------------------------------------ parameters

    def _declare_parameters(self) -> Settings:
        values: dict[str, Any] = {}
        for name, (default, description, extra) in PARAMETERS.items():
            desc = ParameterDescriptor(description=description, read_only=True, **extra)
            if isinstance(default, list):   # an explicit type, so that [] would still be valid
                desc.type = ParameterType.PARAMETER_STRING_ARRAY
            values[name] = self.declare_parameter(name, default, desc).value
        for name, choices in _CHOICES.items():
            if values[name] not in choices:
                raise NodeConfigError(f'parameter {name}={values[name]!r} must be one of '
                                      f'{", ".join(choices)}')
        topics = tuple(str(t) for t in values['input_topics'] or ())
        if not topics or any(not t for t in topics):
            raise NodeConfigError(f'parameter input_topics={list(topics)} must name at least '
                                  'one topic, none empty')
        if len(set(topics)) != len(topics):
            raise NodeConfigError(f'parameter input_topics={list(topics)} repeats a topic')
        values['input_topics'] = topics
        if values['device'] == 'cuda':
            import torch
            if not torch.cuda.is_available():
                raise NodeConfigError("parameter device='cuda' but CUDA is not available")
        return Settings(**values)

    def _make_recognizer(self) -> Any:
        from point_gn_ros.bank.store import FeatureBank
        from point_gn_ros.recognizer import Recognizer, make_encoder

        s = self.settings
        bank = FeatureBank.load(s.bank_path or None)
        # The fast encoder runs its own worker pool (default: every CPU); it gets the
        # same budget as torch, for the same reason.
        encoder = make_encoder(bank.config, s.device, threads=s.torch_threads)
        try:
            return Recognizer(bank, s.device, s.resample, s.top_k,
                              s.unknown_threshold or None, encoder=encoder)
        except ValueError as exc:       # e.g. unknown_threshold < 0 without a calibration
            raise NodeConfigError(str(exc)) from None

    def _configure_torch(self) -> None:
        import torch
        torch.set_num_threads(self.settings.torch_threads)
        try:
            torch.set_num_interop_threads(1)   # the worker is the only caller
        except RuntimeError:
            pass                               # already fixed (torch allows one call)

    # ------------------------------------------------------------------ input

    def _on_cloud(self, topic_index: int, msg: PointCloud2) -> None:
        """Subscription callback: enqueue with the receipt time, nothing else."""
        self._stats.on_received(topic_index)
        self._queue.put(topic_index, msg)

    # ------------------------------------------------------------------ worker

    def _work(self) -> None:
        """Worker thread: take micro-batches until stopped; never dies on one bad batch."""
        while not self._stop.is_set():
            items = self._queue.take(self.settings.max_batch, timeout=0.5)
            if not items:
                continue
            try:
                self._process(items)
            except Exception as exc:  # noqa: BLE001 - the node must outlive any one batch
                if self._stop.is_set() or not self.context.ok():
                    return
                self._on_failure(len(items), exc)

    def _reject(self, item: QueueItem[PointCloud2], reason: str, detail: str) -> None:
        self._stats.on_rejected(reason)
        topic = self.settings.input_topics[item.topic_index]
        self._warn((item.topic_index,),
                   f'dropped a message on {self._subs[item.topic_index].topic_name or topic}: '
                   f'{detail}')

    def _prepare(self, item: QueueItem[PointCloud2]) -> _Job | None:
        """Decode and split one message into object clouds; None if it is rejected."""
        from point_gn_ros.pointcloud2 import decode_xyz, split_segments
        s = self.settings
        seg_field = s.segment_field
        try:
            # allow_empty: an empty or all-NaN cloud counts as 'too few points', not malformed.
            decoded = decode_xyz(item.payload, (seg_field,) if seg_field else (),
                                 allow_empty=True)
            if not seg_field:
                if len(decoded) < s.min_points:
                    self._reject(item, REJECT_TOO_FEW, f'{len(decoded)} finite point(s), '
                                                       f'min_points is {s.min_points}')
                    return None
                return _Job(item, [-1], [decoded.xyz])
            segments = split_segments(decoded, seg_field)
        except DecodeError as exc:
            self._reject(item, _reason_key(str(exc)), str(exc))
            return None
        job = _Job(item, [], [])
        skipped = 0
        for seg_id, xyz in segments:
            if seg_id < 0:
                continue          # unsegmented / background points by convention
            if len(xyz) < s.min_points:
                skipped += 1
                continue
            job.segment_ids.append(seg_id)
            job.clouds.append(xyz)
        if skipped:
            self._stats.on_skipped_segments(skipped)
        return job

    def _process(self, items: Sequence[QueueItem[PointCloud2]]) -> None:
        jobs = [job for job in map(self._prepare, items) if job is not None]
        try:
            results = self._classify([c for job in jobs for c in job.clouds])
        except Exception:
            if len(jobs) <= 1 or self._stop.is_set():
                raise
            # One message broke the batch: classify message by message, so only that
            # message is lost and the others are still answered.
            for job in jobs:
                try:
                    self._answer([job], self._classify(job.clouds))
                except Exception as exc:  # noqa: BLE001 - see _work()
                    if self._stop.is_set():
                        return
                    self._on_failure(1, exc)
            return
        if results is not None:
            self._answer(jobs, results)

    def _classify(self, clouds: list[np.ndarray]) -> tuple[np.ndarray, ...] | None:
        """Labels, scores, top-k ids and scores of clouds, in chunks of max_batch.

        None when the node is stopping.
        """
        s = self.settings
        k = min(s.top_k, len(self.class_names))
        parts = [(np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros((0, k), np.int64),
                  np.zeros((0, k), np.float32))]
        for start in range(0, len(clouds), s.max_batch):
            if self._stop.is_set():
                return None
            res = self.recognizer.classify_clouds(clouds[start:start + s.max_batch])
            parts.append((res.labels, res.scores, res.topk_ids, res.topk_scores))
        self._stats.on_batch(len(clouds))
        return tuple(np.concatenate(column) for column in zip(*parts, strict=True))

    def _answer(self, jobs: Sequence[_Job], results: tuple[np.ndarray, ...] | None) -> None:
        """Publish each job's slice of the batch results (zero objects allowed)."""
        if results is None:
            return
        pos = 0
        for job in jobs:
            sl = slice(pos, pos + len(job.clouds))
            pos = sl.stop
            self._publish(job, *(column[sl] for column in results))

    def _on_failure(self, count: int, exc: Exception) -> None:
        self._stats.on_error(f'{type(exc).__name__}: {exc}')
        self._warn(('error',), f'failed to classify {count} message(s): '
                               f'{type(exc).__name__}: {exc}')

    def _publish(self, job: _Job, labels: np.ndarray, scores: np.ndarray,
                 topk_ids: np.ndarray, topk_scores: np.ndarray) -> None:
        from point_gn_ros.pointcloud2 import make_classifications
        header = job.item.payload.header
        ti = job.item.topic_index
        centroids = np.array([c.mean(axis=0, dtype=np.float64) for c in job.clouds],
                             dtype=np.float32).reshape(-1, 3)
        out = make_classifications(header, centroids, labels, scores, topk_ids, topk_scores,
                                   np.asarray(job.segment_ids, dtype=np.int64), ti)
        self._pub_cls.publish(out)
        if self._pub_markers.get_subscription_count():   # nobody watching: skip the work
            boxes = [object_box(c, self._label_name(int(lbl)), int(lbl), float(sc))
                     for c, lbl, sc in zip(job.clouds, labels, scores, strict=True)]
            self._pub_markers.publish(self._markers.build(ti, header, boxes))
        stamp_ns = header.stamp.sec * 1_000_000_000 + header.stamp.nanosec
        # Header stamps are compared with the wall clock (sensor drivers stamp in system time).
        stamp_lat = (time.time_ns() - stamp_ns) * 1e-9 if stamp_ns > 0 else None
        self._stats.on_published(ti, len(job.clouds), time.monotonic() - job.item.receipt_time,
                                 stamp_lat)

    def _label_name(self, class_id: int) -> str:
        return self.class_names[class_id] if 0 <= class_id < len(self.class_names) else 'unknown'

    # ------------------------------------------------------------------ diagnostics

    def _publish_diagnostics(self) -> None:
        s = self.settings
        snap = self._stats.snapshot(self._queue.dropped(), self._queue.depths())
        drops, rejects = sum(snap.dropped), sum(snap.rejected.values())
        new_drops = drops - self._last_diag[0]
        new_rejects = rejects - self._last_diag[1]
        new_errors = snap.errors - self._last_diag[2]
        self._last_diag = (drops, rejects, snap.errors)

        level, message = DiagnosticStatus.OK, 'ok'
        problems = []
        if new_drops:
            problems.append(f'{new_drops} message(s) dropped (queue full)')
        if new_rejects:
            problems.append(f'{new_rejects} message(s) rejected')
        if problems:
            level, message = DiagnosticStatus.WARN, '; '.join(problems)
        if not self._worker.is_alive():
            level, message = DiagnosticStatus.ERROR, 'worker thread stopped'
        elif new_errors:
            level, message = DiagnosticStatus.ERROR, f'classification failed: {snap.last_error}'

        name = self.get_fully_qualified_name()
        pipeline = DiagnosticStatus(level=level, name=f'{name}: pipeline', message=message,
                                    hardware_id=s.device)
        pipeline.values = _key_values({
            'input_rate_hz': f'{snap.input_rate_hz:.2f}',
            'processed_rate_hz': f'{snap.processed_rate_hz:.2f}',
            'objects_rate_hz': f'{snap.objects_rate_hz:.2f}',
            'received': sum(snap.received),
            'processed': sum(snap.processed),
            'objects': snap.objects,
            'latency_receipt_p50_ms': _fmt_ms(snap.latency_receipt_ms[0]),
            'latency_receipt_p99_ms': _fmt_ms(snap.latency_receipt_ms[1]),
            'latency_stamp_p50_ms': _fmt_ms(snap.latency_stamp_ms[0]),
            'latency_stamp_p99_ms': _fmt_ms(snap.latency_stamp_ms[1]),
            'latency_samples': snap.latency_samples,
            'mean_batch_objects': f'{snap.batch_size_mean:.1f}',
            'queue_depth': sum(snap.queue_depths),
            'queue_capacity': s.queue_size * len(s.input_topics),
            'dropped': drops,
            'rejected': rejects,
            **{f'rejected.{reason}': n for reason, n in sorted(snap.rejected.items())},
            'skipped_segments': snap.skipped_segments,
            'errors': snap.errors,
        })
        statuses = [pipeline]
        for i, sub in enumerate(self._subs):
            full = snap.queue_depths[i] >= s.queue_size
            st = DiagnosticStatus(level=DiagnosticStatus.WARN if full else DiagnosticStatus.OK,
                                  name=f'{name}: input {sub.topic_name}', hardware_id=s.device,
                                  message='queue full' if full else 'ok')
            st.values = _key_values({
                'topic_index': i, 'input_rate_hz': f'{snap.per_topic_input_hz[i]:.2f}',
                'received': snap.received[i], 'processed': snap.processed[i],
                'dropped': snap.dropped[i], 'queue_depth': snap.queue_depths[i]})
            statuses.append(st)
        bank = self.recognizer.bank
        bank_status = DiagnosticStatus(level=DiagnosticStatus.OK, name=f'{name}: bank',
                                       message=bank.summary(), hardware_id=s.device)
        bank_status.values = _key_values({
            'path': str(bank.path), 'entries': len(bank), 'classes': bank.num_classes,
            'num_points': bank.config.num_points, 'resample': s.resample, 'top_k': s.top_k,
            'unknown_threshold': self.recognizer.classifier.unknown_threshold or 0.0})
        statuses.append(bank_status)
        arr = DiagnosticArray(status=statuses)
        arr.header.stamp = self.get_clock().now().to_msg()
        self._pub_diag.publish(arr)

    # ------------------------------------------------------------------ shutdown

    def destroy_node(self) -> None:
        """Stop and join the worker before the publishers it uses go away."""
        self._stop_worker()
        super().destroy_node()

    def _stop_worker(self) -> None:
        stop = getattr(self, '_stop', None)
        if stop is None:
            return                     # construction failed before the worker existed
        stop.set()
        self._queue.close()
        self._worker.join(WORKER_JOIN_TIMEOUT_S)
        # After Ctrl-C the context is already shut down and the node logger could not
        # publish to /rosout any more; a child logger only writes to the console.
        log = (self.get_logger() if self.context.ok()
               else rclpy.logging.get_logger(f'{self.get_name()}.shutdown'))
        if self._worker.is_alive():
            log.warning(f'worker thread did not stop within {WORKER_JOIN_TIMEOUT_S:g} s')
        else:
            log.info('worker stopped, shutting down')


def _reason_key(text: str) -> str:
    """A short reason to count by: the decode error's text without names, numbers, details.

    "field 'x' (offset 8, 4 bytes) does not fit in point_step 8" -> "field does not fit in
    point_step", so the number of distinct counters stays small.
    """
    text = re.sub(r'\([^)]*\)', '', text)
    text = re.sub(r"'[^']*'|\"[^\"]*\"", '', text)
    text = re.sub(r'[-+]?\d[\d,._]*', '', text)
    text = re.split(r'[:;,=]', text)[0]
    return ' '.join(text.split())[:60] or 'malformed'


def _fmt_ms(v: float) -> str:
    return 'nan' if math.isnan(v) else f'{v:.1f}'


def _key_values(d: dict[str, Any]) -> list[KeyValue]:
    return [KeyValue(key=k, value=str(v)) for k, v in d.items()]


def main(args: list[str] | None = None) -> int:
    """Entry point (console script ``classifier_node``); returns the exit code."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    rclpy.init(args=args)
    node: ClassifierNode | None = None
    code = 0
    try:
        node = ClassifierNode()
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass                                   # Ctrl-C / SIGTERM: clean exit
    except (PointGNError, ParameterException) as exc:
        # One clear line, no traceback: the user has a file or a parameter to fix.
        rclpy.logging.get_logger(NODE_NAME).fatal(f'cannot start: {exc}')
        code = 1
    except Exception:
        if rclpy.ok():
            raise          # a bug: keep the traceback
        # Ctrl-C during start-up shut the context down under the constructor: a clean exit.
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == '__main__':
    sys.exit(main(sys.argv))


__all__ = ['ClassifierNode', 'NodeConfigError', 'PARAMETERS', 'main']
