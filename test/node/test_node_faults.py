"""Failure isolation and accounting of the node's pipeline (ROS-free, no DDS).

The real Pipeline with a real Recognizer on a small synthetic bank; faults are injected
around it (a recognizer that raises on one poisoned cloud, a publish callback that raises
for one message, a payload whose attribute access raises) to check that a failure costs
only its own message, and that `received = answered + dropped + rejected + failed +
in_flight` holds in every snapshot.
"""

from __future__ import annotations

from pathlib import Path
import threading
import time
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from point_gn_ros.clients.fuzz import node_params, synthetic_bank
from point_gn_ros.clients.fuzz_messages import (Limits, fuzz_header, generate, make_case,
                                                pack_cloud)
from point_gn_ros.node.params import PARAMETERS, settings_from_values
from point_gn_ros.node.pipeline import Answer, Pipeline
from point_gn_ros.node.stats import NodeStats
from point_gn_ros.node.work_queue import WorkQueue

LIMITS = Limits(min_points=16, max_points=6000, max_objects=8)


@pytest.fixture(scope='module')
def recognizer(tmp_path_factory: pytest.TempPathFactory) -> Any:
    from point_gn_ros.recognizer import Recognizer
    bank = synthetic_bank(tmp_path_factory.mktemp('bank') / 'shapes.npz')
    return Recognizer.from_bank(bank)


class Poisoned:
    """The real recognizer, except that any batch holding a cloud of POISON points raises."""

    POISON = 77

    def __init__(self, inner: Any) -> None:
        self.inner = inner

    def __getattr__(self, name: str) -> Any:     # bank, classifier, class_names, top_k ...
        return getattr(self.inner, name)

    def classify_clouds(self, clouds: list[np.ndarray]) -> Any:
        if any(len(c) == self.POISON for c in clouds):
            raise RuntimeError('injected classification failure')
        return self.inner.classify_clouds(clouds)

    def classify_later(self, clouds: list[np.ndarray]) -> Any:
        # the node's overlapped path: the failure comes with the answer, not the start
        later = self.inner.classify_later(clouds)
        if any(len(c) == self.POISON for c in clouds):
            def fail() -> Any:
                raise RuntimeError('injected classification failure')
            return fail
        return later


def _settings(**over: Any) -> Any:
    values = {name: default for name, (default, _, _) in PARAMETERS.items()}
    params = node_params(Path('unused'), LIMITS)
    values.update({k: v for k, v in params.items() if k in values}, **over)
    return settings_from_values(values)


class Harness:
    """A Pipeline, its stats and queue, and the answers it publishes (by message index)."""

    def __init__(self, recognizer: Any, fail_publish: set[int] = frozenset(), **over: Any):
        self.stats = NodeStats(1)
        self.queue: WorkQueue[Any] = WorkQueue(1, 10_000, on_drop=self.stats.on_dropped)
        self.stop = threading.Event()
        self.warnings: list[str] = []
        self.pipeline = Pipeline(recognizer, _settings(**over), self.stats,
                                 lambda key, text: self.warnings.append(text), self.stop)
        self.answers: dict[int, Answer] = {}
        self.fail_publish = set(fail_publish)

    def publish(self, answer: Answer) -> None:
        """Like the node's _publish: raise for chosen messages, else count as answered."""
        index = answer.job.item.payload.index
        if index in self.fail_publish:
            raise ValueError('injected publish failure')
        answer.centroids  # noqa: B018 - computed by the node's publish too
        self.answers[index] = answer
        self.stats.on_published(0, len(answer.labels), 0.0, None)

    def put(self, msg: Any) -> None:
        """What the node's subscription callback does."""
        self.stats.on_received(0)
        self.queue.put(0, msg)

    def run(self, msgs: list[Any]) -> Any:
        for m in msgs:
            self.put(m)
        self.pipeline.process(self.queue.take(len(msgs)), self.publish)
        snap = self.stats.snapshot([0])
        assert snap.unaccounted() == 0
        return snap


def _msg(index: int, n: int, rng: np.random.Generator, seg_ids: list[int] | None = None) -> Any:
    """A one-object (or segmented) message tagged with `index` (SimpleNamespace payload)."""
    xyz = rng.normal(size=(n, 3)).astype(np.float32)
    seg = np.zeros(n, np.int32) if seg_ids is None else np.asarray(seg_ids, np.uint32)
    msg = pack_cloud(fuzz_header(index), [('x', xyz[:, 0]), ('y', xyz[:, 1]),
                                          ('z', xyz[:, 2]), ('segment', seg)])
    return _Tagged(msg, index)


class _Tagged:
    """A PointCloud2 with the test's message index attached (attribute passthrough)."""

    def __init__(self, msg: Any, index: int) -> None:
        self.__dict__['_msg'] = msg
        self.__dict__['index'] = index

    def __getattr__(self, name: str) -> Any:
        return getattr(self._msg, name)

    def __setattr__(self, name: str, value: Any) -> None:
        setattr(self._msg, name, value)


def test_a_poisoned_cloud_costs_only_its_message(recognizer: Any) -> None:
    rng = np.random.default_rng(0)
    h = Harness(Poisoned(recognizer))
    msgs = [_msg(i, 100 + i, rng) for i in range(7)] + [_msg(7, Poisoned.POISON, rng)]
    snap = h.run(msgs)
    assert sorted(h.answers) == list(range(7))               # all 7 batch-mates answered
    assert snap.failed == {'classify': 1} and snap.answered == 7 and snap.in_flight == 0
    assert any('failed to classify a message' in w for w in h.warnings)


def test_bursts_of_7_valid_and_1_bad_id_lose_nothing_valid(recognizer: Any) -> None:
    """The campaign's case: UINT32 segment id >= 2**31 in every 8th message (was 30/70)."""
    rng = np.random.default_rng(1)
    h = Harness(recognizer)
    index = 0
    for _ in range(10):
        burst = [_msg(index + i, 60, rng) for i in range(7)]
        burst.append(_msg(index + 7, 60, rng, seg_ids=[2**31 + 9] * 60))
        index += 8
        snap = h.run(burst)
    assert len(h.answers) == 70 and snap.answered == 70
    assert snap.rejected == {'segment field holds an id out of range for segment_id': 10}
    assert not snap.failed


def test_decoder_escape_and_publish_failure_are_per_message(recognizer: Any) -> None:
    rng = np.random.default_rng(2)

    class Exploding:
        index = 3
        header = SimpleNamespace()

        def __getattr__(self, name: str) -> Any:
            raise RuntimeError(f'attribute {name} exploded')

    h = Harness(recognizer, fail_publish={5})
    msgs = [_msg(i, 50, rng) for i in range(3)] + [Exploding()] + [_msg(i, 50, rng)
                                                                  for i in range(4, 8)]
    empty_huge = _msg(8, 20, rng)
    empty_huge.width, empty_huge.row_step = 0, 0
    empty_huge.data, empty_huge.point_step = b'', 2**31 + 1      # was a ValueError escape
    snap = h.run([*msgs, empty_huge])
    assert sorted(h.answers) == [0, 1, 2, 4, 6, 7]
    assert snap.failed == {'decode': 1, 'publish': 1}
    assert snap.rejected == {'point_step is out of range': 1}
    assert snap.answered == 6 and snap.in_flight == 0 and snap.errors == 2


def test_limits_reject_points_and_truncate_objects(recognizer: Any) -> None:
    rng = np.random.default_rng(3)
    h = Harness(recognizer)
    too_big = make_case(0, 'too_many_points', rng, LIMITS)
    many = make_case(1, 'many_objects', rng, LIMITS)
    snap = h.run([_Tagged(too_big.msg, 0), _Tagged(many.msg, 1)])
    assert snap.rejected == {'too many points': 1}
    assert tuple(int(s) for s in h.answers[1].job.segment_ids) == many.expected_segments
    assert len(many.expected_segments) == LIMITS.max_objects
    assert snap.objects_truncated > 0 and snap.answered == 1


def test_fuzz_mix_through_the_pipeline(recognizer: Any) -> None:
    """500 generated cases: valid ones answered with the expected ids, invalid rejected."""
    h = Harness(recognizer)
    cases = list(generate(11, 500, LIMITS))
    for start in range(0, len(cases), 16):
        batch = cases[start:start + 16]
        h.run([_Tagged(c.msg, c.index) for c in batch])
    for c in cases:
        if c.valid:
            assert c.index in h.answers, (c.index, c.kind)
            assert tuple(h.answers[c.index].job.segment_ids) == c.expected_segments, c.kind
        else:
            assert c.index not in h.answers, (c.index, c.kind)
    snap = h.stats.snapshot([0])
    assert snap.answered == sum(c.valid for c in cases)
    assert sum(snap.rejected.values()) == sum(not c.valid for c in cases)
    assert not snap.failed and snap.in_flight == 0


def test_identity_holds_at_every_instant_under_concurrency(recognizer: Any) -> None:
    """Producer, worker (with drops and faults) and a reader snapshotting as fast as it can."""
    rng = np.random.default_rng(4)
    h = Harness(Poisoned(recognizer), fail_publish={9, 19})
    h.queue = WorkQueue(1, 4, on_drop=h.stats.on_dropped)   # small: the producer drops
    msgs = [_msg(i, Poisoned.POISON if i % 13 == 0 else 40, rng) for i in range(120)]
    worker = threading.Thread(target=h.pipeline.serve, args=(h.queue, h.publish))
    worker.start()
    checked, bad = 0, []
    done = threading.Event()

    def reader() -> None:
        nonlocal checked
        while not done.is_set():
            snap = h.stats.snapshot([0])
            if snap.unaccounted() != 0:
                bad.append(snap)
            checked += 1

    r = threading.Thread(target=reader)
    r.start()
    for i, m in enumerate(msgs):
        h.put(m)
        if i < 60:
            time.sleep(0.01)    # paced: the worker keeps up and meets the poisoned clouds
    # ... then the second half as one burst: the 4-deep queue must drop
    deadline = time.monotonic() + 60
    while h.stats.snapshot([0]).in_flight and time.monotonic() < deadline:
        time.sleep(0.01)
    done.set()
    h.stop.set()
    r.join()
    worker.join(5)
    snap = h.stats.snapshot([0])
    assert not bad and checked > 100
    assert sum(snap.received) == 120 and snap.in_flight == 0
    assert sum(snap.dropped) > 0 and snap.failed.get('classify', 0) > 0
    assert snap.answered + sum(snap.dropped) + sum(snap.failed.values()) == 120


def test_overlapped_batches_answer_in_order_as_one_at_a_time(recognizer: Any) -> None:
    """A backlog is served overlapped: the same answers, bit for bit, in message order.

    Each batch's encoding overlaps the answers of the one before (recognizer.
    classify_later); the reference is the same batches of 4 taken one at a time.
    """
    rng = np.random.default_rng(6)
    msgs = [_msg(i, 30 + 7 * i, rng) for i in range(24)]
    alone = Harness(recognizer)
    for i in range(0, len(msgs), 4):
        alone.run(msgs[i:i + 4])

    started = []

    class Counting(Poisoned):
        def classify_later(self, clouds: list[np.ndarray]) -> Any:
            started.append(len(clouds))
            return super().classify_later(clouds)

    h = Harness(Counting(recognizer), max_batch=4)
    order: list[int] = []
    publish = h.publish
    h.publish = lambda answer: (publish(answer), order.append(answer.job.item.payload.index))
    for m in msgs:          # all waiting before the worker starts: a backlog
        h.put(m)
    worker = threading.Thread(target=h.pipeline.serve, args=(h.queue, h.publish))
    worker.start()
    deadline = time.monotonic() + 60
    while len(h.answers) < len(msgs) and time.monotonic() < deadline:
        time.sleep(0.01)
    h.stop.set()
    worker.join(5)
    assert len(started) >= 5                  # batches were started ahead, 4 messages each
    assert order == list(range(len(msgs)))
    for i, answer in h.answers.items():
        want = alone.answers[i]
        np.testing.assert_array_equal(answer.labels, want.labels)
        np.testing.assert_array_equal(answer.scores, want.scores)
        np.testing.assert_array_equal(answer.topk_ids, want.topk_ids)
    snap = h.stats.snapshot([0])
    assert snap.answered == len(msgs) and snap.in_flight == 0 and snap.unaccounted() == 0


def test_a_failure_between_steps_settles_a_backlog_once(recognizer: Any) -> None:
    """Clouds that cannot be turned z-up fail their own messages once each, overlapped too.

    A broken frame lookup; the worker goes on answering afterwards.
    """
    rng = np.random.default_rng(7)
    h = Harness(recognizer, max_batch=4)
    broken = {'on': True}
    h.pipeline.frame_rotation = lambda frame_id: np.eye(2) if broken['on'] else None
    for i in range(12):
        h.put(_msg(i, 40, rng))
    worker = threading.Thread(target=h.pipeline.serve, args=(h.queue, h.publish))
    worker.start()
    deadline = time.monotonic() + 60
    while h.stats.snapshot([0]).in_flight and time.monotonic() < deadline:
        time.sleep(0.01)
    broken['on'] = False
    for i in range(12, 16):
        h.put(_msg(i, 40, rng))
    while len(h.answers) < 4 and time.monotonic() < deadline:
        time.sleep(0.01)
    h.stop.set()
    worker.join(5)
    snap = h.stats.snapshot([0])
    assert sorted(h.answers) == [12, 13, 14, 15]
    assert snap.failed == {'classify': 12} and snap.answered == 4
    assert snap.in_flight == 0 and snap.unaccounted() == 0
