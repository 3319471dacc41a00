"""ROS 2 managed (lifecycle) node: classify segmented object point clouds with Point-GN.

Subscribes to one or more sensor_msgs/PointCloud2 topics (each message one object,
or several objects split by an integer segment field) and publishes

* ``~/detections`` (vision_msgs/Detection3DArray, when vision_msgs is installed): input
  header; per object its box in the input frame, top-k (class name, score), id = segment id;
* ``~/label_info`` (vision_msgs/LabelInfo, transient local): class id -> name, threshold;
* ``~/classifications`` (sensor_msgs/PointCloud2): one point per object, at its
  centroid in the input frame, with class_id, score, top-k ids/scores,
  segment_id and topic_index; same header as the input message;
* ``~/markers`` (visualization_msgs/MarkerArray): a "label score" text and a
  bounding box per object, with a lifetime;
* ``~/class_names`` (std_msgs/String, latched): one class name per line,
  line index = class_id;
* ``/diagnostics`` (diagnostic_msgs/DiagnosticArray) once a second.

Lifecycle: configure loads and validates the bank and starts the worker; activate creates
the subscriptions and enables the (lifecycle) publishers; deactivate removes the
subscriptions; cleanup stops the worker and frees the bank. `autostart` (default true) walks
to active at start, so the node runs as a plain one. Extra interfaces plug in as
`rclpy.lifecycle.ManagedEntity`s (``ClassifierNode(extensions=...)``): they get the same
transitions after the node's own work; `replace_recognizer()` swaps the bank between batches.

Threading: an intake thread (node/intake.py), not the executor, takes the input messages
off DDS and only enqueues them (bounded per topic, dropping the oldest); one worker thread
(node/pipeline.py, ROS-free) decodes, resamples, encodes and classifies in micro-batches
across topics, so the executor stays responsive however slow the encoder is, and a burst
of input costs it nothing.
"""

from __future__ import annotations

import point_gn_ros.node._quiet_interrupt  # noqa: F401 - first: before the slow imports

from collections.abc import Callable, Sequence
import signal
import sys
import threading
import time
from typing import Any

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode, LifecycleState, ManagedEntity, TransitionCallbackReturn
import rclpy.logging
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import PointCloud2

from point_gn_ros.errors import BankError, PointGNError
from point_gn_ros.node.diagnostics import DiagnosticsBuilder
from point_gn_ros.node.diagnostics_mixin import DiagnosticsMixin
from point_gn_ros.node.frames import UpConvention
from point_gn_ros.node.gc_pauses import freeze_startup_objects, thaw
from point_gn_ros.node.input_qos import BEST_EFFORT, RELIABLE, InputQoS
from point_gn_ros.node.intake import Intake, NotForExecutors
from point_gn_ros.node.outputs import Outputs, vision_msgs_available
from point_gn_ros.node.parameter_mixin import ParameterMixin
from point_gn_ros.node.parent_death import exit_with_parent
from point_gn_ros.node.params import (PARAMETERS, NodeConfigError, Settings,
                                      resolve_unknown_threshold, rule_thresholds,
                                      settings_from_values)
from point_gn_ros.node.pipeline import Answer, Pipeline
from point_gn_ros.node.rate_limited_log import RateLimitedLogger
from point_gn_ros.node.stats import NodeStats
from point_gn_ros.node.watchdog import InputWatchdog
from point_gn_ros.node.work_queue import WorkQueue

NODE_NAME = 'point_gn_classifier'
# Seconds between two warnings for the same topic (the rest are counted, then summarised).
WARN_PERIOD_S = 5.0
# How long shutdown waits for the worker to finish the batch it is classifying.
WORKER_JOIN_TIMEOUT_S = 10.0
# How often the input topics' publishers are checked (QoS 'auto', incompatible QoS), s.
QOS_CHECK_S = 0.5
# Counted when a message taken before deactivate is finished while inactive (not published).
REJECT_INACTIVE = 'node inactive'

Extension = Callable[['ClassifierNode'], ManagedEntity]


def stamp_latency_s(now_ns: int, stamp_ns: int) -> float | None:
    """Header stamp -> now, both on the node clock; None when either is unset (0).

    The node clock is the ROS clock: system time normally, /clock under use_sim_time, so a
    replayed bag's stamps are compared with replayed time, never with the wall clock.
    """
    if now_ns <= 0 or stamp_ns <= 0:
        return None
    return (now_ns - stamp_ns) * 1e-9


class ClassifierNode(ParameterMixin, DiagnosticsMixin, LifecycleNode):
    """Point-GN classifier node; see the module docstring for topics, lifecycle, threading.

    Parameter and /diagnostics methods: node/parameter_mixin.py, node/diagnostics_mixin.py.
    """

    def __init__(self, *, extensions: Sequence[Extension] = (), **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self._declare_parameters()
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.settings: Settings | None = None
        self.recognizer: Any = None
        self.class_names: list[str] = []
        self.config_error: Exception | None = None
        self.has_vision_msgs = vision_msgs_available()
        self._active = False
        self._setting_class_names = False
        self._subs: list[Any] = []
        self._input_qos: InputQoS | None = None
        self._qos_timer: Any = None
        self._qos_soon: Any = None
        self._intake: Intake | None = None
        self._pipeline: Pipeline | None = None
        self._worker: threading.Thread | None = None
        self._stop = threading.Event()
        self._timer: Any = None
        self._outputs: Outputs | None = None
        self._watchdog: InputWatchdog | None = None
        self._diagnostic_sources: list[Callable[[str], Any]] = []
        self._extensions = [make(self) for make in extensions]
        for entity in self._extensions:
            self.add_managed_entity(entity)
        self._warn_unknown_overrides()          # after the extensions declared theirs

    # ------------------------------------------------------------------ lifecycle

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Validate parameters, load the bank, create publishers, start the worker."""
        self.config_error = None
        try:
            self._configure()
        except (PointGNError, ParameterException) as exc:
            self.config_error = exc
            if not self.autostart:        # autostart: main() says it once, as FATAL
                self.get_logger().error(f'configure failed: {exc}')
            self._teardown()
            return TransitionCallbackReturn.FAILURE
        except Exception as exc:          # a bug: main() re-raises it with its traceback
            self.config_error = exc
            self.get_logger().error(f'configure failed: {type(exc).__name__}: {exc}')
            self._teardown()
            return TransitionCallbackReturn.ERROR
        ret = super().on_configure(state)         # the extensions configure here
        if ret == TransitionCallbackReturn.SUCCESS:
            frozen = freeze_startup_objects()       # node/gc_pauses.py: no 100 ms pauses
            self.get_logger().info(f'{frozen} start-up objects kept out of full garbage '
                                   f'collections')
        return ret

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Subscribe to the input topics and enable the publishers."""
        s = self.settings
        self._input_qos = InputQoS([s.topic(i).qos_reliability
                                    for i in range(len(s.input_topics))])
        self._subs = []
        for i, topic in enumerate(s.input_topics):
            reliability = self._input_qos.choose(i, self.get_publishers_info_by_topic(topic))
            self._subs.append(self._subscribe(i, reliability or RELIABLE))
        self._pipeline.topic_names = [sub.topic_name or topic
                                      for sub, topic in zip(self._subs, s.input_topics,
                                                            strict=True)]
        self._watchdog = InputWatchdog(len(self._subs))
        self._intake = Intake(self.context, self._subs, self._on_cloud, self._on_intake_error)
        # Publishers come and go: follow them ('auto'), describe the incompatible ones.
        self._qos_timer = self.create_timer(QOS_CHECK_S, self._check_input_qos)
        # and at once after an incompatible-QoS event (a best-effort publisher appeared)
        self._qos_soon = self.create_timer(0.001, self._check_input_qos_now)
        self._qos_soon.cancel()
        ret = super().on_activate(state)          # enables the lifecycle publishers
        self._active = True
        self._publish_labels()
        inputs = ', '.join(
            f'{name} ({self._describe_input(i)})'
            for i, name in enumerate(self._pipeline.topic_names))
        self.get_logger().info(f'classifying {inputs}, depth {s.qos_depth} -> '
                               f"{', '.join(self._outputs.topic_names())}")
        return ret

    def _describe_input(self, index: int) -> str:
        t = self.settings.topic(index)
        chosen = self._input_qos.topics[index].reliability
        qos = f'auto: {chosen}' if t.qos_reliability == 'auto' else chosen
        return f'{qos}, segment field {t.segment_field or "none"}, up axis {t.up_axis}'

    def _subscribe(self, index: int, reliability: str, again: bool = False) -> Any:
        """Input topic `index`'s subscription with `reliability`, taken by the intake thread.

        Taken by the intake thread, not the executor (node/intake.py: the executor's cost
        per message starved the worker under bursts). The callback is the same enqueue, so
        an executor that ignored callback groups would still count and queue each message.
        Its incompatible-QoS events run on the executor (a group of their own).
        """
        s = self.settings
        qos = QoSProfile(
            depth=s.qos_depth, history=HistoryPolicy.KEEP_LAST,
            reliability=(ReliabilityPolicy.BEST_EFFORT if reliability == BEST_EFFORT
                         else ReliabilityPolicy.RELIABLE),
            durability=DurabilityPolicy.VOLATILE)
        sub = self.create_subscription(
            PointCloud2, s.input_topics[index], lambda msg, i=index: self._on_cloud(i, msg),
            qos, callback_group=NotForExecutors(),
            event_callbacks=SubscriptionEventCallbacks(use_default_callbacks=False))
        handlers = SubscriptionEventCallbacks(
            incompatible_qos=lambda event, i=index: self._on_incompatible_qos(i, event),
            use_default_callbacks=False).create_event_handlers(
                MutuallyExclusiveCallbackGroup(), sub.handle, sub.topic_name)
        for handler in handlers:
            sub.event_handlers.append(handler)     # destroyed with the subscription
            self.add_waitable(handler)
        self._input_qos.subscribed(index, reliability, again)
        return sub

    def _check_input_qos(self) -> None:
        """Timer: follow each 'auto' topic's publishers; warn once per incompatible kind."""
        if not self._active:
            return
        try:
            for i, topic in enumerate(self._pipeline.topic_names):
                wanted = self._input_qos.choose(i, self.get_publishers_info_by_topic(topic))
                if wanted is not None:
                    self._resubscribe(i, wanted)
                self._describe_incompatible(i)
        finally:
            if self._intake is None:           # stopped by a re-subscription
                self._intake = Intake(self.context, self._subs, self._on_cloud,
                                      self._on_intake_error)

    def _check_input_qos_now(self) -> None:
        self._qos_soon.cancel()             # one shot
        self._check_input_qos()

    def _describe_incompatible(self, index: int) -> None:
        """Record topic `index`'s publishers; warn once per kind of incompatible one."""
        topic = self._pipeline.topic_names[index]
        for text in self._input_qos.observe(index, self.get_publishers_info_by_topic(topic)):
            self.get_logger().warning(
                f'input {topic}: a publisher offers incompatible QoS ({text}): none of its '
                "messages arrive; set qos_reliability to 'auto' or 'best_effort', or make the "
                'publisher reliable')

    def _resubscribe(self, index: int, reliability: str) -> None:
        """Re-create input `index`'s subscription (the queue, stats and worker go on)."""
        self._stop_intake()                 # it waits on the subscription being replaced
        self.destroy_subscription(self._subs[index])
        self._subs[index] = self._subscribe(index, reliability, again=True)
        self.get_logger().info(f'input {self._pipeline.topic_names[index]}: publishers '
                               f'changed, subscribed again with {reliability}')

    def _on_incompatible_qos(self, index: int, event: Any) -> None:
        """The middleware found a publisher this subscription cannot match (executor)."""
        self._input_qos.on_event(index, event.total_count_change)
        if self._active and self._qos_soon is not None:
            # re-checked from a timer: not within the handler of the subscription it replaces
            self._qos_soon.reset()

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop answering: no subscriptions, publishers disabled (the bank stays loaded)."""
        self._active = False
        self._destroy_subscriptions()
        self.get_logger().info('deactivated: not answering')
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop the worker, destroy the publishers, free the bank."""
        ret = super().on_cleanup(state)
        self._teardown()
        self.get_logger().info('cleaned up: bank released')
        return ret

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        ret = super().on_shutdown(state)
        self._active = False
        self._destroy_subscriptions()
        self._teardown()
        return ret

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._active = False
        self._destroy_subscriptions()
        self._teardown()
        return super().on_error(state)

    def _configure(self) -> None:
        s = self.settings = settings_from_values(self._values(), self._topic_values())
        self._configure_torch()
        t0 = time.perf_counter()
        recognizer = self._make_recognizer()
        bank = recognizer.bank
        self.get_logger().info(f'bank {bank.path}: {bank.summary()} '
                               f'(loaded in {time.perf_counter() - t0:.1f} s)')
        # Pay compile / first-call costs before any message can arrive.
        warm_s = recognizer.warmup()
        self.get_logger().info(f'warm-up done in {warm_s:.1f} s: {recognizer.encoder!r}, '
                               f'device {s.device}, {s.encoder_threads} encoder / '
                               f'{s.torch_threads} torch thread(s)')
        self._set_recognizer(recognizer)

        self._outputs = Outputs(self, s.input_topics, s.qos_depth, self.has_vision_msgs)
        if not self.has_vision_msgs:
            self.get_logger().warning('vision_msgs is not installed: no ~/detections or '
                                      '~/label_info, only ~/classifications (PointCloud2)')
        self._pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)

        self._stats = NodeStats(len(s.input_topics))
        self._queue: WorkQueue[PointCloud2] = WorkQueue(len(s.input_topics), s.queue_size,
                                                        on_drop=self._stats.on_dropped)
        self._warn = RateLimitedLogger(self.get_logger().warning, WARN_PERIOD_S)
        self._diagnostics = DiagnosticsBuilder()
        self._stop = threading.Event()
        self._pipeline = Pipeline(self.recognizer, s, self._stats, self._warn, self._stop)
        # A tf2 lookup (input frame -> gravity-aligned frame) can replace the convention here.
        self._pipeline.frame_rotation = UpConvention(s.up_axis)
        self._pipeline.topic_rotations = {i: UpConvention(s.topic(i).up_axis)
                                          for i in range(len(s.input_topics))
                                          if s.topic(i).up_axis != s.up_axis}
        self._worker = threading.Thread(
            target=self._pipeline.serve, args=(self._queue, self._publish, self.context.ok),
            name='point_gn_worker', daemon=True)
        self._worker.start()
        self._timer = self.create_timer(1.0, self._publish_diagnostics)

    def _make_recognizer(self) -> Any:
        from point_gn_ros.bank.store import FeatureBank
        from point_gn_ros.recognizer import Recognizer, make_encoder

        s = self.settings
        bank = FeatureBank.load(s.bank_path or None)
        if bank.config.num_points != s.num_points:
            raise BankError(f'{bank.path}: bank was built for num_points='
                            f'{bank.config.num_points}, node parameter num_points='
                            f'{s.num_points}')
        # The fast encoder runs its own worker pool (default: every CPU): bounded by its own
        # parameter, apart from torch's (the classifier), which wants fewer.
        encoder = make_encoder(bank.config, s.device, threads=s.encoder_threads)
        try:
            return Recognizer(bank, s.device, s.resample, s.top_k,
                              s.unknown_threshold or None, encoder=encoder, search=s.search,
                              object_test=s.object_test, metric_size=s.metric_size,
                              **rule_thresholds(s))
        except ValueError as exc:       # e.g. unknown_threshold < 0 without a calibration
            raise NodeConfigError(str(exc)) from None

    def _configure_torch(self) -> None:
        import torch
        torch.set_num_threads(self.settings.torch_threads)
        try:
            torch.set_num_interop_threads(1)   # the worker is the only caller
        except RuntimeError:
            pass                               # already fixed (torch allows one call)

    def replace_recognizer(self, recognizer: Any) -> None:
        """Swap in another recognizer (e.g. a re-built bank); takes effect between batches.

        Raises NodeConfigError when the node is not configured or the bank does not fit the
        node's num_points / unknown_threshold.
        """
        s = self.settings
        if s is None or self._pipeline is None:
            raise NodeConfigError('the node is not configured')
        if recognizer.bank.config.num_points != s.num_points:
            raise NodeConfigError(f'bank num_points={recognizer.bank.config.num_points}, node '
                                  f'num_points={s.num_points}')
        resolve_unknown_threshold(recognizer.bank, s.unknown_threshold)
        self._pipeline.update(recognizer=recognizer)
        self._set_recognizer(recognizer)
        if self._active:
            self._publish_labels()

    def _publish_labels(self) -> None:
        """The latched class list: ~/class_names and ~/label_info."""
        if not self._active:
            return
        threshold = resolve_unknown_threshold(self.recognizer.bank,
                                              self.settings.unknown_threshold)
        self._outputs.publish_labels(self.class_names, threshold,
                                     self.get_clock().now().to_msg())

    def _destroy_subscriptions(self) -> None:
        for timer in (self._qos_timer, self._qos_soon):
            if timer is not None:
                self.destroy_timer(timer)
        self._qos_timer = self._qos_soon = None
        self._stop_intake()                 # first: it waits on the subscriptions
        for sub in self._subs:
            self.destroy_subscription(sub)
        self._subs = []

    def _teardown(self) -> None:
        """Undo configure (any part of it); safe to call twice."""
        thaw()
        self._stop_worker()
        if self._timer is not None:
            self.destroy_timer(self._timer)
            self._timer = None
        if self._outputs is not None:
            self._outputs.destroy()
            self._outputs = None
        if getattr(self, '_pub_diag', None) is not None:
            self.destroy_publisher(self._pub_diag)
            self._pub_diag = None
        self._pipeline = None
        self.recognizer = None          # the bank's tensors go with it
        self.settings = None

    # ------------------------------------------------------------------ input

    def _on_cloud(self, topic_index: int, msg: PointCloud2) -> None:
        """Each input message (intake thread): enqueue with the receipt time, nothing else."""
        self._stats.on_received(topic_index)
        self._watchdog.on_message(topic_index)
        self._queue.put(topic_index, msg)   # a message it pushes out: stats.on_dropped

    def _on_intake_error(self, exc: Exception) -> None:
        self._warn(('intake',), f'taking an input message failed: {type(exc).__name__}: {exc}')

    # ------------------------------------------------------------------ output

    def _publish(self, answer: Answer) -> None:
        """Publish one message's answer (worker thread)."""
        job = answer.job
        if not self._active:       # taken before deactivate: counted, not answered
            self._stats.on_rejected(REJECT_INACTIVE)
            return
        # The names of the recognizer that produced this answer (the worker swaps it only
        # between batches; self.class_names may already be a newer bank's).
        self._outputs.publish(answer, self._pipeline.class_names,
                              self.settings.marker_lifetime_s)
        header = job.item.payload.header
        stamp_ns = header.stamp.sec * 1_000_000_000 + header.stamp.nanosec
        stamp_lat = stamp_latency_s(self.get_clock().now().nanoseconds, stamp_ns)
        self._stats.on_published(job.item.topic_index, len(job.clouds),
                                 time.monotonic() - job.item.receipt_time, stamp_lat)

    # ------------------------------------------------------------------ shutdown

    def destroy_node(self) -> None:
        """Stop and join the worker before the publishers it uses go away.

        Extensions with a `stop()` (enrollment) stop first: nothing they queued runs after.
        """
        self._active = False
        for entity in self._extensions:
            if callable(getattr(entity, 'stop', None)):
                entity.stop()
        self._stop_intake()
        self._stop_worker()
        super().destroy_node()

    def _stop_intake(self) -> None:
        intake, self._intake = self._intake, None
        if intake is not None and not intake.stop():
            self.get_logger().warning('input intake thread did not stop')

    def _stop_worker(self) -> None:
        worker, self._worker = self._worker, None
        if worker is None:
            return                     # not configured
        self._stop.set()
        self._queue.close()
        worker.join(WORKER_JOIN_TIMEOUT_S)
        # After Ctrl-C the context is already shut down and the node logger could not
        # publish to /rosout any more; a child logger only writes to the console.
        log = (self.get_logger() if self.context.ok()
               else rclpy.logging.get_logger(f'{self.get_name()}.shutdown'))
        if worker.is_alive():
            log.warning(f'worker thread did not stop within {WORKER_JOIN_TIMEOUT_S:g} s')
        else:
            log.info('worker stopped')


def autostart(node: ClassifierNode) -> None:
    """Configure and activate; raises the configure error (PointGNError: a user's mistake)."""
    if node.trigger_configure() != TransitionCallbackReturn.SUCCESS:
        raise node.config_error or NodeConfigError('configure failed')
    if node.trigger_activate() != TransitionCallbackReturn.SUCCESS:
        raise NodeConfigError('activate failed')


def main(args: list[str] | None = None) -> int:
    """Entry point (console script ``classifier_node``); returns the exit code."""
    interrupted = threading.Event()

    def on_sigint(signum: int, frame: object) -> None:
        interrupted.set()
        raise KeyboardInterrupt

    # A KeyboardInterrupt raised inside a pybind11 call of rclpy's can come out of spin() as
    # another exception ("Unable to convert call argument ..."): after Ctrl-C it is still a
    # clean exit, so the handler records that Ctrl-C came.
    signal.signal(signal.SIGINT, on_sigint)
    rclpy.init(args=args)               # its signal handlers: SIGINT and SIGTERM shut down
    exit_with_parent()                  # under ros2 launch: stop when launch is killed
    node: ClassifierNode | None = None
    code = 0
    try:
        from point_gn_ros.node.enrollment import Enrollment
        node = ClassifierNode(extensions=[Enrollment])
        if node.autostart:
            autostart(node)
        else:
            node.get_logger().info('waiting for a lifecycle manager (autostart is false)')
        # One thread: rclpy's multi-threaded executor triples the latency at 100 objects/s;
        # services that wait (enrollment saves) are coroutines instead.
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
        if rclpy.ok() and not interrupted.is_set():
            raise          # a bug: keep the traceback
        # Ctrl-C shut the context down under the constructor, or interrupted a call into
        # rclpy's C++ layer: a clean exit.
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == '__main__':
    sys.exit(main(sys.argv))


__all__ = ['ClassifierNode', 'Extension', 'NodeConfigError', 'PARAMETERS', 'autostart', 'main',
           'stamp_latency_s']
