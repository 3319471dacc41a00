"""Rate-limited warnings: at most one per key per period, with a count of the suppressed ones.

A misconfigured publisher can send hundreds of bad messages a second; one line per
topic every few seconds says the same thing without drowning the log.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Hashable


class RateLimiter:
    """Decides whether a message for `key` may be logged now (thread-safe)."""

    def __init__(self, period_s: float = 5.0, clock: Callable[[], float] = time.monotonic) -> None:
        self._period = period_s
        self._clock = clock
        self._last: dict[Hashable, float] = {}
        self._suppressed: dict[Hashable, int] = {}
        self._lock = threading.Lock()

    def check(self, key: Hashable) -> tuple[bool, int]:
        """(may_log, suppressed since the last logged one); suppressed resets when logging."""
        now = self._clock()
        with self._lock:
            last = self._last.get(key)
            if last is not None and now - last < self._period:
                self._suppressed[key] = self._suppressed.get(key, 0) + 1
                return False, 0
            self._last[key] = now
            return True, self._suppressed.pop(key, 0)


class RateLimitedLogger:
    """Wraps a `log(text)` callable (e.g. an rclpy logger's `warning`)."""

    def __init__(self, log: Callable[[str], object], period_s: float = 5.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._log = log
        self._limiter = RateLimiter(period_s, clock)
        self.period_s = period_s

    def __call__(self, key: Hashable, text: str) -> bool:
        """Log `text` unless `key` was logged within the period; returns whether it logged."""
        ok, suppressed = self._limiter.check(key)
        if ok:
            if suppressed:
                text += f' ({suppressed} similar message(s) suppressed since the last report)'
            self._log(text)
        return ok
