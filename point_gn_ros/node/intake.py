"""Input messages taken off DDS by a thread of their own, not by the node's executor.

rclpy's executor costs ~1.2 ms of Python per message it dispatches in this node (it rebuilds
its wait set over every service, timer and subscription each time), so a burst of 1,000
clouds/s would take more than a core before any encoding. The input subscriptions are
therefore kept out of the executor (a callback group that never lets it run them) and one
intake thread waits on them alone and takes every message as it arrives: a wait, a C
deserialisation and the node's enqueue (counted, drop oldest), ~0.1 ms. rclpy's own
`wait_for_message` takes messages the same way.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from contextlib import ExitStack
import threading
import time
from typing import Any

from rclpy.callback_groups import CallbackGroup
from rclpy.guard_condition import GuardCondition
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

from point_gn_ros.core.threads import name_os_thread

# How long one wait may block (s): bounds how late a shut-down context is noticed.
WAIT_TIMEOUT_NS = 500_000_000


class NotForExecutors(CallbackGroup):
    """A callback group whose entities no executor waits on or runs (the intake owns them)."""

    def can_execute(self, entity: Any) -> bool:
        return False

    def beginning_execution(self, entity: Any) -> bool:
        return False

    def ending_execution(self, entity: Any) -> None:
        pass


class Intake:
    """Takes messages of `subscriptions` on its own thread: on_message(index, msg) for each.

    The subscriptions must be in a `NotForExecutors` group. on_message must not block (it
    enqueues); an exception in it is passed to on_error(exc) and the thread goes on.
    `stop()` before the subscriptions are destroyed.
    """

    def __init__(self, context: Any, subscriptions: Sequence[Any],
                 on_message: Callable[[int, Any], None],
                 on_error: Callable[[Exception], None]) -> None:
        self._context = context
        self._subs = list(subscriptions)
        self._on_message = on_message
        self._on_error = on_error
        self._stopping = False
        self._wake = GuardCondition(None, None, context=context)
        self._thread = threading.Thread(target=self._run, name='point_gn_intake', daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> bool:
        """Wake and join the thread; True when it has ended."""
        self._stopping = True
        try:
            self._wake.trigger()
        except Exception:  # noqa: BLE001 - context already shut down: the wait times out
            pass
        self._thread.join(timeout_s)
        ended = not self._thread.is_alive()
        if ended:
            self._wake.destroy()
        return ended

    def _run(self) -> None:
        name_os_thread()
        subs = self._subs
        with ExitStack() as held:
            # Held: a subscription is not freed while this thread can still wait on it.
            for sub in subs:
                held.enter_context(sub.handle)
            held.enter_context(self._wake.handle)
            wait_set = _rclpy.WaitSet(len(subs), 1, 0, 0, 0, 0, self._context.handle)
            while not self._stopping and self._context.ok():
                wait_set.clear_entities()
                for sub in subs:
                    wait_set.add_subscription(sub.handle)
                wait_set.add_guard_condition(self._wake.handle)
                try:
                    wait_set.wait(WAIT_TIMEOUT_NS)
                except Exception as exc:  # noqa: BLE001 - e.g. the context went away
                    if self._stopping or not self._context.ok():
                        return
                    self._on_error(exc)
                    time.sleep(0.1)       # a failing wait must not spin a core
                    continue
                ready = wait_set.get_ready_entities('subscription')
                for index, sub in enumerate(subs):
                    if sub.handle.pointer in ready:
                        self._drain(index, sub)

    def _drain(self, index: int, sub: Any) -> None:
        """Take every message waiting on one subscription."""
        while not self._stopping:
            try:
                taken = sub.handle.take_message(sub.msg_type, sub.raw)
            except Exception as exc:  # noqa: BLE001 - e.g. a message that cannot be read
                self._on_error(exc)
                return
            if taken is None:
                return
            try:
                self._on_message(index, taken[0])
            except Exception as exc:  # noqa: BLE001 - the intake outlives a bad callback
                self._on_error(exc)
