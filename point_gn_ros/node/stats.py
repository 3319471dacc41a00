"""Counters, rates and latency percentiles for the classifier node (ROS-free, thread-safe).

The worker thread and the subscription callbacks record events; the diagnostics
timer reads a consistent snapshot once a second.

Every received message is settled exactly once, as answered, dropped (queue full),
rejected (by reason) or failed (by stage); until then it is in flight. All of these change
under one lock, so every snapshot satisfies the accounting identity exactly::

    received = answered + dropped + rejected + failed + in_flight
"""

from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field
import threading
import time
from collections.abc import Callable

import numpy as np


class RateMeter:
    """Events per second over a sliding window (not thread-safe; guard externally)."""

    def __init__(self, window_s: float = 5.0, clock: Callable[[], float] = time.monotonic) -> None:
        self._window = window_s
        self._clock = clock
        self._events: deque[tuple[float, int]] = deque()
        self._start = clock()

    def add(self, count: int = 1) -> None:
        now = self._clock()
        self._events.append((now, count))
        self._trim(now)

    def _trim(self, now: float) -> None:
        while self._events and self._events[0][0] < now - self._window:
            self._events.popleft()

    def rate(self) -> float:
        now = self._clock()
        self._trim(now)
        # Before a full window has passed, divide by the time actually observed.
        span = min(self._window, max(now - self._start, 1e-3))
        return sum(c for _, c in self._events) / span


class LatencyWindow:
    """The latest `maxlen` latency samples (seconds) and their percentiles."""

    def __init__(self, maxlen: int = 1000) -> None:
        self._samples: deque[float] = deque(maxlen=maxlen)

    def add(self, seconds: float) -> None:
        self._samples.append(seconds)

    def __len__(self) -> int:
        return len(self._samples)

    def percentiles_ms(self, qs: tuple[float, ...] = (50.0, 99.0)) -> tuple[float, ...]:
        """Percentiles in milliseconds; NaN for each when there are no samples yet."""
        if not self._samples:
            return tuple(float('nan') for _ in qs)
        arr = np.fromiter(self._samples, dtype=np.float64, count=len(self._samples))
        return tuple(float(v) * 1e3 for v in np.percentile(arr, qs))


@dataclass
class StatsSnapshot:
    """A consistent copy of every figure the diagnostics report."""

    input_rate_hz: float
    processed_rate_hz: float
    objects_rate_hz: float
    received: list[int]
    processed: list[int]                         # answered, per topic
    objects: int
    dropped: list[int]
    queue_depths: list[int]
    rejected: dict[str, int]
    skipped_segments: int
    latency_receipt_ms: tuple[float, float]      # p50, p99: receipt -> publish
    latency_stamp_ms: tuple[float, float]        # p50, p99: header stamp -> publish
    latency_samples: int
    batch_size_mean: float
    errors: int = 0
    last_error: str = ''
    per_topic_input_hz: list[float] = field(default_factory=list)
    failed: dict[str, int] = field(default_factory=dict)    # stage -> messages
    in_flight: int = 0                                      # received, not yet settled
    objects_truncated: int = 0
    numeric_warnings: int = 0                               # numpy FP errors (garbage input)

    @property
    def answered(self) -> int:
        return sum(self.processed)

    def unaccounted(self) -> int:
        """Received minus (answered + dropped + rejected + failed + in_flight): always 0."""
        return (sum(self.received) - self.answered - sum(self.dropped)
                - sum(self.rejected.values()) - sum(self.failed.values()) - self.in_flight)


class NodeStats:
    """Everything the node counts, behind one lock."""

    def __init__(self, num_topics: int, window_s: float = 5.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._lock = threading.Lock()
        self._in_rate = RateMeter(window_s, clock)
        self._topic_rates = [RateMeter(window_s, clock) for _ in range(num_topics)]
        self._out_rate = RateMeter(window_s, clock)
        self._obj_rate = RateMeter(window_s, clock)
        self._received = [0] * num_topics
        self._processed = [0] * num_topics
        self._objects = 0
        self._rejected: Counter[str] = Counter()
        self._skipped_segments = 0
        self._lat_receipt = LatencyWindow()
        self._lat_stamp = LatencyWindow()
        self._batches: deque[int] = deque(maxlen=100)
        self._errors = 0
        self._last_error = ''
        self._dropped = [0] * num_topics
        self._failed: Counter[str] = Counter()
        self._in_flight = 0
        self._objects_truncated = 0
        self._numeric_warnings = 0

    def on_numeric_warning(self, kind: str = '', flag: int = 0) -> None:
        """A numpy floating-point error (overflow, invalid, divide) in the worker: counted.

        The signature is numpy's error callback (np.errstate(call=...)).
        """
        with self._lock:
            self._numeric_warnings += 1

    def on_received(self, topic_index: int) -> None:
        """A message arrived (subscription callback); it is in flight until settled."""
        with self._lock:
            self._received[topic_index] += 1
            self._in_flight += 1
            self._in_rate.add()
            self._topic_rates[topic_index].add()

    def on_dropped(self, topic_index: int) -> None:
        """Settled: a queued message was pushed out by a newer one (queue full)."""
        with self._lock:
            self._dropped[topic_index] += 1
            self._in_flight -= 1

    def on_rejected(self, reason: str) -> None:
        """Settled: the message was malformed or over a limit (counted by reason)."""
        with self._lock:
            self._rejected[reason] += 1
            self._in_flight -= 1

    def on_failed(self, stage: str, description: str) -> None:
        """Settled: an unexpected exception at `stage` (decode, classify, publish) lost it."""
        with self._lock:
            self._failed[stage] += 1
            self._in_flight -= 1
            self._errors += 1
            self._last_error = f'{stage}: {description}'

    def on_truncated_objects(self, count: int) -> None:
        """Objects left out of a message over max_objects_per_message (message answered)."""
        with self._lock:
            self._objects_truncated += count

    def on_skipped_segments(self, count: int) -> None:
        with self._lock:
            self._skipped_segments += count

    def on_batch(self, num_objects: int) -> None:
        with self._lock:
            self._batches.append(num_objects)

    def on_published(self, topic_index: int, num_objects: int, receipt_latency_s: float,
                     stamp_latency_s: float | None) -> None:
        """Settled: a message was answered; stamp latency is None when the stamp is unset."""
        with self._lock:
            self._processed[topic_index] += 1
            self._in_flight -= 1
            self._objects += num_objects
            self._out_rate.add()
            if num_objects:
                self._obj_rate.add(num_objects)
            self._lat_receipt.add(receipt_latency_s)
            if stamp_latency_s is not None:
                self._lat_stamp.add(stamp_latency_s)

    def snapshot(self, queue_depths: list[int]) -> StatsSnapshot:
        """Every counter, read under the lock (the identity holds); depths from the queue."""
        with self._lock:
            r50, r99 = self._lat_receipt.percentiles_ms()
            s50, s99 = self._lat_stamp.percentiles_ms()
            return StatsSnapshot(
                input_rate_hz=self._in_rate.rate(),
                processed_rate_hz=self._out_rate.rate(),
                objects_rate_hz=self._obj_rate.rate(),
                received=list(self._received),
                processed=list(self._processed),
                objects=self._objects,
                dropped=list(self._dropped),
                queue_depths=list(queue_depths),
                rejected=dict(self._rejected),
                skipped_segments=self._skipped_segments,
                latency_receipt_ms=(r50, r99),
                latency_stamp_ms=(s50, s99),
                latency_samples=len(self._lat_receipt),
                batch_size_mean=float(np.mean(self._batches)) if self._batches else 0.0,
                errors=self._errors,
                last_error=self._last_error,
                per_topic_input_hz=[m.rate() for m in self._topic_rates],
                failed=dict(self._failed),
                in_flight=self._in_flight,
                objects_truncated=self._objects_truncated,
                numeric_warnings=self._numeric_warnings,
            )
