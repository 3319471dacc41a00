"""ClassifierNode's /diagnostics report: its own statuses plus those of its extensions.

A mixin of ClassifierNode (node/classifier_node.py); node/diagnostics.py builds the
statuses, this gathers what they report on and publishes them (the node's 1 s timer).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

__all__ = ['DiagnosticsMixin']


class DiagnosticsMixin:
    """ClassifierNode's diagnostics methods (it provides _stats, _queue, _pub_diag, ...)."""

    def add_diagnostic_source(self, source: Callable[[str], Any]) -> None:
        """source(node_name) -> diagnostic_msgs/DiagnosticStatus, added to every report."""
        self._diagnostic_sources.append(source)

    def _input_problems(self) -> list[str]:
        """Per input topic: '' or why it is suspicious.

        No publisher / no message for N s, or publishers whose QoS it cannot match.
        """
        if not self._active:
            return []
        # Every publisher on the graph, matched or not: one with incompatible QoS is a
        # publisher, reported as such, never as "no publisher".
        topics = self._pipeline.topic_names
        silent = self._watchdog.problems(topics, [self.count_publishers(t) for t in topics],
                                         self.settings.input_timeout_s)
        out = []
        for i, problem in enumerate(silent):
            qos = self._input_qos.problem(i)
            out.append(qos if qos and (not problem or problem.startswith('no message'))
                       else problem)
        return out

    def _input_values(self) -> list[dict[str, Any]]:
        if not self._active or self._input_qos is None:
            return []
        return [self._input_qos.values(i) for i in range(len(self._subs))]

    def _publish_diagnostics(self) -> None:
        if self._pipeline is None:
            return
        snap = self._stats.snapshot(self._queue.depths())
        arr = self._diagnostics.build(
            self.get_fully_qualified_name(), snap, self.settings, self._pipeline.topic_names,
            self._worker is not None and self._worker.is_alive(), self.recognizer.bank,
            self.recognizer.classifier.unknown_threshold, self._input_problems(),
            'active' if self._active else 'inactive', self._input_values(),
            self.recognizer.classifier.path)
        arr.status += [source(self.get_fully_qualified_name())
                       for source in self._diagnostic_sources]
        arr.header.stamp = self.get_clock().now().to_msg()
        self._pub_diag.publish(arr)
