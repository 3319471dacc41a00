"""WorkQueue: bounded per-topic FIFOs, drop-oldest, fair micro-batches, clean close."""

from __future__ import annotations

import threading
import time

import pytest

from point_gn_ros.node.work_queue import WorkQueue


def test_drop_oldest_keeps_the_freshest() -> None:
    q: WorkQueue[int] = WorkQueue(num_topics=1, maxlen=3)
    dropped = [q.put(0, i) for i in range(10)]
    assert dropped == [False] * 3 + [True] * 7
    assert q.dropped() == [7] and q.depths() == [3]
    assert [it.payload for it in q.take(10)] == [7, 8, 9]
    assert q.depths() == [0]


def test_batches_are_fair_across_topics_and_fifo_per_topic() -> None:
    q: WorkQueue[str] = WorkQueue(num_topics=3, maxlen=10)
    for i in range(6):
        q.put(0, f'a{i}')
    q.put(1, 'b0')
    q.put(2, 'c0')
    q.put(2, 'c1')
    batch = q.take(4)
    assert {it.payload for it in batch} >= {'a0', 'b0', 'c0'}   # every topic gets a turn
    assert len(batch) == 4
    rest = [it.payload for it in q.take(100)]
    taken = [it.payload for it in batch] + rest
    assert [p for p in taken if p.startswith('a')] == [f'a{i}' for i in range(6)]
    assert sorted(taken) == sorted([f'a{i}' for i in range(6)] + ['b0', 'c0', 'c1'])


def test_items_carry_topic_and_receipt_time() -> None:
    q: WorkQueue[str] = WorkQueue(num_topics=2, maxlen=2)
    t0, w0 = time.monotonic(), time.time_ns()
    q.put(1, 'x')
    (item,) = q.take(1)
    assert item.topic_index == 1 and item.payload == 'x'
    assert t0 <= item.receipt_time <= time.monotonic()
    assert w0 <= item.receipt_wall_ns <= time.time_ns()


def test_take_blocks_until_put_or_timeout_or_close() -> None:
    q: WorkQueue[int] = WorkQueue(num_topics=1, maxlen=2)
    t0 = time.monotonic()
    assert q.take(1, timeout=0.05) == []
    assert time.monotonic() - t0 >= 0.04

    got: list = []
    worker = threading.Thread(target=lambda: got.append(q.take(5, timeout=5)))
    worker.start()
    time.sleep(0.05)
    q.put(0, 42)
    worker.join(2)
    assert [it.payload for it in got[0]] == [42]

    worker = threading.Thread(target=lambda: got.append(q.take(5)))
    worker.start()
    time.sleep(0.05)
    q.close()
    worker.join(2)
    assert not worker.is_alive() and got[-1] == [] and q.closed
    q.put(0, 1)
    assert q.take(1, timeout=0) == []


def test_concurrent_producers_lose_nothing_but_overflow() -> None:
    q: WorkQueue[int] = WorkQueue(num_topics=4, maxlen=1000)
    threads = [threading.Thread(target=lambda t=t: [q.put(t, i) for i in range(500)])
               for t in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert q.depths() == [500] * 4 and q.dropped() == [0] * 4
    assert len(q.take(5000)) == 2000


def test_invalid_arguments() -> None:
    with pytest.raises(ValueError):
        WorkQueue(num_topics=0, maxlen=1)
    with pytest.raises(ValueError):
        WorkQueue(num_topics=1, maxlen=0)
    with pytest.raises(ValueError):
        WorkQueue(num_topics=1, maxlen=1).take(0)
