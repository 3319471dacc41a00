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

import signal
import sys
import threading
import time
from typing import Any

import numpy as np
import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
import rclpy.logging
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy)

from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import ParameterDescriptor, ParameterType
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String
from visualization_msgs.msg import MarkerArray

from point_gn_ros.errors import BankError, PointGNError
from point_gn_ros.node.diagnostics import DiagnosticsBuilder
from point_gn_ros.node.markers import MarkerTracker, object_box
from point_gn_ros.node.params import PARAMETERS, NodeConfigError, Settings, settings_from_values
from point_gn_ros.node.pipeline import Answer, Pipeline
from point_gn_ros.node.rate_limited_log import RateLimitedLogger
from point_gn_ros.node.stats import NodeStats
from point_gn_ros.node.work_queue import WorkQueue

NODE_NAME = 'point_gn_classifier'
# Seconds between two warnings for the same topic (the rest are counted, then summarised).
WARN_PERIOD_S = 5.0
# How long shutdown waits for the worker to finish the batch it is classifying.
WORKER_JOIN_TIMEOUT_S = 10.0


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
        # Read-only and taken from the bank: an override on the command line is ignored.
        self.declare_parameter(
            'class_names', list(self.recognizer.class_names),
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
        self._publish_class_names(self._enrollment.live.current())
        self._pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)

        self._queue: WorkQueue[PointCloud2] = WorkQueue(len(s.input_topics), s.queue_size)
        self._stats = NodeStats(len(s.input_topics))
        self._markers = MarkerTracker(s.input_topics)
        self._warn = RateLimitedLogger(self.get_logger().warning, WARN_PERIOD_S)
        self._diagnostics = DiagnosticsBuilder()
        self._stop = threading.Event()
        self._pipeline = Pipeline(self.recognizer, s, self._stats, self._warn, self._stop)
        self._enrollment.attach(self._pipeline, list(s.input_topics), self._publish_class_names,
                                self._warn, s.min_points)
        self._worker = threading.Thread(
            target=self._pipeline.serve, args=(self._queue, self._publish, self.context.ok),
            name='point_gn_worker', daemon=True)
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
        self._pipeline.topic_names = [sub.topic_name or topic
                                      for sub, topic in zip(self._subs, s.input_topics,
                                                            strict=True)]
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
        return settings_from_values(values)

    def _make_recognizer(self) -> Any:
        from point_gn_ros.node.enrollment import Enrollment
        from point_gn_ros.recognizer import Recognizer, make_encoder

        s = self.settings
        encoder: list[Any] = []

        def make_model(bank: Any) -> Recognizer:
            """A recognizer for one bank version; every version shares one encoder."""
            if not encoder:
                # The fast encoder runs its own worker pool (default: every CPU); it gets
                # the same budget as torch, for the same reason.
                encoder.append(make_encoder(bank.config, s.device, threads=s.torch_threads))
            return Recognizer(bank, s.device, s.resample, s.top_k,
                              s.unknown_threshold or None, encoder=encoder[0])

        try:
            # Loads the bank; every later version comes from live enrollment.
            self._enrollment = Enrollment(self, s.bank_path or None, make_model)
        except ValueError as exc:       # e.g. unknown_threshold < 0 without a calibration
            raise NodeConfigError(str(exc)) from None
        return self._enrollment.recognizer

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

    # ------------------------------------------------------------------ output

    def _publish(self, answer: Answer) -> None:
        """Publish one message's answer (worker thread)."""
        from point_gn_ros.pointcloud2 import make_classifications
        job = answer.job
        header = job.item.payload.header
        ti = job.item.topic_index
        out = make_classifications(header, answer.centroids, answer.labels, answer.scores,
                                   answer.topk_ids, answer.topk_scores,
                                   np.asarray(job.segment_ids, dtype=np.int64), ti)
        self._pub_cls.publish(out)
        if self._pub_markers.get_subscription_count():   # nobody watching: skip the work
            boxes = [object_box(c, self._label_name(int(lbl)), int(lbl), float(sc))
                     for c, lbl, sc in zip(job.clouds, answer.labels, answer.scores,
                                           strict=True)]
            self._pub_markers.publish(self._markers.build(ti, header, boxes))
        stamp_ns = header.stamp.sec * 1_000_000_000 + header.stamp.nanosec
        # Header stamps are compared with the wall clock (sensor drivers stamp in system time).
        stamp_lat = (time.time_ns() - stamp_ns) * 1e-9 if stamp_ns > 0 else None
        self._stats.on_published(ti, len(job.clouds), time.monotonic() - job.item.receipt_time,
                                 stamp_lat)

    def _label_name(self, class_id: int) -> str:
        names = self._pipeline.class_names          # the version that made this answer
        return names[class_id] if 0 <= class_id < len(names) else 'unknown'

    def _publish_class_names(self, snap: Any) -> None:
        """(Re)publish the class list of a bank version (latched; after every change)."""
        self._pub_names.publish(String(data='\n'.join(snap.class_names)))

    # ------------------------------------------------------------------ diagnostics

    def _publish_diagnostics(self) -> None:
        snap = self._stats.snapshot(self._queue.dropped(), self._queue.depths())
        arr = self._diagnostics.build(
            self.get_fully_qualified_name(), snap, self.settings, self._pipeline.topic_names,
            self._worker.is_alive(), self._pipeline.recognizer.bank,
            self._pipeline.recognizer.classifier.unknown_threshold)
        arr.status.append(self._enrollment.diagnostic_status(self.get_fully_qualified_name()))
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
        self._enrollment.close()
        # After Ctrl-C the context is already shut down and the node logger could not
        # publish to /rosout any more; a child logger only writes to the console.
        log = (self.get_logger() if self.context.ok()
               else rclpy.logging.get_logger(f'{self.get_name()}.shutdown'))
        if self._worker.is_alive():
            log.warning(f'worker thread did not stop within {WORKER_JOIN_TIMEOUT_S:g} s')
        else:
            log.info('worker stopped, shutting down')


def main(args: list[str] | None = None) -> int:
    """Entry point (console script ``classifier_node``); returns the exit code."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    rclpy.init(args=args)
    node: ClassifierNode | None = None
    code = 0
    try:
        node = ClassifierNode()
        # Two threads: the enrollment services (own callback group) may wait for a save or
        # a refit without holding up the input callbacks.
        executor = MultiThreadedExecutor(num_threads=2)
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
