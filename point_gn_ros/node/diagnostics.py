"""The node's /diagnostics content: one DiagnosticArray from a stats snapshot (no rclpy).

Statuses: `<node>: pipeline` (counters, rates, latencies), `<node>: input <topic>` per input
topic, `<node>: bank`. Levels compare with the previous report: WARN when messages were
dropped or rejected since then, ERROR when messages failed (decode, classify or publish
raised) or the worker died. The counters satisfy, in every report,
`received = answered + dropped + rejected + failed + in_flight` (see node/stats.py).
"""

from __future__ import annotations

from collections.abc import Sequence
import math
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from point_gn_ros.node.params import Settings
from point_gn_ros.node.stats import StatsSnapshot


class DiagnosticsBuilder:
    """Builds each report; remembers the previous one's totals to detect new problems."""

    def __init__(self) -> None:
        self._last: tuple[int, int, int] = (0, 0, 0)   # drops, rejects, failed messages

    def build(self, name: str, snap: StatsSnapshot, settings: Settings,
              topic_names: Sequence[str], worker_alive: bool, bank: Any,
              unknown_threshold: float | None, input_problems: Sequence[str] = (),
              state: str = 'active', input_values: Sequence[dict[str, Any]] = (),
              query_path: dict[str, str] | None = None) -> DiagnosticArray:
        """DiagnosticArray (header unset) for node `name` (fully qualified).

        input_problems: per topic '' or why it is suspicious (no publisher / no message for
        a while, publishers with incompatible QoS: WARN); state: the lifecycle state, reported
        as is; input_values: per topic extra key-values (its QoS: node/input_qos.py).
        """
        input_problems = list(input_problems) or [''] * len(topic_names)
        s = settings
        drops, rejects = sum(snap.dropped), sum(snap.rejected.values())
        failed = sum(snap.failed.values())
        new_drops = drops - self._last[0]
        new_rejects = rejects - self._last[1]
        new_failed = failed - self._last[2]
        self._last = (drops, rejects, failed)

        level, message = DiagnosticStatus.OK, 'ok'
        problems = []
        if new_drops:
            problems.append(f'{new_drops} message(s) dropped (queue full)')
        if new_rejects:
            problems.append(f'{new_rejects} message(s) rejected')
        problems += [p for p in input_problems if p]
        if problems:
            level, message = DiagnosticStatus.WARN, '; '.join(problems)
        if not worker_alive:
            level, message = DiagnosticStatus.ERROR, 'worker thread stopped'
        elif new_failed:
            level, message = (DiagnosticStatus.ERROR,
                              f'{new_failed} message(s) failed; last: {snap.last_error}')

        pipeline = DiagnosticStatus(level=level, name=f'{name}: pipeline', message=message,
                                    hardware_id=s.device)
        pipeline.values = key_values({
            'state': state,
            'input_rate_hz': f'{snap.input_rate_hz:.2f}',
            'processed_rate_hz': f'{snap.processed_rate_hz:.2f}',
            'objects_rate_hz': f'{snap.objects_rate_hz:.2f}',
            # The identity: received = answered + dropped + rejected + failed + in_flight.
            'received': sum(snap.received),
            'answered': snap.answered,
            'processed': snap.answered,          # the former name of 'answered'
            'in_flight': snap.in_flight,
            'objects': snap.objects,
            'latency_receipt_p50_ms': fmt_ms(snap.latency_receipt_ms[0]),
            'latency_receipt_p99_ms': fmt_ms(snap.latency_receipt_ms[1]),
            'latency_stamp_p50_ms': fmt_ms(snap.latency_stamp_ms[0]),
            'latency_stamp_p99_ms': fmt_ms(snap.latency_stamp_ms[1]),
            'latency_samples': snap.latency_samples,
            'mean_batch_objects': f'{snap.batch_size_mean:.1f}',
            'queue_depth': sum(snap.queue_depths),
            'queue_capacity': s.queue_size * len(s.input_topics),
            'dropped': drops,
            'rejected': rejects,
            **{f'rejected.{reason}': n for reason, n in sorted(snap.rejected.items())},
            'failed': failed,
            **{f'failed.{stage}': n for stage, n in sorted(snap.failed.items())},
            'skipped_segments': snap.skipped_segments,
            'objects_truncated': snap.objects_truncated,
            'errors': snap.errors,
            'numeric_warnings': snap.numeric_warnings,
            'incompatible_qos_events': sum(int(v.get('incompatible_qos_events', 0))
                                           for v in input_values),
        })
        statuses = [pipeline]
        for i, topic in enumerate(topic_names):
            full = snap.queue_depths[i] >= s.queue_size
            trouble = '; '.join(p for p in (input_problems[i], 'queue full' if full else '') if p)
            st = DiagnosticStatus(level=DiagnosticStatus.WARN if trouble else DiagnosticStatus.OK,
                                  name=f'{name}: input {topic}', hardware_id=s.device,
                                  message=trouble or 'ok')
            st.values = key_values({
                'topic_index': i, 'input_rate_hz': f'{snap.per_topic_input_hz[i]:.2f}',
                'received': snap.received[i], 'processed': snap.processed[i],
                'dropped': snap.dropped[i], 'queue_depth': snap.queue_depths[i],
                **(input_values[i] if i < len(input_values) else {})})
            statuses.append(st)
        bank_status = DiagnosticStatus(level=DiagnosticStatus.OK, name=f'{name}: bank',
                                       message=bank.summary(), hardware_id=s.device)
        bank_status.values = key_values({
            'path': str(bank.path), 'entries': len(bank), 'classes': bank.num_classes,
            'single_view_entries': 0 if bank.views is None else len(bank.views),
            'num_points': bank.config.num_points, 'resample': s.resample, 'top_k': s.top_k,
            'unknown_threshold': unknown_threshold or 0.0,
            **{f'query_{k}': v for k, v in (query_path or {}).items()}})
        statuses.append(bank_status)
        return DiagnosticArray(status=statuses)


def fmt_ms(v: float) -> str:
    return 'nan' if math.isnan(v) else f'{v:.1f}'


def key_values(d: dict[str, Any]) -> list[KeyValue]:
    return [KeyValue(key=k, value=str(v)) for k, v in d.items()]
