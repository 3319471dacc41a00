"""Silent input topics: no publisher, or no message, for too long (ROS-free).

A misspelt topic name otherwise shows only as `input_rate_hz=0` with status OK. The node
feeds the publisher counts and message arrivals; the diagnostics report what this returns.
"""

from __future__ import annotations

from collections.abc import Sequence
import threading
import time


class InputWatchdog:
    """Per input topic: when it last had a publisher and last delivered a message."""

    def __init__(self, num_topics: int, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        self._lock = threading.Lock()
        self._last_msg = [now] * num_topics
        self._last_publisher = [now] * num_topics

    def on_message(self, topic_index: int, now: float | None = None) -> None:
        """A message arrived on the topic (subscription callback)."""
        with self._lock:
            self._last_msg[topic_index] = time.monotonic() if now is None else now

    def problems(self, topic_names: Sequence[str], publisher_counts: Sequence[int],
                 timeout_s: float, now: float | None = None) -> list[str]:
        """Per topic '' or why it is suspicious; timeout_s <= 0 turns the check off."""
        now = time.monotonic() if now is None else now
        out = []
        with self._lock:
            for i, (name, publishers) in enumerate(zip(topic_names, publisher_counts,
                                                        strict=True)):
                if publishers > 0:
                    self._last_publisher[i] = now
                no_pub, no_msg = now - self._last_publisher[i], now - self._last_msg[i]
                if timeout_s <= 0:
                    out.append('')
                elif no_pub > timeout_s:
                    out.append(f'no publisher on {name} for {no_pub:.0f} s')
                elif no_msg > timeout_s:
                    out.append(f'no message on {name} for {no_msg:.0f} s')
                else:
                    out.append('')
        return out
