"""The classifier node's work, without ROS: decode, split, classify, answer.

One worker thread takes micro-batches of queued messages, decodes and splits each into
object clouds (`prepare`), classifies all objects of the batch together in chunks of
`max_batch` (`classify`) and hands each message's slice of the results to a `publish`
callback (`Answer`). A batch that fails is retried message by message, and every step
catches per message, so that one bad message costs only itself: each message is settled
exactly once in NodeStats (answered, rejected{reason} or failed{stage}). The node
(classifier_node.py) owns the ROS side: subscriptions enqueue, `publish` turns an Answer
into messages.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass, field
import re
import threading
from typing import Any

import numpy as np

from point_gn_ros.core.threads import name_os_thread
from point_gn_ros.errors import DecodeError
from point_gn_ros.node.frames import to_z_up
from point_gn_ros.node.params import Settings
from point_gn_ros.node.stats import NodeStats
from point_gn_ros.node.work_queue import QueueItem, WorkQueue

REJECT_TOO_FEW = 'too few points'


@dataclass
class Job:
    """One dequeued message on its way through the pipeline.

    clouds: list of (N_i, 3) float32 finite object clouds; segment_ids: one per cloud
    (-1 = the whole message is one object).
    """

    item: QueueItem[Any]
    segment_ids: list[int]
    clouds: list[np.ndarray]
    # (3, 3) rotation of the input frame into z-up (node/frames.py); None = already z-up.
    rotation: np.ndarray | None = None

    def model_clouds(self) -> list[np.ndarray]:
        """The clouds as the classifier sees them: turned z-up (outputs keep the input frame)."""
        return [to_z_up(c, self.rotation) for c in self.clouds]


@dataclass
class Answer:
    """One message's results: labels (M,), scores (M,), topk_ids / topk_scores (M, k)."""

    job: Job
    labels: np.ndarray
    scores: np.ndarray
    topk_ids: np.ndarray
    topk_scores: np.ndarray

    @property
    def centroids(self) -> np.ndarray:
        """(M, 3) float32 object centroids (computed in float64), input frame."""
        return np.array([c.mean(axis=0, dtype=np.float64) for c in self.job.clouds],
                        dtype=np.float32).reshape(-1, 3)


Results = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


@dataclass
class Batch:
    """One micro-batch of messages between `Pipeline.start` and `Pipeline.finish`."""

    items: Sequence[QueueItem[Any]]
    jobs: list[Job] = field(default_factory=list)
    size: int = 0                                    # objects to classify
    # each max_batch chunk's started classification (recognizer.classify_later)
    later: list[Callable[[], Any]] | None = None
    error: Exception | None = None                   # starting it failed: per message
    overlapped: bool = False                         # encoding on the encoder's threads


def _now(classify: Callable[[Any], Any]) -> Callable[[Any], Callable[[], Any]]:
    """classify(clouds) done at once, in classify_later's form."""
    def start(clouds: Any) -> Callable[[], Any]:
        result = classify(clouds)
        return lambda: result
    return start


class Pipeline:
    """Turns queued PointCloud2 messages into Answers (thread: the worker).

    recognizer: a `point_gn_ros.recognizer.Recognizer`; warn(key, text): a rate-limited
    logger; topic_names: display name per topic index (the node sets the resolved names);
    frame_rotation(frame_id): rotation into z-up or None (node/frames.py UpConvention, or
    later a tf2 lookup). `update()` swaps settings and/or the recognizer between batches.
    """

    def __init__(self, recognizer: Any, settings: Settings, stats: NodeStats,
                 warn: Callable[[Hashable, str], object], stop: threading.Event) -> None:
        self.recognizer = recognizer
        self.settings = settings
        self.topic_names: list[str] = list(settings.input_topics)
        self.frame_rotation: Callable[[str], np.ndarray | None] = lambda frame_id: None
        # topic index -> its own convention (topics.<key>.up_axis); others: frame_rotation
        self.topic_rotations: dict[int, Callable[[str], np.ndarray | None]] = {}
        self._stats = stats
        self._warn = warn
        self._stop = stop
        self._unsettled: set[int] = set()   # ids of started messages not yet settled
        self._pending: tuple[Settings, Any] | None = None
        self._pending_lock = threading.Lock()
        # Optional worker hooks (node/enrollment.py): observe(jobs) sees each prepared
        # micro-batch; between_batches() runs after each (and when idle), returns "more to do".
        self.observe: Callable[[Sequence[Job]], None] | None = None
        self.between_batches: Callable[[], bool] | None = None
        self.update(settings, recognizer)
        self._apply_pending()

    def update(self, settings: Settings | None = None, recognizer: Any = None) -> None:
        """Use new settings and/or another recognizer from the next batch on (any thread).

        The swap happens between batches, so a batch is never classified half with the old
        and half with the new. The caller has validated both (params.resolve_unknown_threshold).
        """
        with self._pending_lock:
            old_s, old_r = self._pending or (self.settings, self.recognizer)
            self._pending = (settings or old_s, recognizer or old_r)

    def _apply_pending(self) -> None:
        with self._pending_lock:
            pending, self._pending = self._pending, None
        if pending is None:
            return
        settings, recognizer = pending
        recognizer.top_k = settings.top_k
        recognizer.set_unknown_threshold(settings.unknown_threshold)
        self.settings, self.recognizer = settings, recognizer

    @property
    def class_names(self) -> list[str]:
        return list(self.recognizer.class_names)

    # ------------------------------------------------------------------ worker loop

    def serve(self, queue: WorkQueue[Any], publish: Callable[[Answer], None],
              alive: Callable[[], bool] = lambda: True) -> None:
        """Worker thread body: take micro-batches until stopped; never dies on one bad batch.

        While messages keep coming, a batch is started (prepared, its encoding begun on the
        encoder's threads) before the one ahead of it is answered (classified, published),
        so that the encoder's threads and this one work at the same time; a batch alone is
        answered at once. Answers keep the order of the batches. alive(): False once the
        middleware is shut down (a failure then ends the loop quietly instead of being
        reported).
        """
        name_os_thread()
        # Floating-point errors on garbage input (overflow, invalid) are counted in the
        # diagnostics (numeric_warnings), not written to the log as RuntimeWarnings.
        with np.errstate(over='call', invalid='call', divide='call', under='ignore',
                         call=self._stats.on_numeric_warning):
            self._serve(queue, publish, alive)

    def _serve(self, queue: WorkQueue[Any], publish: Callable[[Answer], None],
               alive: Callable[[], bool]) -> None:
        busy = False
        ahead: Batch | None = None       # started, answered after the next one is started
        while not self._stop.is_set():
            items = queue.take(self.settings.max_batch,
                               timeout=0.0 if busy or ahead is not None else 0.5)
            batch = None
            if items:
                if ahead is not None and self._update_waiting():
                    # a new bank or settings: the batch ahead is answered with its own first
                    if not self._answer(ahead, publish, alive):
                        return
                    ahead = None
                batch = Batch(items)
                # a backlog (more than one message came while the last batch ran)
                overlap = ahead is not None or len(items) > 1 or any(queue.depths())
                if not self._guarded(batch, lambda b=batch, o=overlap: self.start(b, o), alive):
                    return
            if ahead is not None:
                if not self._answer(ahead, publish, alive):
                    return
                ahead = None
            if batch is not None:
                if batch.overlapped:
                    ahead = batch
                elif not self._answer(batch, publish, alive):
                    return
            busy = self.between_batches is not None and self.between_batches()

    def _answer(self, batch: Batch, publish: Callable[[Answer], None],
                alive: Callable[[], bool]) -> bool:
        """finish(batch) guarded; the batch is done with either way. False: stop."""
        try:
            return self._guarded(batch, lambda: self.finish(batch, publish), alive)
        finally:
            self._forget(batch)

    def _guarded(self, batch: Batch, step: Callable[[], None], alive: Callable[[], bool]
                 ) -> bool:
        """step(); an exception fails what of the batch is still unsettled. False: stop."""
        try:
            step()
        except Exception as exc:  # noqa: BLE001 - the node must outlive any one batch
            if self._stop.is_set() or not alive():
                return False
            # A bug outside the per-message guards: what is still unsettled fails here.
            for item in batch.items:
                if id(item) in self._unsettled:
                    self.fail(item, 'internal', exc)
            self._forget(batch)
            batch.jobs = []              # settled: nothing of it is answered any more
        return True

    def _forget(self, batch: Batch) -> None:
        for item in batch.items:
            self._unsettled.discard(id(item))

    def _update_waiting(self) -> bool:
        with self._pending_lock:
            return self._pending is not None

    def process(self, items: Sequence[QueueItem[Any]], publish: Callable[[Answer], None]
                ) -> None:
        """Prepare, classify and publish one micro-batch of messages, now.

        Each message is settled exactly once (answered, rejected or failed at a stage) unless
        the node stops first; a failure costs only the message it belongs to.
        """
        batch = Batch(items)
        try:
            self.start(batch, overlap=False)
            self.finish(batch, publish)
        finally:
            self._forget(batch)

    def start(self, batch: Batch, overlap: bool) -> None:
        """Decode and split the batch's messages and start classifying their objects.

        overlap: the encoding runs on the encoder's threads after this returns (`finish`
        waits for it); else it is done here.
        """
        items = batch.items
        self._unsettled.update(id(item) for item in items)   # first: a failure settles them
        self._apply_pending()
        jobs = []
        for item in items:
            try:
                job = self.prepare(item)
            except Exception as exc:  # noqa: BLE001 - a decoder bug costs one message
                self.fail(item, 'decode', exc)
                continue
            if job is not None:
                jobs.append(job)
        if self.observe is not None:
            try:
                self.observe(jobs)
            except Exception as exc:  # noqa: BLE001 - capture must not cost answers
                self._warn(('observe',), f'enrollment capture failed: {exc!r}')
        batch.jobs = jobs
        if not jobs:
            return
        try:
            clouds = [c for job in jobs for c in job.model_clouds()]
            batch.size = len(clouds)
            batch.later = self._classify_later(clouds, overlap)
        except Exception as exc:  # noqa: BLE001 - retried message by message in finish
            batch.error = exc
        batch.overlapped = overlap and batch.later is not None

    def finish(self, batch: Batch, publish: Callable[[Answer], None]) -> None:
        """Classify the started batch (waiting for its encoding) and publish its answers."""
        jobs = batch.jobs
        if not jobs:
            return
        results = None
        if batch.error is None:
            try:
                results = self._collect(batch)
            except Exception as exc:  # noqa: BLE001 - retried message by message below
                batch.error = exc
        if batch.error is not None:
            if self._stop.is_set():
                return
            if len(jobs) == 1:
                self.fail(jobs[0].item, 'classify', batch.error)
                return
            # One message broke the batch: classify message by message, so only that
            # message is lost and its batch-mates are still answered.
            for job in jobs:
                try:
                    one = self.classify(job.model_clouds())
                except Exception as exc_one:  # noqa: BLE001 - counted against this message
                    if self._stop.is_set():
                        return
                    self.fail(job.item, 'classify', exc_one)
                    continue
                for answer in self.answers([job], one):
                    self.publish_one(answer, publish)
            return
        for answer in self.answers(jobs, results):
            self.publish_one(answer, publish)

    # ------------------------------------------------------------------ steps

    def reject(self, item: QueueItem[Any], reason: str, detail: str) -> None:
        """Count a rejected message and warn (rate-limited, per topic)."""
        self._unsettled.discard(id(item))
        self._stats.on_rejected(reason)
        self._warn((item.topic_index,),
                   f'dropped a message on {self.topic_names[item.topic_index]}: {detail}')

    def fail(self, item: QueueItem[Any], stage: str, exc: Exception) -> None:
        """Count one message lost to an unexpected exception at `stage`, and warn."""
        what = f'{type(exc).__name__}: {exc}'
        self._unsettled.discard(id(item))
        self._stats.on_failed(stage, what)
        self._warn(('failed', stage), f'failed to {stage} a message on '
                                      f'{self.topic_names[item.topic_index]}: {what}')

    def publish_one(self, answer: Answer, publish: Callable[[Answer], None]) -> None:
        """publish(answer) (which counts it answered); an exception fails this message only."""
        try:
            publish(answer)
        except Exception as exc:  # noqa: BLE001 - counted against this message
            if not self._stop.is_set():
                self.fail(answer.job.item, 'publish', exc)
        else:
            self._unsettled.discard(id(answer.job.item))

    def prepare(self, item: QueueItem[Any]) -> Job | None:
        """Decode and split one message into object clouds; None if it is rejected.

        Messages over max_points_per_message are rejected before anything is copied; beyond
        max_objects_per_message only the largest segments are kept (counted as truncated).
        """
        from point_gn_ros.pointcloud2 import decode_xyz, split_segments
        s = self.settings
        seg_field = s.topic(item.topic_index).segment_field
        try:
            # allow_empty: an empty or all-NaN cloud counts as 'too few points', not malformed.
            decoded = decode_xyz(item.payload, (seg_field,) if seg_field else (),
                                 max_points=s.max_points_per_message, allow_empty=True)
            if not seg_field:
                if len(decoded) < s.min_points:
                    self.reject(item, REJECT_TOO_FEW, f'{len(decoded)} finite point(s), '
                                                      f'min_points is {s.min_points}')
                    return None
                return Job(item, [-1], [decoded.xyz], self._rotation(item))
            unsegmented = s.unsegmented
            kept = split_segments(decoded, seg_field, skip_ids=unsegmented.ids,
                                  skip_negative=unsegmented.negative,
                                  skip_type_max=unsegmented.type_max)
        except DecodeError as exc:
            self.reject(item, reason_key(str(exc)), str(exc))
            return None
        big = [(seg_id, xyz) for seg_id, xyz in kept if len(xyz) >= s.min_points]
        if len(kept) > len(big):
            self._stats.on_skipped_segments(len(kept) - len(big))
        if len(big) > s.max_objects_per_message:
            # Keep the largest segments (ties: lower id), answered in id order as usual.
            order = sorted(range(len(big)), key=lambda i: (-len(big[i][1]), big[i][0]))
            chosen = sorted(order[:s.max_objects_per_message])
            self._stats.on_truncated_objects(len(big) - len(chosen))
            self._warn((item.topic_index, 'truncated'),
                       f'a message on {self.topic_names[item.topic_index]} has {len(big)} '
                       f'objects: classified the largest {s.max_objects_per_message} '
                       '(max_objects_per_message)')
            big = [big[i] for i in chosen]
        return Job(item, [seg_id for seg_id, _ in big], [xyz for _, xyz in big],
                   self._rotation(item))

    def _rotation(self, item: QueueItem[Any]) -> np.ndarray | None:
        rotation = self.topic_rotations.get(item.topic_index, self.frame_rotation)
        return rotation(item.payload.header.frame_id)

    def classify(self, clouds: list[np.ndarray]) -> Results | None:
        """Labels, scores, top-k ids and scores of clouds, in chunks of max_batch.

        None when the node is stopping.
        """
        batch = Batch([])
        batch.size = len(clouds)
        batch.later = self._classify_later(clouds, overlap=False)
        return self._collect(batch)

    def _classify_later(self, clouds: list[np.ndarray], overlap: bool
                        ) -> list[Callable[[], Any]]:
        """Each max_batch chunk of clouds started (recognizer.classify_later), in order."""
        s = self.settings
        recognizer = self.recognizer
        step = recognizer.classify_later if overlap else _now(recognizer.classify_clouds)
        return [step(clouds[start:start + s.max_batch])
                for start in range(0, len(clouds), s.max_batch)]

    def _collect(self, batch: Batch) -> Results | None:
        """The started chunks' results, concatenated; None when the node is stopping."""
        k = min(self.settings.top_k, len(self.recognizer.class_names))
        parts = [(np.zeros(0, np.int64), np.zeros(0, np.float32), np.zeros((0, k), np.int64),
                  np.zeros((0, k), np.float32))]
        for later in batch.later or []:
            if self._stop.is_set():
                return None
            res = later()
            parts.append((res.labels, res.scores, res.topk_ids, res.topk_scores))
        self._stats.on_batch(batch.size)
        return tuple(np.concatenate(column) for column in zip(*parts, strict=True))

    @staticmethod
    def answers(jobs: Sequence[Job], results: Results | None) -> list[Answer]:
        """Each job's slice of the batch results (zero objects allowed); [] when stopping."""
        if results is None:
            return []
        out, pos = [], 0
        for job in jobs:
            sl = slice(pos, pos + len(job.clouds))
            pos = sl.stop
            out.append(Answer(job, *(column[sl] for column in results)))
        return out


def reason_key(text: str) -> str:
    """A short reason to count by: the decode error's text without names, numbers, details.

    "field 'x' (offset 8, 4 bytes) does not fit in point_step 8" -> "field does not fit in
    point_step", so the number of distinct counters stays small.
    """
    text = re.sub(r'\([^)]*\)', '', text)
    text = re.sub(r"'[^']*'|\"[^\"]*\"", '', text)
    text = re.sub(r'[-+]?\d[\d,._]*', '', text)
    text = re.split(r'[:;,=]', text)[0]
    return ' '.join(text.split())[:60] or 'malformed'
