"""Bounded per-topic work queues with drop-oldest overflow and fair micro-batching.

ROS-free so that it can be unit tested without a middleware. Subscription
callbacks `put()` messages (never block, never do work); one worker thread
`take()`s micro-batches. When a topic produces faster than the worker consumes,
its oldest waiting message is dropped: a classifier of live sensor data should
answer the freshest view of the world, not a backlog.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
import threading
import time
from typing import Generic, TypeVar

T = TypeVar('T')


@dataclass(frozen=True)
class QueueItem(Generic[T]):
    """One queued message with where and when it arrived."""

    topic_index: int
    payload: T
    receipt_time: float          # time.monotonic() at enqueue
    receipt_wall_ns: int         # time.time_ns() at enqueue, comparable with header stamps


class WorkQueue(Generic[T]):
    """One bounded FIFO per input topic; thread-safe.

    put() is O(1) and never blocks; take() blocks until something is queued, the
    timeout expires, or close() is called.
    """

    def __init__(self, num_topics: int, maxlen: int) -> None:
        if num_topics < 1:
            raise ValueError(f'num_topics must be >= 1, got {num_topics}')
        if maxlen < 1:
            raise ValueError(f'maxlen must be >= 1, got {maxlen}')
        self._queues: list[deque[QueueItem[T]]] = [deque() for _ in range(num_topics)]
        self._maxlen = maxlen
        self._dropped = [0] * num_topics
        self._cond = threading.Condition()
        self._closed = False
        self._next_topic = 0      # round-robin start, so no topic starves the others

    @property
    def num_topics(self) -> int:
        return len(self._queues)

    @property
    def maxlen(self) -> int:
        return self._maxlen

    def put(self, topic_index: int, payload: T) -> bool:
        """Enqueue a message; returns True when an older message had to be dropped."""
        item = QueueItem(topic_index, payload, time.monotonic(), time.time_ns())
        with self._cond:
            q = self._queues[topic_index]
            dropped = len(q) >= self._maxlen
            if dropped:
                q.popleft()
                self._dropped[topic_index] += 1
            q.append(item)
            self._cond.notify()
        return dropped

    def resize(self, maxlen: int) -> None:
        """New per-topic bound; the change itself drops nothing.

        A longer queue shrinks to the bound as the worker takes from it (each put still
        pushes out one oldest message), so every drop is still counted by put().
        """
        if maxlen < 1:
            raise ValueError(f'maxlen must be >= 1, got {maxlen}')
        with self._cond:
            self._maxlen = maxlen

    def take(self, max_items: int, timeout: float | None = None) -> list[QueueItem[T]]:
        """Up to max_items messages, taken round-robin across topics, oldest first per topic.

        Blocks until at least one is available; returns [] on timeout or once closed.
        """
        if max_items < 1:
            raise ValueError(f'max_items must be >= 1, got {max_items}')
        with self._cond:
            if not self._cond.wait_for(lambda: self._closed or self._size() > 0, timeout):
                return []
            if self._closed:
                return []
            out: list[QueueItem[T]] = []
            n = len(self._queues)
            while len(out) < max_items and self._size() > 0:
                for k in range(n):
                    q = self._queues[(self._next_topic + k) % n]
                    if q and len(out) < max_items:
                        out.append(q.popleft())
                self._next_topic = (self._next_topic + 1) % n
            return out

    def _size(self) -> int:
        return sum(len(q) for q in self._queues)

    def depths(self) -> list[int]:
        """Messages waiting, per topic."""
        with self._cond:
            return [len(q) for q in self._queues]

    def dropped(self) -> list[int]:
        """Messages dropped on overflow since start, per topic."""
        with self._cond:
            return list(self._dropped)

    def close(self) -> None:
        """Wake the worker and make every later take() return []; queued items are discarded."""
        with self._cond:
            self._closed = True
            for q in self._queues:
                q.clear()
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed
