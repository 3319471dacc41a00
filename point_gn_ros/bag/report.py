"""Replay results -> report dict, JSON, Markdown and PNGs (confusion matrix, latency)."""

from __future__ import annotations

from dataclasses import dataclass, field
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from point_gn_ros.bag.reader import BagContents

PERCENTILES = (50, 90, 99)


@dataclass(frozen=True)
class Answer:
    """The classifier's answer for one object, class index in the *bag's* class list."""

    class_id: int      # -1 = unknown (or a class the bag does not have)
    score: float


@dataclass
class RunResult:
    """What one replay (online or offline) produced."""

    mode: str                                        # offline | lockstep | rate | listen-only
    answers: dict[tuple[int, int], Answer]           # (message index, segment id) -> answer
    answered: set[int]                               # message indices with an answer
    sent: int                                        # messages sent (listen-only: in the bag)
    wall_s: float                                    # first send -> last answer
    latency_s: dict[int, float] = field(default_factory=dict)   # message index -> seconds
    dropped: int | None = None                       # node-reported drops (diagnostics)
    node: str | None = None
    info: dict[str, Any] = field(default_factory=dict)


def map_class_ids(source_names: list[str], bag_names: list[str]) -> np.ndarray:
    """Lookup table source class id -> bag class id (-1 when the bag lacks that class)."""
    where = {name: i for i, name in enumerate(bag_names)}
    return np.array([where.get(name, -1) for name in source_names], dtype=np.int64)


def _percentiles(values_ms: np.ndarray) -> dict[str, float | None]:
    if values_ms.size == 0:
        return {f'p{q}': None for q in PERCENTILES} | {'mean': None, 'max': None}
    out: dict[str, float | None] = {f'p{q}': float(np.percentile(values_ms, q))
                                    for q in PERCENTILES}
    return out | {'mean': float(values_ms.mean()), 'max': float(values_ms.max())}


def build_report(contents: BagContents, result: RunResult) -> dict[str, Any]:
    """Accuracy over answered objects, delivery counts, latency and throughput."""
    from point_gn_ros.evaluation.metrics import accuracy_report

    sent_msgs = contents.messages[:result.sent]
    rows = []
    for m in sent_msgs:
        for seg, gt in m.gt.items():
            ans = result.answers.get((m.index, seg))
            if ans is not None:
                rows.append((m.index, m.stamp_ns, seg, gt, ans.class_id, ans.score))
    true = np.array([r[3] for r in rows], dtype=np.int64)
    pred = np.array([r[4] for r in rows], dtype=np.int64)
    acc = accuracy_report(true, pred, contents.class_names)
    objects_sent = sum(len(m.gt) for m in sent_msgs)
    answered = len(result.answered)
    lat_ms = np.array([result.latency_s[i] for i in sorted(result.latency_s)],
                      dtype=np.float64) * 1e3   # in message order
    dropped = result.dropped
    dropped_source = 'node diagnostics'
    if dropped is None:
        dropped, dropped_source = result.sent - answered, 'unanswered'
    wall = max(result.wall_s, 1e-9)
    report: dict[str, Any] = {
        'mode': result.mode,
        'bag': str(contents.path),
        'storage': contents.storage,
        'topic': contents.topic,
        'node': result.node,
        'classes': len(contents.class_names),
        'recorded_rate_hz': contents.rate_hz,
        'sent': result.sent,
        'answered': answered,
        'unanswered': result.sent - answered,
        'dropped': int(dropped),
        'dropped_source': dropped_source,
        'objects_sent': objects_sent,
        'objects_answered': len(rows),
        'accuracy': acc['accuracy'],
        'accuracy_counting_unanswered_as_wrong':
            float((true == pred).sum() / objects_sent) if objects_sent else 0.0,
        'mean_class_accuracy': acc['mean_class_accuracy'],
        'answered_unknown': acc['unknown'],
        'latency_ms': _percentiles(lat_ms),
        'latency_values_ms': [round(float(v), 3) for v in lat_ms],
        'wall_s': result.wall_s,
        'throughput_msgs_per_s': answered / wall if answered else 0.0,
        'throughput_objects_per_s': len(rows) / wall if rows else 0.0,
        'per_class': acc['per_class'],
        'confusion': acc['confusion'],
        'info': result.info,
        # One row per answered object: message index, stamp (ns), segment, truth, answer, score.
        'predictions': [list(r) for r in rows],
    }
    return report


def format_markdown(report: dict[str, Any], class_names: list[str]) -> str:
    """Headline table (delivery, latency, throughput) followed by the accuracy tables."""
    from point_gn_ros.evaluation.metrics import format_report

    lat = report['latency_ms']

    def ms(v: float | None) -> str:
        return 'n/a' if v is None else f'{v:.1f}'

    lines = [
        f'# Replay report ({report["mode"]})', '',
        f'- bag: `{report["bag"]}` ({report["storage"]}), topic `{report["topic"]}`, '
        f'{report["classes"]} classes, recorded at {report["recorded_rate_hz"]:.1f} Hz',
        f'- node: `{report["node"] or "none (offline)"}`', '',
        '| figure | value |', '|---|---:|',
        f'| messages sent | {report["sent"]} |',
        f'| messages answered | {report["answered"]} |',
        f'| messages unanswered | {report["unanswered"]} |',
        f'| dropped ({report["dropped_source"]}) | {report["dropped"]} |',
        f'| objects sent / answered | {report["objects_sent"]} / '
        f'{report["objects_answered"]} |',
        f'| accuracy (answered objects) | {100 * report["accuracy"]:.2f} % |',
        f'| accuracy (unanswered = wrong) | '
        f'{100 * report["accuracy_counting_unanswered_as_wrong"]:.2f} % |',
        f'| mean class accuracy | {100 * report["mean_class_accuracy"]:.2f} % |',
        f'| latency p50 / p90 / p99 / max (ms) | {ms(lat["p50"])} / {ms(lat["p90"])} / '
        f'{ms(lat["p99"])} / {ms(lat["max"])} |',
        f'| throughput (messages/s, objects/s) | {report["throughput_msgs_per_s"]:.1f}, '
        f'{report["throughput_objects_per_s"]:.1f} |',
        f'| wall time (s) | {report["wall_s"]:.1f} |', '']
    acc = {'count': report['objects_answered'], 'accuracy': report['accuracy'],
           'mean_class_accuracy': report['mean_class_accuracy'],
           'unknown': report['answered_unknown'], 'per_class': report['per_class']}
    return '\n'.join(lines) + '\n' + format_report(acc, 'Accuracy on answered objects')


def write_outputs(report: dict[str, Any], class_names: list[str], *,
                  json_path: str | os.PathLike[str] | None = None,
                  markdown_path: str | os.PathLike[str] | None = None,
                  png_prefix: str | None = None) -> list[Path]:
    """Write whichever outputs were asked for; returns the files written."""
    written: list[Path] = []
    if json_path:
        p = Path(json_path)
        p.write_text(json.dumps(report, indent=1) + '\n')
        written.append(p)
    if markdown_path:
        p = Path(markdown_path)
        p.write_text(format_markdown(report, class_names))
        written.append(p)
    if png_prefix:
        written += write_pngs(report, class_names, png_prefix)
    return written


def write_pngs(report: dict[str, Any], class_names: list[str], prefix: str) -> list[Path]:
    """<prefix>_confusion.png and, when latencies were measured, <prefix>_latency.png."""
    from point_gn_ros.evaluation.metrics import plot_confusion

    out = [plot_confusion(np.asarray(report['confusion']), class_names,
                          f'{prefix}_confusion.png',
                          f'{report["mode"]} replay: {100 * report["accuracy"]:.2f} % '
                          f'({report["objects_answered"]} objects)')]
    lat = report.get('latency_values_ms') or []
    if lat:
        import matplotlib
        matplotlib.use('Agg')
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 3.5))
        ax.hist(lat, bins=min(60, max(10, len(lat) // 10)), color='tab:blue')
        for q, style in zip(PERCENTILES, (':', '--', '-.'), strict=True):
            v = report['latency_ms'][f'p{q}']
            ax.axvline(v, color='k', linestyle=style, label=f'p{q} {v:.1f} ms')
        ax.set_xlabel('publish -> answer (ms)')
        ax.set_ylabel('messages')
        ax.set_title(f'{report["mode"]} replay latency ({len(lat)} messages)')
        ax.legend()
        fig.tight_layout()
        path = Path(f'{prefix}_latency.png')
        fig.savefig(path, dpi=110)
        plt.close(fig)
        out.append(path)
    return out
