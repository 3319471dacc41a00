"""Accuracy figures, per-class tables and confusion-matrix plots."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def confusion_matrix(true: np.ndarray, pred: np.ndarray, num_classes: int) -> np.ndarray:
    """true, pred: (N,) int (pred -1 = unknown, kept in an extra last column) -> (C, C+1)."""
    cm = np.zeros((num_classes, num_classes + 1), dtype=np.int64)
    np.add.at(cm, (np.asarray(true), np.where(np.asarray(pred) < 0, num_classes, pred)), 1)
    return cm


def accuracy_report(true: np.ndarray, pred: np.ndarray, class_names: list[str]) -> dict[str, Any]:
    """Overall and mean-class accuracy (fractions) and a per-class table."""
    true, pred = np.asarray(true, dtype=np.int64), np.asarray(pred, dtype=np.int64)
    cm = confusion_matrix(true, pred, len(class_names))
    support = cm.sum(axis=1)
    present = support > 0
    per_class_acc = np.divide(np.diag(cm[:, :-1]), support, out=np.zeros(len(support)),
                              where=present)
    return {
        'count': int(len(true)),
        'accuracy': float((true == pred).mean()) if len(true) else 0.0,
        'mean_class_accuracy': float(per_class_acc[present].mean()) if present.any() else 0.0,
        'unknown': int((pred < 0).sum()),
        'per_class': [{'class': n, 'support': int(s), 'accuracy': float(a)}
                      for n, s, a, p in zip(class_names, support, per_class_acc, present,
                                            strict=True) if p],
        'confusion': cm.tolist(),
    }


def format_report(report: dict[str, Any], title: str = '') -> str:
    """Human-readable Markdown: headline figures then the per-class table."""
    lines = [f'## {title}' if title else '',
             f'- objects: {report["count"]}',
             f'- overall accuracy: {100 * report["accuracy"]:.2f} %',
             f'- mean class accuracy: {100 * report["mean_class_accuracy"]:.2f} %']
    if report.get('unknown'):
        lines.append(f'- answered unknown: {report["unknown"]}')
    lines += ['', '| class | objects | accuracy |', '|---|---:|---:|']
    lines += [f'| {r["class"]} | {r["support"]} | {100 * r["accuracy"]:.1f} % |'
              for r in report['per_class']]
    return '\n'.join(line for line in lines if line is not None).strip() + '\n'


def plot_confusion(cm: np.ndarray, class_names: list[str], path: str | Path,
                   title: str = 'Confusion matrix') -> Path:
    """Row-normalised confusion matrix as a PNG; cm (C, C) or (C, C+1) with unknowns."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    cm = np.asarray(cm, dtype=np.float64)
    cols = list(class_names) + (['unknown'] if cm.shape[1] == len(class_names) + 1 else [])
    norm = cm / np.maximum(cm.sum(axis=1, keepdims=True), 1)
    size = max(6.0, 0.28 * len(cols))
    fig, ax = plt.subplots(figsize=(size, size * 0.9))
    im = ax.imshow(norm, cmap='Blues', vmin=0, vmax=1)
    ax.set_xticks(range(len(cols)), cols, rotation=90, fontsize=7)
    ax.set_yticks(range(len(class_names)), class_names, fontsize=7)
    ax.set_xlabel('predicted')
    ax.set_ylabel('true')
    ax.set_title(title)
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
