"""Live enrollment interfaces of the classifier node: parameters, topics, services, swaps.

Off unless the read-only parameter ``enable_enrollment`` is true: then, and only then, the
node creates the topics and services below. ROS 2 topics and services are unauthenticated
without SROS2, so with enrollment on ANY peer on the domain can teach, forget and save
(docs/NODE.md "Enrollment"; SROS2 access control restricts who may).

Standard interfaces only (no custom message package), all in the node's private namespace:

* ``~/enroll`` (vision_msgs/Detection3DArray) + ``~/enroll_scene`` (sensor_msgs/PointCloud2),
  when vision_msgs is importable: the points of the scene cloud with the SAME header stamp
  inside each detection's ``bbox`` (in the cloud's frame; a zero-size box = the whole cloud)
  are one example of class ``results[0].hypothesis.class_id`` (new or existing). vision_msgs 4
  (ROS 2 Humble and later) dropped ``Detection3D.source_cloud``, hence the paired cloud.
  Unlabelled detections and unpaired messages (after 5 s) are refused and counted;
* ``~/enroll_cloud`` (sensor_msgs/PointCloud2, always; the fallback where vision_msgs is
  absent): each message is one example of the class named by parameter ``enroll_class``;
* ``~/start_capture`` / ``~/stop_capture`` (std_srvs/Trigger): while capturing, every object
  the node classifies on ``capture_topic`` (default: every input topic) is also kept (up to
  ``capture_max``); stop enrolls them under ``enroll_class`` (with ``enroll_fuse_views``,
  as views of one object in one fixed frame: their fused cloud and 8 scans of it too);
* ``~/forget`` (std_srvs/Trigger): removes the class named by ``enroll_class``;
* ``~/save_bank`` (std_srvs/Trigger): writes the current bank atomically (temporary file,
  fsync, rename: a crash leaves the previous file whole) to ``save_bank_path`` (read-only,
  set at start), or, when that is an existing folder, to the file named by
  ``save_bank_name`` inside it (a plain ``*.npz`` name: no folders, no ``..``, not hidden).

Bounds (node/enroll_engine.py): clouds over ``max_points_per_message``, bad class names,
classes beyond ``enroll_max_classes``, examples beyond ``enroll_max_examples`` per request
or ``enroll_max_pending`` waiting are refused and counted by reason; forget / save requests
beyond a few waiting are answered "busy"; the worker encodes enrollment examples only when
no input waits (at least one step a second); shutdown drops what waits.

Every change makes a new bank version (copy-on-write, bank/enroll.py) that the worker picks
up between two micro-batches (Pipeline.update): each answer is computed with one version.
Classes with fewer than ``min_examples_per_class`` examples are kept but not predicted;
``enroll_augment`` stores each example in several frames (core/augment.py).
Examples are turned z-up like the objects the node classifies (frames.py) and encoded on the
worker between micro-batches (node/enroll_engine.py); ~/enroll's stamp pairing and box crop
are in node/enroll_detections.py.
"""

from __future__ import annotations

from concurrent.futures import Future
import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from pathlib import Path

import rclpy.logging
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.lifecycle import ManagedEntity, TransitionCallbackReturn
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future as RclpyFuture
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger

from point_gn_ros.bank.discriminant import MAX_BUDGET, MAX_SHARE
from point_gn_ros.bank.enroll import remove_stale_temps
from point_gn_ros.bank.enroll import BankFile, EnrollResult, predictable
from point_gn_ros.bank.refit import RefitPolicy
from point_gn_ros.bank.live import LiveBank, Snapshot
from point_gn_ros.bank.refit import LDA_PRIORS
from point_gn_ros.core.augment import AUGMENTS
from point_gn_ros.errors import DecodeError, PointGNError
from point_gn_ros.node.enroll_detections import StampPairing, crop_box
from point_gn_ros.node.enroll_engine import EnrollEngine
from point_gn_ros.node.frames import to_z_up
from point_gn_ros.node.params import rule_thresholds

try:
    from vision_msgs.msg import Detection3DArray
except ImportError:          # a ROS install without vision_msgs: PointCloud2 route only
    Detection3DArray = None

# A detection array waits this long for the scene cloud of the same stamp (and vice versa).
PAIR_TIMEOUT_S = 5.0
# Detection arrays (and scene clouds) waiting for their partner at most; older ones expire.
PAIR_MAX_WAITING = 16
# Requests a service's DDS reader keeps before it is served (KEEP_LAST): a burst of up to
# this many calls is taken, each answered (done, or "busy" at once).
SERVICE_QUEUE_DEPTH = 100
# Enrollment examples the worker encodes in one step at most (a query arriving meanwhile
# waits for them): a few, so that a step costs a fraction of a micro-batch.
ENROLL_CHUNK = 8
# While input waits, the worker still takes one enrollment step at least this often.
ENROLL_STEP_MIN_S = 1.0
_WRITABLE = ('enroll_class', 'save_bank_name', 'capture_topic')

# name -> (default, description, extra ParameterDescriptor kwargs); the writable ones are read
# each time a service is called, the others once at start.
ENROLL_PARAMETERS: dict[str, tuple[Any, str, dict[str, Any]]] = {
    'enable_enrollment': (False, 'Create the enrollment topics and services (~/enroll, '
                                 '~/enroll_scene, ~/enroll_cloud, ~/start_capture, '
                                 '~/stop_capture, ~/forget, ~/save_bank). Any peer on the '
                                 'ROS domain can then change the bank: use SROS2 access '
                                 'control on a shared graph. Default false: no peer can.', {}),
    'enroll_class': ('', 'Class that ~/enroll_cloud, ~/start_capture and ~/forget act on '
                         '(settable at run time).', {}),
    'save_bank_path': ('', "File ~/save_bank writes (atomically), or an existing folder: "
                           "then the file save_bank_name in it. '' = no saves. Set at start "
                           'only; the node creates no folders.', {}),
    'save_bank_name': ('bank.npz', 'With save_bank_path a folder: the file ~/save_bank writes '
                                   'in it (a plain *.npz name: no folders, no "..", not '
                                   'hidden); settable at run time.', {}),
    'enroll_max_classes': (256, 'Classes the bank may hold at most (built + enrolled); an '
                                'example of a further new class is refused.',
                           {'integer_range': [IntegerRange(from_value=1, to_value=4096,
                                                           step=1)]}),
    'enroll_max_examples': (200, "Examples one request (a message, a detection array's "
                                 'class, a capture) enrolls at most; the rest are refused.',
                            {'integer_range': [IntegerRange(from_value=1, to_value=100_000,
                                                            step=1)]}),
    'capture_topic': ('', "Input topic ~/start_capture takes objects from; '' = every input "
                          'topic (settable at run time).', {}),
    'min_examples_per_class': (1, 'A class is predicted only once it has this many examples.',
                               {'integer_range': [IntegerRange(from_value=1, to_value=10_000,
                                                               step=1)]}),
    'enroll_refit_gamma': ('auto', "After a change: 'keep' gamma, re-choose it by 'cv', or "
                                   "'auto' (CV on banks of <= 2,000 entries).",
                           {'additional_constraints': "one of 'auto', 'keep', 'cv'"}),
    'enroll_lda_prior': ('typical', "LDA class priors after a change: 'entries' (class shares "
                                    "of the bank), 'balanced' (equal priors) or 'typical' "
                                    '(default: built classes keep theirs, each enrolled class '
                                    'gets their mean share).',
                         {'additional_constraints': "one of 'entries', 'balanced', 'typical'"}),
    'enroll_lda_debias': (2.0, 'Share f of the mean-noise correction of a wide LDA '
                               '(bank/discriminant.py lda_noise_trace) for classes created by '
                               'enrollment: LDA bias += f tr(P Sigma) / (2 n); 0 = none; with '
                               'enroll_steal_budget > 0, the most a class gets. Default 2: the '
                               'choice of CV on the train split (README).',
                          {'floating_point_range': [FloatingPointRange(
                              from_value=0.0, to_value=MAX_SHARE, step=0.0)]}),
    'enroll_steal_budget': (0.001, 'Steal budget rho of each class created by enrollment '
                                   '(bank/discriminant.py): it gets the largest share <= '
                                   'enroll_lda_debias whose predicted share of built-class '
                                   'examples called it stays <= rho; 0 = every such class gets '
                                   'enroll_lda_debias. Default 0.001: the train-CV choice.',
                            {'floating_point_range': [FloatingPointRange(
                                from_value=0.0, to_value=MAX_BUDGET, step=0.0)]}),
    'enroll_augment': ('none', "Frames each example is stored in (core/augment.py): 'none', "
                               "'mirror', 'rot4' or 'd4' (8 entries per example: the frames "
                               'the yaw alignment confuses on partial scans).',
                       {'additional_constraints': "one of 'none', 'mirror', 'rot4', 'd4'"}),
    'enroll_max_pending': (512, 'Examples waiting (to be encoded or committed) at most; '
                                'beyond, refused and counted.',
                           {'integer_range': [IntegerRange(from_value=1, to_value=100_000,
                                                           step=1)]}),
    'enroll_fuse_views': (False, 'A capture (~/start_capture .. ~/stop_capture) holds views '
                                 'of ONE object in one fixed frame (capture_topic in odom or '
                                 'map): also enroll their fused cloud and 8 scans simulated '
                                 'from it (core/fusion.py). Views that do not overlap (a '
                                 'moving frame) are enrolled as they are, with a warning.', {}),
    'capture_max': (200, 'Objects one capture keeps at most.',
                    {'integer_range': [IntegerRange(from_value=1, to_value=100_000, step=1)]}),
}


class Enrollment(ManagedEntity):
    """Live enrollment for a ClassifierNode: `ClassifierNode(extensions=[Enrollment])`.

    Constructed with the node (declares the parameters, adds the `<node>: enrollment`
    diagnostics); on configure (after the node loaded its bank and started its worker) it
    wraps that bank in a LiveBank and hooks the worker; on activate it creates the topics
    and services, on deactivate it removes them; cleanup releases the bank. Every new
    version reaches the node through `node.replace_recognizer` (swap between micro-batches,
    class names and label info republished).
    """

    def __init__(self, node: Any) -> None:
        self.node = node
        self.values = {name: node.declare_parameter(
            name, default, ParameterDescriptor(description=text,
                                               read_only=name not in _WRITABLE, **extra)).value
            for name, (default, text, extra) in ENROLL_PARAMETERS.items()}
        self.enabled = bool(self.values['enable_enrollment'])
        self.live: LiveBank | None = None
        self.engine: EnrollEngine | None = None
        self._pipeline: Any = None
        self._subs: list[Any] = []
        self._services: list[Any] = []
        self._save_base: tuple[Path, bool] | None = None    # (path, is a folder)
        self._last_step = 0.0
        node.add_diagnostic_source(self.diagnostic_status)

    # ------------------------------------------------------------------ lifecycle

    def on_configure(self, state: Any) -> TransitionCallbackReturn:
        node, log = self.node, self.node.get_logger()
        if not self.enabled:
            log.info('enrollment is off (enable_enrollment false): no peer can change the bank')
            return TransitionCallbackReturn.SUCCESS
        gamma = self.values['enroll_refit_gamma']
        if gamma not in ('auto', 'keep', 'cv'):
            log.error(f'parameter enroll_refit_gamma={gamma!r} must be one of auto, keep, cv')
            return TransitionCallbackReturn.FAILURE
        augment = self.values['enroll_augment']
        if augment not in AUGMENTS:
            log.error(f'parameter enroll_augment={augment!r} must be one of '
                      f'{", ".join(AUGMENTS)}')
            return TransitionCallbackReturn.FAILURE
        prior = self.values['enroll_lda_prior']
        if prior not in LDA_PRIORS:
            log.error(f'parameter enroll_lda_prior={prior!r} must be one of '
                      f'{", ".join(LDA_PRIORS)}')
            return TransitionCallbackReturn.FAILURE
        policy = RefitPolicy(gamma=gamma, min_examples=self.values['min_examples_per_class'],
                             lda_prior=prior,
                             lda_debias=float(self.values['enroll_lda_debias']),
                             lda_steal_budget=float(self.values['enroll_steal_budget']))
        try:
            # The first version's model derives from the node's recognizer (same rows): its
            # search index's basis is reused, not fitted again (~0.4 s of start-up CPU).
            self.live = LiveBank(BankFile.of_loaded(node.recognizer.bank),
                                 lambda bank: self._make_model(bank, node.recognizer), policy,
                                 derive=self._make_model)
            node.replace_recognizer(self.live.current().model)
        except (PointGNError, ValueError) as exc:
            log.error(f'enrollment: {exc}')
            self.live = None
            return TransitionCallbackReturn.FAILURE
        # The node's worker (node/pipeline.py) calls these between and inside micro-batches.
        self._pipeline = node._pipeline
        self.engine = EnrollEngine(
            self.live, self._swap, log.info, node._warn,
            chunk=min(node.settings.max_batch, ENROLL_CHUNK),
            max_pending=self.values['enroll_max_pending'],
            capture_max=self.values['capture_max'], min_points=node.settings.min_points,
            augment=augment, fuse_views=bool(self.values['enroll_fuse_views']),
            max_classes=self.values['enroll_max_classes'],
            max_examples=self.values['enroll_max_examples'])
        self._pipeline.observe = self._observe
        self._pipeline.between_batches = self._between_batches
        self._save_base = self._configure_save_target()
        log.warning('enrollment is on: ANY peer on this ROS domain can teach, forget and save '
                    '(enable_enrollment); restrict who may with SROS2 access control on a '
                    'shared graph')
        return TransitionCallbackReturn.SUCCESS

    def _configure_save_target(self) -> tuple[Path, bool] | None:
        """save_bank_path, resolved once; the temporary files of a killed save removed."""
        text = str(self.values['save_bank_path'] or '').strip()
        if not text:
            return None
        path = Path(text).expanduser().absolute()
        folder = path.is_dir()
        log = self.node.get_logger()
        if not folder and not path.parent.is_dir():
            log.warning(f'save_bank_path {path}: folder {path.parent} does not exist (the '
                        f'node creates none): ~/save_bank will fail')
        for tmp in remove_stale_temps(path):
            log.info(f'removed {tmp}, left by an interrupted save')
        return path, folder

    def save_target(self) -> tuple[Path | None, str]:
        """The file ~/save_bank writes now -> (path, '') or (None, why not)."""
        if self._save_base is None:
            return None, ('no save_bank_path: set it (a file, or a folder with save_bank_name) '
                          'at start')
        base, folder = self._save_base
        if not folder:
            return base, ''
        name = self._param('save_bank_name')
        problem = save_name_problem(name)
        if problem:
            return None, f'save_bank_name {name[:80]!r}: {problem}'
        return base / name, ''

    def on_activate(self, state: Any) -> TransitionCallbackReturn:
        node = self.node
        if not self.enabled:
            return TransitionCallbackReturn.SUCCESS
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                         history=HistoryPolicy.KEEP_LAST)
        self._subs = [node.create_subscription(PointCloud2, '~/enroll_cloud',
                                               self._on_cloud, qos)]
        if Detection3DArray is not None:
            self._pairing = StampPairing(PAIR_TIMEOUT_S, PAIR_MAX_WAITING)
            self._subs += [
                node.create_subscription(Detection3DArray, '~/enroll', self._on_detections, qos),
                node.create_subscription(PointCloud2, '~/enroll_scene', self._on_scene, qos)]
        # Services that wait for a save or a refit are coroutines (see _finished): they never
        # hold up the input callbacks of the node's single-threaded executor, nor (reentrant
        # group) the next request: each is taken at once, and answered done or "busy".
        group = ReentrantCallbackGroup()
        srv_qos = QoSProfile(depth=SERVICE_QUEUE_DEPTH, reliability=ReliabilityPolicy.RELIABLE,
                             history=HistoryPolicy.KEEP_LAST)
        self._services = [
            node.create_service(Trigger, f'~/{name}', handler, qos_profile=srv_qos,
                                callback_group=group)
            for name, handler in (('start_capture', self._start_capture),
                                  ('stop_capture', self._stop_capture),
                                  ('forget', self._forget), ('save_bank', self._save_bank))]
        snap = self.live.current()
        route = ('~/enroll (Detection3DArray) + ~/enroll_scene (PointCloud2), '
                 if Detection3DArray is not None else '')
        node.get_logger().info(
            f'enrollment: {route}~/enroll_cloud (PointCloud2 + enroll_class), services '
            f'start_capture, stop_capture, forget, save_bank; bank v{snap.version}, '
            f'{len(predictable(snap.bank, self.live.policy.min_examples))} of '
            f'{len(snap.class_names)} classes predicted')
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: Any) -> TransitionCallbackReturn:
        self._destroy_interfaces()
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: Any) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: Any) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: Any) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def _destroy_interfaces(self) -> None:
        for sub in self._subs:
            self.node.destroy_subscription(sub)
        for srv in self._services:
            self.node.destroy_service(srv)
        self._subs, self._services = [], []

    def _release(self) -> None:
        self._destroy_interfaces()
        self.stop()
        self.engine = self.live = self._pipeline = None

    def stop(self) -> None:
        """Stop enrolling now (node shutdown): pending work dropped, nothing published after."""
        if self.engine is not None:
            if not self.node.context.ok():     # /rosout is gone: a console-only logger
                self.engine.set_log(rclpy.logging.get_logger(
                    f'{self.node.get_name()}.shutdown').info)
            self.engine.close()

    def _make_model(self, bank: Any, previous: Any = None) -> Any:
        """A recognizer for one bank version, sharing the node's encoder.

        previous: the recognizer of the version before (an enrollment): its search index is
        extended rather than rebuilt where that is exact (bank/index.py).
        """
        from point_gn_ros.recognizer import Recognizer
        s, enc = self.node.settings, self.node.recognizer.encoder
        return Recognizer(bank, s.device, s.resample, s.top_k, s.unknown_threshold or None,
                          encoder=enc, search=s.search, previous=previous,
                          object_test=s.object_test, metric_size=s.metric_size,
                          **rule_thresholds(s))

    # ------------------------------------------------------------------ worker hooks

    def _observe(self, jobs: list[Any]) -> None:
        if self.engine is not None and self.engine.capturing():
            for job in jobs:
                self.engine.observe(job.item.topic_index, job.model_clouds())

    def _between_batches(self) -> bool:
        """Worker: one enrollment step, unless input waits (answers first, but one a second)."""
        queue = getattr(self.node, '_queue', None)
        now = time.monotonic()
        if queue is not None and any(queue.depths()) and now - self._last_step < \
                ENROLL_STEP_MIN_S:
            return False
        self._last_step = now
        try:
            return self.engine is not None and self.engine.step(self._pipeline.recognizer)
        except Exception as exc:  # noqa: BLE001 - the worker must outlive enrollment bugs
            self.engine.report_error(f'enrollment step failed: {type(exc).__name__}: {exc}')
            return False

    def _swap(self, snap: Snapshot, result: EnrollResult) -> None:
        """Committer thread: the worker uses `snap` from its next micro-batch on."""
        self.node.replace_recognizer(snap.model)

    # ------------------------------------------------------------------ topics

    def _on_detections(self, msg: Any) -> None:
        self._paired(self._pairing.add(msg, None))

    def _on_scene(self, msg: PointCloud2) -> None:
        self._paired(self._pairing.add(None, msg))

    def _paired(self, pairs: list[tuple[Any, Any]]) -> None:
        """Each detection's box crops one example out of the scene cloud of the same stamp."""
        from point_gn_ros.pointcloud2 import decode_xyz

        if self._pairing.expired:
            n, self._pairing.expired = self._pairing.expired, 0
            self.engine.refuse(n, f'{n} detection array(s) or scene cloud(s) found no partner '
                                   f'with the same stamp within {PAIR_TIMEOUT_S:g} s',
                               'unpaired')
        for dets, scene in pairs:
            try:
                xyz = decode_xyz(scene, max_points=self._max_points(),
                                 allow_empty=True).xyz
            except DecodeError as exc:
                self.engine.refuse(len(dets.detections), f'scene cloud not decodable: {exc}',
                                   _decode_reason(exc))
                continue
            rot = self._pipeline.frame_rotation(scene.header.frame_id)
            per_class: dict[str, list] = {}
            unlabelled = 0
            for det in dets.detections:
                label = det.results[0].hypothesis.class_id.strip() if det.results else ''
                if not label:
                    unlabelled += 1
                    continue
                per_class.setdefault(label, []).append(to_z_up(crop_box(xyz, det.bbox), rot))
            if unlabelled:
                self.engine.refuse(unlabelled, 'detection without results[0].hypothesis.'
                                                'class_id', 'unlabelled')
            for label, clouds in per_class.items():
                self.engine.submit(label, clouds, '~/enroll')

    def _on_cloud(self, msg: PointCloud2) -> None:
        from point_gn_ros.pointcloud2 import decode_xyz

        name = self._param('enroll_class')
        try:
            xyz = decode_xyz(msg, max_points=self._max_points(), allow_empty=True).xyz
        except DecodeError as exc:
            self.engine.refuse(1, f'~/enroll_cloud message not decodable: {exc}',
                               _decode_reason(exc))
            return
        rot = self._pipeline.frame_rotation(msg.header.frame_id)
        self.engine.submit(name, [to_z_up(xyz, rot)], '~/enroll_cloud')

    # ------------------------------------------------------------------ services

    def _start_capture(self, request: Any, response: Any) -> Any:
        topic = self._param('capture_topic')
        topics = None
        if topic:
            names = self._pipeline.topic_names
            matches = [i for i, t in enumerate(names)
                       if t == topic or t.rsplit('/', 1)[-1] == topic.rsplit('/', 1)[-1]]
            if not matches:
                return _answer(response, False, f'capture_topic {topic!r} is not an input '
                                                f'topic ({", ".join(names)})')
            topics = frozenset(matches)
        return _answer(response, *self.engine.start_capture(self._param('enroll_class'),
                                                            topics))

    def _stop_capture(self, request: Any, response: Any) -> Any:
        return _answer(response, *self.engine.stop_capture())

    async def _forget(self, request: Any, response: Any) -> Any:
        name = self._param('enroll_class')
        if not name:
            return _answer(response, False, 'set the enroll_class parameter first')
        return _answer(response, *await self._finished(self.engine.forget_later(name,
                                                                                '~/forget')))

    async def _save_bank(self, request: Any, response: Any) -> Any:
        path, why = self.save_target()
        if path is None:
            return _answer(response, False, why)
        return _answer(response, *await self._finished(self.engine.save_later(str(path))))

    def _max_points(self) -> int:
        return int(self.node.settings.max_points_per_message)

    async def _finished(self, fut: Future) -> tuple[bool, str]:
        """The committer's (ok, message), awaited without holding the executor.

        The node spins a single-threaded executor (a multi-threaded one triples the
        latency); a service that blocked on a save would stall every input
        callback meanwhile, so it yields until the committer is done instead.
        """
        done = RclpyFuture(executor=self.node.executor)
        done.add_done_callback(lambda _: None)   # scheduled on completion: wakes the executor
        fut.add_done_callback(lambda _: done.set_result(None))
        await done
        return fut.result()

    def _param(self, name: str) -> str:
        return str(self.node.get_parameter(name).value or '').strip()

    # ------------------------------------------------------------------ diagnostics, shutdown

    def diagnostic_status(self, node_name: str) -> DiagnosticStatus:
        """`<node>: enrollment` status: bank version, class counts, enrollment counters."""
        if self.live is None:
            return DiagnosticStatus(level=DiagnosticStatus.OK, name=f'{node_name}: enrollment',
                                    message='not configured' if self.enabled else
                                    'off (enable_enrollment false)')
        values = self.diagnostic_values()
        eng = self.engine
        level, message = DiagnosticStatus.OK, f'bank v{values["bank_version"]}'
        if eng is not None and eng.last_error:
            level, message = DiagnosticStatus.WARN, eng.last_error[:200]
        st = DiagnosticStatus(level=level, name=f'{node_name}: enrollment', message=message)
        st.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        return st

    def diagnostic_values(self) -> dict[str, Any]:
        """Key -> value for the node's diagnostics: bank version, class counts, enrollment."""
        snap = self.live.current()
        counts = snap.counts()
        out: dict[str, Any] = {
            'bank_version': snap.version, 'bank_entries': len(snap.bank),
            'classes': len(counts),
            'predicted_classes': len(predictable(snap.bank, self.live.policy.min_examples)),
            'min_examples_per_class': self.live.policy.min_examples,
        }
        eng = self.engine
        if eng is not None:
            out |= {'enroll_pending': eng.pending(), 'capturing': eng.capturing() or 'no',
                    **{f'enroll_{k}': v for k, v in eng.counters.items()},
                    **{f'enroll_refused.{k}': v for k, v in sorted(eng.refused_by.items())},
                    'enroll_last_latency_s': f'{eng.last_latency_s:.3f}',
                    'last_save': (f'v{eng.last_save[1]} {eng.last_save[0]}' if eng.last_save
                                  else 'none')}
        out |= {f'count.{name}': n for name, n in counts.items()}
        return out


def _decode_reason(exc: DecodeError) -> str:
    """The refusal counter of an enrollment cloud the codec refused."""
    return 'too_many_points' if str(exc).startswith('too many points') else 'undecodable'


def save_name_problem(name: str) -> str | None:
    """Why `name` cannot be the file ~/save_bank writes in the save folder, or None.

    A plain file name: no folder part, no '..', not hidden, ending in .npz, printable.
    """
    if not name:
        return 'empty'
    if len(name) > 128:
        return 'longer than 128 characters'
    if '/' in name or '\\' in name or name in ('.', '..') or Path(name).name != name:
        return 'must be a plain file name (no folder, no "..")'
    if name.startswith('.'):
        return 'must not be hidden (start with ".")'
    if not name.isprintable():
        return 'must be printable'
    if not name.endswith('.npz') or name == '.npz':
        return 'must end with .npz'
    return None


def _answer(response: Any, ok: bool, message: str) -> Any:
    response.success, response.message = bool(ok), message
    return response
